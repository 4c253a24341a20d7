"""Fits of 3-D table-tennis shots under the friction law (issue 23, fitting half): the
known parameters of synthetic shots come back (e, mu, the spin across the flight), and
``estim fit --scene data/scenes/table_tennis.xml`` fits a shot with its defaults and writes
the release state and the fitted positions into its JSON.

Each shot is ``estim.simulate`` on the bundled table-tennis scene (drag, Magnus, the
friction law at the bounce), 180 Hz, 2 mm Gaussian noise per coordinate. The batch of four
shots compiles one fit program; the command line (one shot) another.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from conftest import ROOT

import estim
from estim.app._cli import main
from estim.fitting import _registry as registry
from estim.fitting._missing_physics import EXPLAINS

TABLE = ROOT / "data" / "scenes" / "table_tennis.xml"
HZ, NOISE, T_END = 180.0, 0.002, 0.65
# name: (e, mu, release position, velocity, spin): drives with topspin and sidespin, a
# push with backspin, a flat hit; each bounces once on the far half of the table and
# slides through its bounce (where a ball grips, mu only bounds the friction, and the data
# cannot tell it).
SHOTS = {
    "topspin": (0.90, 0.12, (0.2, -1.6, 0.2), (-0.3, 8.0, 2.0), (-150.0, 10.0, 20.0)),
    "backspin": (0.86, 0.25, (-0.3, -1.5, 0.25), (0.3, 5.0, 1.2), (120.0, -15.0, 0.0)),
    "sidespin": (0.88, 0.15, (0.5, -1.7, 0.3), (-0.8, 7.0, 1.5), (-40.0, 30.0, 90.0)),
    "flat": (0.92, 0.30, (0.0, -1.4, 0.15), (0.2, 6.5, 1.8), (-20.0, 0.0, 0.0)),
}


def shot(scene, name, rng):
    e, mu, position, velocity, spin = SHOTS[name]
    p = estim.Params.for_ball(scene, "pingpong", e=e, mu_t=1.0, mu=mu, position=position, velocity=velocity,
                              spin=spin)
    t = np.arange(0.0, T_END, 1 / HZ)
    traj = estim.simulate(scene, p, T_END, ts=t)
    impacts = np.asarray(traj.events.t)[np.asarray(traj.events.kind) == 0]
    assert impacts.size and impacts[0] < T_END - 0.1, name  # one bounce, with a flight after it
    return t, np.asarray(traj.position) + rng.normal(0.0, NOISE, (t.size, 3))


def across(spin, velocity):
    """The spin across the velocity: the part a flight's Magnus curve shows."""
    v = np.asarray(velocity, dtype=np.float64)
    return np.asarray(spin) - (np.asarray(spin) @ v) / (v @ v) * v


@pytest.mark.slow
def test_fit_recovers_the_shots_with_spin():
    """e within 0.01, mu within 0.03, the spin across the release velocity within 10% and
    the rms within 10% of the noise, fitted with the scene's defaults (e, mu, the drag
    coefficient, which the scene gives priors, release position, velocity and spin) from
    starts read off the data."""
    scene = estim.load_scene(TABLE)
    rng = np.random.default_rng(7)
    data = {name: shot(scene, name, rng) for name in SHOTS}
    result = estim.fit(scene, data, balls={name: "pingpong" for name in SHOTS})
    for name, (e, mu, _, velocity, spin) in SHOTS.items():
        bf = result.balls[name]
        assert bf.names == ("e", "mu", "drag_coefficient", "x0", "y0", "z0", "vx0", "vy0", "vz0",
                            "spin_x", "spin_y", "spin_z")
        assert "mu_t" not in bf.values and bf.n_bounces == 1, name
        assert bf.values["e"] == pytest.approx(e, abs=0.01), name
        assert bf.values["mu"] == pytest.approx(mu, abs=0.03), name
        fitted = np.array([bf.values[c] for c in ("spin_x", "spin_y", "spin_z")])
        truth = across(spin, velocity)
        assert np.linalg.norm(across(fitted, velocity) - truth) <= 0.1 * np.linalg.norm(truth), (name, fitted)
        # (The rms of n residuals after fitting p parameters estimates the noise times
        # sqrt(1 - p / n).)
        n = np.isfinite(data[name][1]).sum()
        assert bf.rms_m * np.sqrt(n / (n - len(bf.names))) == pytest.approx(NOISE, rel=0.1), name


