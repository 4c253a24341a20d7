"""Plots (matplotlib): a fit's tracks, residuals and loss history; a simulation's heights
with its contact events and its mechanical energy.

Every function draws on its own ``matplotlib.figure.Figure`` (no pyplot, so no global
state and no backend is chosen for the caller), saves it when given a path, and returns it,
so a notebook can show it and a test can count its lines.
"""

from __future__ import annotations

import os

import numpy as np
from matplotlib.figure import Figure

from ..fitting._fit import FitResult
from ..forward._trajectory import IMPACT, REST

__all__ = ["COLOURS", "plot_energy", "plot_fit", "plot_from_above", "plot_heights", "plot_loss_history",
           "plot_residuals"]

# One colour per ball, shared by the plots, the side view and the MuJoCo replay. The golf
# ball is drawn dark grey: white would vanish on a white page.
COLOURS = {"bocce": "#8c5a1f", "golf": "#555555", "pingpong": "#f08c1a"}


def _colour(ball: str, i: int) -> str:
    return COLOURS.get(ball, f"C{i}")


def _save(fig: Figure, path) -> Figure:
    if path is not None:
        fig.savefig(os.fspath(path), dpi=110)
    return fig


def _axes_of(data: dict, balls) -> tuple[tuple[int, str], ...]:
    """The coordinates to draw, (index, name): z and x, and y where any track has one (a
    ball thrown along y moves in y, not in x)."""
    has_y = any(np.isfinite(np.asarray(data[b][1], np.float64)[:, 1]).any() for b in balls)
    return ((2, "z"), (0, "x")) + (((1, "y"),) if has_y else ())


def plot_fit(data: dict, result: FitResult, path=None) -> Figure:
    """Measured positions (markers; outliers crossed) and the fitted model (lines), z and
    x, and y where the tracks have it. The model is the fit's own solution at the samples,
    so it carries every fitted parameter (the release state in 3D, drag, spin, ...)."""
    coords = _axes_of(data, result.balls)
    fig = Figure(figsize=(8, 3.2 * len(coords)), layout="tight")
    axes = fig.subplots(len(coords), 1, sharex=True)
    for i, (ball, bf) in enumerate(result.balls.items()):
        t, pos = data[ball]
        c = _colour(ball, i)
        n = len(t)
        out = np.abs(bf.residuals[:n]) > 5 * bf.noise_m
        for ax, (k, name) in zip(axes, coords, strict=True):
            ok = np.isfinite(pos[:, k])
            ax.plot(t[ok & ~out[:, k]], pos[ok & ~out[:, k], k], "o", ms=2.5, color=c, alpha=0.55,
                    label=f"{ball} measured" if k == 2 else None)
            if np.any(ok & out[:, k]):
                ax.plot(t[ok & out[:, k]], pos[ok & out[:, k], k], "x", ms=6, color="red",
                        label="outliers (robust loss)" if (k == 2 and i == 0) else None)
            ax.plot(bf.model_t[:n], bf.model_position[:n, k], "-", lw=1.3, color=c,
                    label=f"{ball} fit e={bf.values['e']:.3f}" if k == 2 else None)
            ax.set_ylabel(f"{name} [m]")
            ax.grid(alpha=0.25)
    axes[0].set_title("Tracked positions and the fitted hybrid model")
    axes[0].legend(fontsize=7, ncol=2)
    axes[-1].set_xlabel("t [s]")
    return _save(fig, path)


def plot_from_above(data: dict, result: FitResult, path=None) -> Figure:
    """The tracks seen from above (y against x, equal scales): measured positions (markers)
    and the fitted model (lines), for tracks with y: a shot's direction of play and its
    curve sideways (sidespin, wind) that the panels over time show only one at a time."""
    fig = Figure(figsize=(6.4, 6.4), layout="tight")
    ax = fig.subplots()
    for i, (ball, bf) in enumerate(result.balls.items()):
        t, pos = data[ball]
        c = _colour(ball, i)
        ok = np.all(np.isfinite(pos[:, :2]), axis=1)
        ax.plot(pos[ok, 0], pos[ok, 1], "o", ms=2.5, color=c, alpha=0.55, label=f"{ball} measured")
        ax.plot(bf.model_position[: len(t), 0], bf.model_position[: len(t), 1], "-", lw=1.3, color=c,
                label=f"{ball} fit")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("Seen from above")
    ax.grid(alpha=0.25)
    ax.legend(fontsize=7)
    return _save(fig, path)


