"""``estim demo``: the seed scene's three balls, a summary table and a height plot."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

__all__ = ["DEMO_TRACKS", "SEED", "SEED_SCENE", "run_demo", "format_summary"]

SEED_SCENE = Path(__file__).resolve().parent.parent / "data" / "scenes" / "stairs.xml"
DEMO_TRACKS = Path(__file__).resolve().parent.parent / "data" / "tracks" / "stairs_demo.csv"

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


def run_demo(out_dir: str | os.PathLike, *, scene_path: str | os.PathLike | None = None,
             n_samples: int = 500) -> dict:
    """Simulate the seed scene's balls together (one batched call), write
    ``summary.json`` and ``heights.png`` into ``out_dir`` (created if missing) and
    return the summary."""
    import jax.numpy as jnp

    import estim

    scene_path = str(scene_path) if scene_path is not None else default_scene_path()
    scene = estim.load_scene(scene_path)
    balls = [b for b in scene.balls if b.name in SEED["e"]] or list(scene.balls)
    t_end = SEED["t_end"]
    params = estim.Params(
        [SEED["e"].get(b.name, 0.7) for b in balls],
        [SEED["mu_t"]] * len(balls),
        [b.radius for b in balls],
        [b.position for b in balls],
        [SEED["velocity"]] * len(balls),
    )
    ts = jnp.linspace(0.0, t_end, n_samples)
    traj = estim.simulate(scene, params, t_end, ts=ts)

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
        json.dump(summary, fh, indent=2)
        fh.write("\n")
    _plot(out / "heights.png", np.asarray(ts), np.asarray(traj.position[..., 2]), rows)
    summary["files"] = [str(out / "summary.json"), str(out / "heights.png")]
    return summary


def _plot(path: Path, ts, z, rows) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=120)
    for i, row in enumerate(rows):
        (line,) = ax.plot(ts, z[i], lw=1.5, label=f"{row['ball']} (e = {row['e']:.2f}, {row['bounces']} bounces)")
        ax.plot(row["impact_t"], row["impact_z"], "v", color=line.get_color(), ms=6)
    ax.plot([], [], "v", color="0.4", label="impacts")
    ax.set_xlabel("time t (s)")
    ax.set_ylabel("centre height z (m)")
    ax.set_title("Seed scene: balls bouncing down the stairs (exact event-driven solution)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def format_summary(summary: dict) -> str:
    lines = [f"{'ball':<10} {'e':>5} {'bounces':>8} {'final x (m)':>14} {'final z (m)':>14}"]
    for r in summary["balls"]:
        lines.append(
            f"{r['ball']:<10} {r['e']:>5.2f} {r['bounces']:>8d} {r['final_x']:>14.10f} {r['final_z']:>14.10f}"
        )
    return "\n".join(lines)
