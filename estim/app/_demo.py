"""``estim demo``: the seed scene's three balls, a summary table, height and energy plots;
the replays of the demo fit."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._json import dump
from ..forward._simulate import simulate
from ..model._params import Params
from ..model._scene import load_scene

__all__ = ["DEMO_TRACKS", "SEED", "SEED_SCENE", "run_demo", "format_summary", "seed_params"]

SEED_SCENE = Path(__file__).resolve().parents[2] / "data" / "scenes" / "stairs.xml"
DEMO_TRACKS = Path(__file__).resolve().parents[2] / "data" / "tracks" / "stairs_demo.csv"

# The seed experiment: restitution per ball, shared tangential coefficient and release
# velocity, simulated over [0, T_END]. Release positions come from the scene file.
SEED = {
    "e": {"bocce": 0.55, "golf": 0.70, "pingpong": 0.85},
    "mu_t": 0.98,
    "velocity": (1.15, 0.0, 0.0),
    "t_end": 2.3,
}


def default_scene_path() -> str:
    """The bundled seed scene (next to the package in a source checkout), else the
    relative path ``data/scenes/stairs.xml``."""
    if SEED_SCENE.is_file():
        return str(SEED_SCENE)
    return os.path.join("data", "scenes", "stairs.xml")


def seed_params(scene, names=None, *, e=None, mu_t=SEED["mu_t"], velocity=SEED["velocity"]):
    """The seed experiment's balls of ``scene`` as one batch of ``Params``.

    Each ball is released at its position in the scene file, with its mass, the seed's
    restitution (``SEED["e"]``, or ``e`` for every ball), ``mu_t`` and ``velocity``.
    ``names`` defaults to the scene's balls that the seed names, in scene order. A ball the
    scene lacks is a KeyError naming the scene's balls; one without a seed e and no ``e``
    given, a ValueError.
    """
    names = list(names) if names is not None else [b.name for b in scene.balls if b.name in SEED["e"]]
    rows = []
    for name in names:
        scene.ball(name)
        e_ball = e if e is not None else SEED["e"].get(name)
        if e_ball is None:
            raise ValueError(f"no seed restitution for ball {name!r}: give e (--e)")
        rows.append(Params.for_ball(scene, name, e=e_ball, mu_t=mu_t, velocity=velocity))
    return jax.tree.map(lambda *x: jnp.stack(x), *rows)


def run_demo(out_dir: str | os.PathLike, *, scene_path: str | os.PathLike | None = None,
             n_samples: int = 500) -> dict:
    """Simulate the seed scene's balls together (one batched call), write
    ``summary.json``, ``heights.png`` (with the impacts) and ``energy.png`` into
    ``out_dir`` (created if missing) and return the summary."""
    scene_path = str(scene_path) if scene_path is not None else default_scene_path()
    scene = load_scene(scene_path)
    balls = [b for b in scene.balls if b.name in SEED["e"]] or list(scene.balls)
    t_end = SEED["t_end"]
    params = Params(
        [SEED["e"].get(b.name, 0.7) for b in balls],
        [SEED["mu_t"]] * len(balls),
        [b.radius for b in balls],
        [b.position for b in balls],
        [SEED["velocity"]] * len(balls),
    )
    ts = jnp.linspace(0.0, t_end, n_samples)
    traj = simulate(scene, params, t_end, ts=ts)

    ev = traj.events
    count = np.asarray(ev.count)
    kind = np.asarray(ev.kind)
    ev_t = np.asarray(ev.t)
    ev_z = np.asarray(ev.position[..., 2])
    final = np.asarray(traj.final.position)
    rows = []
    for i, b in enumerate(balls):
        c = int(count[i])
        impacts = kind[i, :c] == 0
        rows.append({
            "ball": b.name,
            "e": float(params.e[i]),
            "mu_t": float(params.mu_t[i]),
            "bounces": int(np.sum(impacts)),
            "final_x": float(final[i, 0]),
            "final_y": float(final[i, 1]),
            "final_z": float(final[i, 2]),
            "impact_t": ev_t[i, :c][impacts].tolist(),
            "impact_z": ev_z[i, :c][impacts].tolist(),
        })
    summary = {
        "scene": scene_path,
        "t_end": t_end,
        "velocity": list(SEED["velocity"]),
        "balls": rows,
    }

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "summary.json", "w") as fh:
        dump(summary, fh, indent=2)
        fh.write("\n")
    from ..show._plots import plot_energy, plot_heights  # lazy: matplotlib

    names = [b.name for b in balls]
    plot_heights(traj, names, out / "heights.png",
                 title="Seed scene: heights and the located bounce events (exact solution)")
    plot_energy(traj, names, out / "energy.png", gravity=float(scene.gravity))
    summary["files"] = [str(out / n) for n in ("summary.json", "heights.png", "energy.png")]
    return summary


def write_replays(out_dir: str | os.PathLike, *, scene_path: str | os.PathLike | None = None,
                  tracks_path: str | os.PathLike = DEMO_TRACKS, fps: float = 25.0) -> list[str]:
    """The replays of ``out_dir/fit.json`` against the tracks: ``replay.gif`` (MuJoCo) and
    ``sideview.gif`` (matplotlib). Where MuJoCo cannot render (no OpenGL), says so on
    stderr and writes the side view only. Returns the files written."""
    from ..show._replay import RenderError, render_replay  # lazy: MuJoCo
    from ..show._sideview import render_sideview  # lazy: matplotlib

    scene_path = str(scene_path) if scene_path is not None else default_scene_path()
    out = Path(out_dir)
    fit_json = out / "fit.json"
    files = []
    try:
        files.append(render_replay(scene_path, fit_json, tracks_path, out / "replay.gif", fps=fps).path)
    except RenderError as err:
        print(f"estim demo: replay.gif not written: {err}", file=sys.stderr)
    files.append(render_sideview(scene_path, fit_json, tracks_path, out / "sideview.gif", fps=fps).path)
    return files


def format_summary(summary: dict) -> str:
    lines = [f"{'ball':<10} {'e':>5} {'bounces':>8} {'final x (m)':>14} {'final z (m)':>14}"]
    for r in summary["balls"]:
        lines.append(
            f"{r['ball']:<10} {r['e']:>5.2f} {r['bounces']:>8d} {r['final_x']:>14.10f} {r['final_z']:>14.10f}"
        )
    return "\n".join(lines)