def plot_residuals(data: dict, result: FitResult, path=None) -> Figure:
    """Residuals (model - measured) in x and z (and y where the tracks have it) over time,
    per ball, in millimetres."""
    coords = sorted(_axes_of(data, result.balls))
    fig = Figure(figsize=(8, 2.2 * len(result.balls) + 0.6), layout="tight")
    axes = fig.subplots(len(result.balls), 1, sharex=True, squeeze=False)
    for i, (ball, bf) in enumerate(result.balls.items()):
        ax = axes[i, 0]
        t, _ = data[ball]
        n = len(t)
        r = bf.residuals[:n] * 1e3
        for k, name in coords:
            m = {"x": ".", "y": "x", "z": "+"}[name]
            ok = np.isfinite(data[ball][1][:, k])
            ax.plot(t[ok], r[ok, k], m, ms=3, label=f"{name}")
        band = bf.noise_m * 1e3
        ax.axhspan(-band, band, color="0.85", zorder=0, label="noise level")
        ax.set_ylim(-6 * band, 6 * band)
        ax.set_ylabel(f"{ball}\nresidual [mm]")
        ax.grid(alpha=0.25)
        ax.legend(fontsize=7, loc="upper right", ncol=3)
    axes[0, 0].set_title("Fit residuals, model minus measurement (outliers off scale)")
    axes[-1, 0].set_xlabel("t [s]")
    return _save(fig, path)


def plot_loss_history(result: FitResult, path=None) -> Figure:
    """Robust loss per Levenberg-Marquardt iteration, per ball (log scale)."""
    fig = Figure(figsize=(6.4, 3.6), layout="tight")
    ax = fig.subplots()
    for i, (ball, bf) in enumerate(result.balls.items()):
        h = np.asarray(bf.loss_history, dtype=float)
        h = np.where(np.isfinite(h), h, np.nan)
        ax.semilogy(np.arange(1, len(h) + 1), h, "-o", ms=3, color=_colour(ball, i), label=ball)
    ax.set_xlabel("iteration")
    ax.set_ylabel("robust loss (sum of rho(r/s))")
    ax.set_title("Loss history of the fit (full data window)")
    ax.grid(alpha=0.25, which="both")
    ax.legend(fontsize=8)
    return _save(fig, path)


def _per_ball(traj, balls):
    """Samples and listed events of a Trajectory as numpy arrays with one leading ball axis."""
    names = [balls] if isinstance(balls, str) else list(balls)
    n = len(names)
    ts = np.asarray(traj.ts, np.float64)
    pos = np.asarray(traj.position, np.float64).reshape(n, -1, 3)
    vel = np.asarray(traj.velocity, np.float64).reshape(n, -1, 3)
    ev = traj.events
    count = np.asarray(ev.count).reshape(n)
    m = np.asarray(ev.t).shape[-1]
    events = []
    for i in range(n):
        c = int(count[i])
        events.append({
            "t": np.asarray(ev.t).reshape(n, m)[i, :c],
            "position": np.asarray(ev.position).reshape(n, m, 3)[i, :c],
            "pre": np.asarray(ev.velocity_pre).reshape(n, m, 3)[i, :c],
            "post": np.asarray(ev.velocity_post).reshape(n, m, 3)[i, :c],
            "kind": np.asarray(ev.kind).reshape(n, m)[i, :c],
        })
    # Only events inside the sampled interval belong on a plot of the samples.
    for e in events:
        keep = (e["t"] >= ts[0]) & (e["t"] <= ts[-1])
        for k in e:
            e[k] = e[k][keep]
    return names, ts, pos, vel, events


