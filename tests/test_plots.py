"""Plots: files written and non-empty, one line (or marker set) per ball with the right
number of points, and the plotted numbers against independent truths (tread heights for
the impact markers; the restitution law for the energy steps)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import estim
from estim.fitting._fit import BallFit, FitResult

SEED_BALLS = ("bocce", "golf", "pingpong")
IMPACTS = {"bocce": 9, "golf": 6, "pingpong": 4}  # the seed scene (README)
TREAD_TOPS = (1.4, 1.2, 1.0, 0.8, 0.6)
G = 9.81


def is_png(path) -> bool:
    data = path.read_bytes()
    return data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def lines_by_label(ax) -> dict:
    return {line.get_label(): line for line in ax.get_lines()}


@pytest.fixture(scope="module")
def seed(stairs, kit):
    """The seed simulation (first three balls of the suite's padded batch), its release
    states and the ball radii."""
    e, mu, r, pos, vel = kit.seed_arrays(stairs)
    traj = kit.run(stairs, e, mu, r, pos, vel, kit.SEED_T_END)
    kit_complete = np.asarray(traj.complete[:3])
    assert kit_complete.all()
    return traj[:3], dict(e=e, mu=mu, r=r, pos=pos, vel=vel)


def test_heights_markers_at_the_impacts(seed, tmp_path):
    traj, s = seed
    path = tmp_path / "heights.png"
    fig = estim.plot_heights(traj, SEED_BALLS, path)
    assert is_png(path)
    ax = fig.axes[0]
    lines = lines_by_label(ax)
    assert len(ax.get_lines()) == 2 * len(SEED_BALLS)  # a trace and its impacts per ball
    for i, b in enumerate(SEED_BALLS):
        trace = lines[f"{b} ({IMPACTS[b]} bounces)"]
        assert len(trace.get_xdata()) == len(np.asarray(traj.ts))
        marks = lines[f"{b} impacts"]
        z = np.asarray(marks.get_ydata())
        assert len(z) == IMPACTS[b]
        # Every impact is on a tread top: the centre is one radius above it.
        gap = np.min(np.abs(z[:, None] - s["r"][i] - np.array(TREAD_TOPS)[None]), axis=1)
        assert gap.max() < 1e-9
        assert np.all(np.diff(marks.get_xdata()) > 0)
    assert ax.get_xlabel() == "time t [s]" and ax.get_ylabel() == "centre height z [m]"
    assert ax.get_title() and ax.get_legend() is not None


def test_heights_with_measured_samples(seed):
    traj, _ = seed
    t = np.linspace(0, 2, 11)
    pos = np.zeros((11, 3))
    pos[3, 2] = np.nan  # a lost sample is not drawn
    fig = estim.plot_heights(traj, SEED_BALLS, data={"golf": (t, pos)})
    measured = lines_by_label(fig.axes[0])["golf measured"]
    assert len(measured.get_xdata()) == 10


def test_energy_steps_follow_the_restitution_law(seed, tmp_path):
    """E/E0 with E = g z + |v|^2/2: E0 from the release state, and at each impact on a
    tread the reset vz -> -e vz, (vx, vy) -> mu_t (vx, vy) takes away
    ((1 - e^2) vz^2 + (1 - mu_t^2)(vx^2 + vy^2)) / 2; in flight nothing changes."""
    traj, s = seed
    path = tmp_path / "energy.png"
    fig = estim.plot_energy(traj, SEED_BALLS, path, gravity=G)
    assert is_png(path)
    ax = fig.axes[0]
    lines = lines_by_label(ax)
    assert len(ax.get_lines()) == 2 * len(SEED_BALLS)
    ts = np.asarray(traj.ts)
    for i, b in enumerate(SEED_BALLS):
        e0 = G * s["pos"][i, 2] + 0.5 * np.sum(s["vel"][i] ** 2)
        c = int(traj.events.count[i])
        t_ev = np.asarray(traj.events.t[i, :c])
        pre = np.asarray(traj.events.velocity_pre[i, :c])
        loss = 0.5 * ((1 - s["e"][i] ** 2) * pre[:, 2] ** 2
                      + (1 - s["mu"][i] ** 2) * (pre[:, 0] ** 2 + pre[:, 1] ** 2))
        line = lines[b]
        x, y = np.asarray(line.get_xdata()), np.asarray(line.get_ydata())
        on_sample = np.isin(x, ts) & ~np.isin(x, t_ev)
        want = (e0 - np.array([loss[t_ev < t].sum() for t in x[on_sample]])) / e0
        np.testing.assert_allclose(y[on_sample], want, rtol=0, atol=1e-9)
        assert y[0] == pytest.approx(1.0, abs=1e-12)
        marks = lines[f"{b} after each impact"]
        assert len(marks.get_xdata()) == IMPACTS[b]
        np.testing.assert_allclose(marks.get_ydata(), (e0 - np.cumsum(loss)) / e0, atol=1e-9)
    # The default g is the one the trajectory was solved with.
    again = estim.plot_energy(traj, SEED_BALLS)
    np.testing.assert_array_equal(lines_by_label(again.axes[0])["golf"].get_ydata(),
                                  lines["golf"].get_ydata())


def fake_result(n=50, outliers=(10, 30), lost=(5, 6, 7), with_y=False):
    """A FitResult for two balls, built by hand: known samples, outliers and gaps (and,
    ``with_y``, a y coordinate: the balls move along y)."""
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 1.0, n)
    data, balls = {}, {}
    for k, b in enumerate(("golf", "pingpong")):
        model = np.stack([0.1 + t, np.zeros(n), 1.5 - 0.5 * G * t**2 + 0.1 * k], 1)
        if with_y:
            model[:, [0, 1]] = model[:, [1, 0]]
        meas = model + rng.normal(0, 0.002, model.shape)
        if not with_y:
            meas[:, 1] = np.nan
        if b == "golf":
            meas[list(outliers), 2] += 0.05
            meas[list(lost), 2] = np.nan
        data[b] = (t, meas)
        res = np.where(np.isfinite(meas), model - meas, 0.0)
        balls[b] = BallFit(
            ball=b, values={"e": 0.7, "mu_t": 0.95, "vx0": 1.0}, stderr={}, names=("e",),
            correlation=np.eye(1), rms_m=0.002, noise_m=0.002, n_obs=n, n_outliers=0,
            n_bounces=0, converged=True, at_noise_floor=True,
            loss_history=np.geomspace(100.0, 1.0, 12 + 3 * k), model_t=t, model_position=model,
            residuals=res,
        )
    return data, FitResult(balls)


def test_fit_residual_and_loss_plots(tmp_path):
    data, result = fake_result()
    fig = estim.plot_fit(data, result, tmp_path / "fit.png")
    z_ax, x_ax = fig.axes
    z = lines_by_label(z_ax)
    assert len(z["golf measured"].get_xdata()) == 50 - 2 - 3  # no outliers, no gaps
    assert len(z["outliers (robust loss)"].get_xdata()) == 2
    np.testing.assert_array_equal(z["outliers (robust loss)"].get_xdata(), data["golf"][0][[10, 30]])
    assert len(z["pingpong measured"].get_xdata()) == 50
    assert len(z["golf fit e=0.700"].get_xdata()) == 50
    assert len(x_ax.get_lines()) == 4  # measured and fitted x per ball
    assert z_ax.get_ylabel() == "z [m]" and x_ax.get_xlabel() == "t [s]"

    fig = estim.plot_residuals(data, result, tmp_path / "residuals.png")
    assert len(fig.axes) == 2
    for ax, b in zip(fig.axes, ("golf", "pingpong"), strict=True):
        lines = lines_by_label(ax)
        assert len(lines["x"].get_xdata()) == 50
        assert len(lines["z"].get_xdata()) == (47 if b == "golf" else 50)
        assert "[mm]" in ax.get_ylabel()

    fig = estim.plot_loss_history(result, tmp_path / "loss.png")
    lines = lines_by_label(fig.axes[0])
    assert len(lines["golf"].get_xdata()) == 12 and len(lines["pingpong"].get_xdata()) == 15
    for name in ("fit.png", "residuals.png", "loss.png"):
        assert is_png(tmp_path / name)


def test_fit_plots_of_3d_tracks_show_y():
    """Tracks with y (a ball thrown along y) get a y panel beside z and x: the measured y
    and the fitted model's y (the fit's own solution, so every fitted parameter)."""
    data, result = fake_result(with_y=True)
    fig = estim.plot_fit(data, result)
    z_ax, x_ax, y_ax = fig.axes
    assert y_ax.get_ylabel() == "y [m]" and y_ax.get_xlabel() == "t [s]" and x_ax.get_xlabel() == ""
    for line, b in zip(y_ax.get_lines()[1::2], ("golf", "pingpong"), strict=True):  # measured, model per ball
        np.testing.assert_array_equal(line.get_ydata(), result.balls[b].model_position[:, 1])
    np.testing.assert_allclose(y_ax.get_lines()[1].get_ydata(), 0.1 + data["golf"][0])  # along y
    fig = estim.plot_residuals(data, result)
    for ax in fig.axes:
        assert {"x", "y", "z"} <= set(lines_by_label(ax))
    # and from above: y against x, measured and model per ball
    (ax,) = estim.plot_from_above(data, result).axes
    lines = lines_by_label(ax)
    assert ax.get_xlabel() == "x [m]" and ax.get_ylabel() == "y [m]"
    for b in ("golf", "pingpong"):
        np.testing.assert_array_equal(lines[f"{b} fit"].get_ydata(), result.balls[b].model_position[:, 1])
        np.testing.assert_array_equal(lines[f"{b} fit"].get_xdata(), result.balls[b].model_position[:, 0])
    np.testing.assert_allclose(lines["golf measured"].get_ydata(), 0.1 + data["golf"][0], atol=0.01)


def test_demo_writes_heights_and_energy(tmp_path):
    from estim.app._demo import run_demo

    summary = run_demo(tmp_path)
    for name in ("heights.png", "energy.png"):
        assert is_png(tmp_path / name)
        assert str(tmp_path / name) in summary["files"]
    assert math.isfinite(summary["balls"][0]["final_x"])