def test_command_line_fits_a_shot_on_the_table_tennis_scene(tmp_path, capsys):
    """``estim fit TRACK.csv --scene data/scenes/table_tennis.xml --json``: a `t,ball,x,y,z`
    track of one shot, the scene's defaults; the JSON gives e and mu (no mu_t: the
    friction law does not read it), the release state as vectors (t, position, velocity,
    spin) that match the values, and the model's positions at the track's times, which
    lie within a few noise levels of the noise-free shot. With ``--effects``: the effects
    of the model, each in noise levels, and a 0.4 s shot at 4-7 m/s through air shows its
    drag by many noise levels."""
    scene = estim.load_scene(TABLE)
    t, pos = shot(scene, "topspin", np.random.default_rng(11))
    csv = tmp_path / "shot.csv"
    csv.write_text("t,ball,x,y,z\n" + "".join(f"{a:.6f},pingpong,{x:.5f},{y:.5f},{z:.5f}\n"
                                              for a, (x, y, z) in zip(t, pos, strict=True)))
    code = main(["fit", str(csv), "--scene", str(TABLE), "--json", "--effects"])
    ball = json.loads(capsys.readouterr().out)["balls"]["pingpong"]
    effects = {m["effect"]: m for m in ball["effects"]}
    assert list(effects) == ["quadratic drag", "linear drag", "Magnus", "spin at the bounce", "friction at the bounce"]
    assert effects["quadratic drag"]["verdict"] == "measured"
    for m in effects.values():
        assert m["noise_levels"] == pytest.approx(m["max_deviation_mm"] * 1e-3 / ball["noise_m"], rel=1e-9)
    assert code == 0 and ball["converged"] and ball["at_noise_floor"]
    assert "mu" in ball and "mu_t" not in ball and ball["e"] == pytest.approx(0.90, abs=0.01)
    release = ball["release"]
    assert release["t"] == ball["t0"] == 0.0
    assert release["position"] == [ball["x0"], ball["y0"], ball["z0"]]
    assert release["velocity"] == [ball["vx0"], ball["vy0"], ball["vz0"]]
    assert release["spin"] == [ball["spin_x"], ball["spin_y"], ball["spin_z"]]
    np.testing.assert_allclose(ball["fitted"]["t"], t, atol=1e-6)
    e, mu, position, velocity, spin = SHOTS["topspin"]
    exact = estim.simulate(scene, estim.Params.for_ball(scene, "pingpong", e=e, mu_t=1.0, mu=mu, position=position,
                                                        velocity=velocity, spin=spin), T_END, ts=t)
    gap = np.linalg.norm(np.asarray(ball["fitted"]["position"]) - np.asarray(exact.position), axis=1)
    assert np.max(gap) < 2 * NOISE


def mujoco_shot(damping=0.1, noise=0.001):
    """The topspin drive of ``SHOTS`` (lifted to clear MuJoCo's net) in MuJoCo's own physics
    (``docs/scripts/camera_views.py``'s ``mujoco_shot``: the ball's ellipsoid fluid model at
    MuJoCo's default coefficients, drag and Magnus; a frictional contact with the table,
    friction 0.2, ``solref="0.0005 damping"``), sampled at 180 Hz with ``noise`` (m).
    Returns the times, the positions, the release spin and the restitution MuJoCo's
    contact shows (normal speed after over before)."""
    sys.path.insert(0, str(ROOT / "docs" / "scripts"))
    import camera_views

    spin = np.array([-150.0, 10.0, 20.0])
    t = np.arange(0.0, T_END, 1 / HZ)
    pos, e = camera_views.mujoco_shot((0.2, -1.6, 0.2), (-0.3, 8.0, 2.6), spin, t, damping=damping)
    return t, pos + np.random.default_rng(5).normal(0.0, noise, (t.size, 3)), spin, e