def plot_heights(traj, balls, path=None, *, data: dict | None = None,
                 title: str | None = None) -> Figure:
    """Centre height z(t) of every ball of a simulation, with a marker at each impact the
    solver located (and at each landing to rest), and optionally the measured heights.

    Args:
        traj: an :class:`estim.Trajectory` whose batch holds one ball per name in ``balls``
            (``simulate(..., ts=...)``; the samples draw the lines).
        balls: the ball names, in batch order (a single name for an unbatched trajectory).
        path: where to save the figure (PNG, PDF, ...), or None.
        data: ``ball -> (t, position)`` measured samples to draw as dots.
        title: the figure's title (a default says what is shown).
    """
    names, ts, pos, _, events = _per_ball(traj, balls)
    fig = Figure(figsize=(8, 4.5), layout="tight")
    ax = fig.subplots()
    for i, (ball, ev) in enumerate(zip(names, events, strict=True)):
        c = _colour(ball, i)
        impact = ev["kind"] == IMPACT
        n_imp = int(np.sum(impact))
        ax.plot(ts, pos[i, :, 2], "-", lw=1.5, color=c,
                label=f"{ball} ({n_imp} bounce{'s' if n_imp != 1 else ''})")
        ax.plot(ev["t"][impact], ev["position"][impact, 2], "v", color=c, ms=6, ls="none",
                label=f"{ball} impacts")
        rest = ev["kind"] == REST
        if np.any(rest):
            ax.plot(ev["t"][rest], ev["position"][rest, 2], "o", mfc="none", color=c, ms=7,
                    ls="none", label=f"{ball} comes to rest")
        if data is not None and ball in data:
            t, p = (np.asarray(a, np.float64) for a in data[ball])
            ok = np.isfinite(p[:, 2])
            ax.plot(t[ok], p[ok, 2], ".", ms=2.5, color=c, alpha=0.5, label=f"{ball} measured")
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("centre height z [m]")
    ax.set_title(title or "Ball heights and the located bounce events (exact event-driven solution)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=7, ncol=2)
    return _save(fig, path)


def energy_curve(ts, position, velocity, event, g: float):
    """Mechanical energy per unit mass ``E = g z + |v|^2 / 2`` of one ball, at the samples
    and on both sides of every event (so each impact shows as the exact step it is).

    Returns ``(t, E)``, sorted by time; potential energy is measured from ``z = 0``.
    """
    e_samples = g * position[:, 2] + 0.5 * np.sum(velocity**2, axis=1)
    e_pre = g * event["position"][:, 2] + 0.5 * np.sum(event["pre"] ** 2, axis=1)
    e_post = g * event["position"][:, 2] + 0.5 * np.sum(event["post"] ** 2, axis=1)
    t = np.concatenate([ts, event["t"], event["t"]])
    e = np.concatenate([e_samples, e_pre, e_post])
    # Stable sort with pre before post at equal times: samples, then pre, then post.
    order = np.argsort(t, kind="stable")
    return t[order], e[order]


def plot_energy(traj, balls, path=None, *, gravity: float | None = None,
                title: str | None = None) -> Figure:
    """Normalised mechanical energy ``E / E0`` per ball, ``E = g z + |v|^2 / 2`` from the
    model (per unit mass, potential energy from ``z = 0``), with a marker after each impact.

    In free flight under gravity alone E is constant; an impact keeps ``e^2`` of the normal
    (vertical) kinetic energy and ``mu_t^2`` of the tangential, so the curve is a staircase
    whose steps show where the energy goes (in air, drag also drains it in flight).
    ``gravity`` is g (m/s^2), by default the one the trajectory was solved with; other
    arguments as for :func:`plot_heights`.
    """
    names, ts, pos, vel, events = _per_ball(traj, balls)
    if gravity is None:
        gravity = getattr(getattr(traj, "solution", None), "gravity", None)
        gravity = getattr(traj, "gravity", None) if gravity is None else gravity
    if gravity is None:
        raise ValueError("plot_energy: pass gravity= (the scene's g), the trajectory does not hold it")
    g = float(np.asarray(gravity))
    fig = Figure(figsize=(8, 4.5), layout="tight")
    ax = fig.subplots()
    for i, (ball, ev) in enumerate(zip(names, events, strict=True)):
        c = _colour(ball, i)
        t, e = energy_curve(ts, pos[i], vel[i], ev, g)
        e0 = e[0]
        ax.plot(t, e / e0, "-", lw=1.5, color=c, label=ball)
        impact = ev["kind"] == IMPACT
        e_post = g * ev["position"][impact, 2] + 0.5 * np.sum(ev["post"][impact] ** 2, axis=1)
        ax.plot(ev["t"][impact], e_post / e0, "v", color=c, ms=5, ls="none",
                label=f"{ball} after each impact")
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("E / E0  (E = g z + |v|^2 / 2)")
    ax.set_title(title or "Normalised mechanical energy per ball\n(each bounce keeps e^2 of "
                          "the vertical kinetic energy)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=7, ncol=2)  # the staircases fall to the right
    return _save(fig, path)