@pytest.mark.slow
def test_a_fit_that_holds_the_drag_coefficient_says_to_fit_it():
    """The same MuJoCo shot fitted holding the drag coefficient at the textbook value (0.47;
    MuJoCo's is 1.0) and the lift factor at 1: the fit stays above its noise floor, and its
    report probes the held coefficients and says that a quarter more drag would move the
    ball by many noise levels, and to fit it. The scene's defaults fit both (below)."""
    scene = estim.load_scene(TABLE)
    t, pos, _, _ = mujoco_shot()
    bf = estim.fit(scene, {"pingpong": (t, pos)}, free=("e", "mu", "position", "velocity", "spin")).balls["pingpong"]
    assert not bf.at_noise_floor and bf.values["drag_coefficient"] == 0.47  # held
    drag = next(m for m in bf.missing_physics if m["effect"].startswith("a drag_coefficient"))
    assert drag["effect"] == "a drag_coefficient 25% above the 0.47 held"
    assert drag["explains"] and drag["noise_levels"] >= EXPLAINS
    assert drag["advice_note"] in bf.notes and drag["advice_note"].endswith("fit it (--also drag_coefficient)")
    lift = next(m for m in bf.missing_physics if m["effect"].startswith("a lift_factor"))
    assert lift["explains"] and lift["advice"] == "fit it (--also lift_factor)"


@pytest.mark.slow
def test_fit_follows_mujocos_own_table_tennis_physics():
    """MuJoCo's physics, the independent engine, fitted with the scene's defaults, which fit
    the drag coefficient under the scene's prior (1 mm noise). estim's fitted motion follows
    MuJoCo's to well under 2 mm rms (0.9 mm of noise) and reads MuJoCo's own numbers: the drag
    coefficient of its ellipsoid model's blunt drag, ``C_blunt rho A |v| v`` with
    C_blunt = 0.5 (its first ``fluidcoef``), is C_D = 2 C_blunt = 1.0 in estim's
    ``(1/2) rho C_D A |v| v``; the restitution its contact shows; and the release spin
    across the velocity, within 10%. Where the models differ: MuJoCo's angular drag slows
    the spin in flight (estim holds it), its Magnus and added-mass forces scale as a
    constant ``(C_M - 1/2) rho V`` where estim's lift coefficient saturates with the spin
    ratio (so the fitted lift factor is an average, ``estim.model._air``), and its soft
    friction grips where Coulomb's impulse would still slide (so mu is only bounded:
    docs/pages/contact-model.md)."""
    scene = estim.load_scene(TABLE)
    t, pos, spin, e = mujoco_shot()
    bf = estim.fit(scene, {"pingpong": (t, pos)}).balls["pingpong"]
    assert "drag_coefficient" in bf.names and "lift_factor" not in bf.names
    assert bf.rms_m < 0.002 and bf.n_bounces == 1
    assert bf.values["drag_coefficient"] == pytest.approx(1.0, abs=0.05)
    assert bf.values["e"] == pytest.approx(e, abs=0.02)
    fitted = np.array([bf.values[c] for c in ("spin_x", "spin_y", "spin_z")])
    velocity = (-0.3, 8.0, 2.6)
    assert np.linalg.norm(across(fitted, velocity) - across(spin, velocity)) <= 0.1 * np.linalg.norm(across(spin, velocity))


def test_fit_reads_a_restitution_that_falls_with_impact_speed():
    """A ball dropped on the table bounces at 3.9, 3.0 and 2.5 m/s with e falling by 0.04
    per m/s (``e_slope``; 180 Hz, 2 mm noise, in the scene's air). Fitted with ``e_slope``
    asked for (it is never fitted by default), e at the reference speed comes back within
    0.005 and the slope within three standard errors (about 0.0004 s/m); the rms reaches
    the noise."""
    scene = estim.load_scene(TABLE)
    truth = estim.Params.for_ball(scene, "pingpong", e=0.88, mu_t=0.0, mu=0.2, position=(0.1, -0.6, 0.9),
                                  velocity=(0.2, 0.5, 0.0), e_slope=-0.04)
    t = np.arange(0.0, 1.8, 1 / HZ)
    traj = estim.simulate(scene, truth, 1.8, ts=t)
    assert int(np.sum(np.asarray(traj.events.kind) == 0)) == 3
    data = {"pingpong": (t, np.asarray(traj.position) + np.random.default_rng(3).normal(0.0, NOISE, (t.size, 3)))}
    default = registry.default_free(scene, lateral=True)
    assert "e_slope" not in default
    bf = estim.fit(scene, data, free=default + ("e_slope",)).balls["pingpong"]
    assert bf.values["e"] == pytest.approx(0.88, abs=0.005)
    assert abs(bf.values["e_slope"] + 0.04) < 3 * bf.stderr["e_slope"] < 0.003
    assert bf.rms_m == pytest.approx(NOISE, rel=0.1)
