"""Many shots of one ball, one camera: each shot fitted alone, then all fitted together.

The shots of `camera_views.py` (a rally's, released behind one end, bouncing once on the
far half, 25 fps, 2 px of noise), all of one ball: one restitution and one friction
coefficient (estim's physics), or one contact, friction and drag (MuJoCo's, whose soft
contact keeps a restitution that varies a little with the impact: the truth is each
shot's, and the shared e is compared with their mean). Per view: each shot fitted alone
as `estim fit TRACK --camera CAM` fits it (the scene's priors), and the shots fitted
together (`estim.fit_image_clips`, `--shared`: e and mu by default): the error of e, its
standard error, and the mean 3-D error of the paths.

    python docs/scripts/camera_pooled.py [--engine mujoco] [--shots 8] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from camera_views import NOISE_PX, SCENE, VIEWS, draw_mujoco_shot, draw_shot

import estim
from estim.tracks._image import ImageTracks

FPS = 25.0
# The ball: estim's shots' e and mu (the middle of camera_views' ranges; e the scene's prior
# mean, which a fit alone is drawn to: ``--e`` moves it); MuJoCo's contact
# damping (its restitution about 0.88), friction and drag coefficient.
BALL = {"estim": {"e": 0.88, "mu": 0.3},
        "mujoco": {"damping": 0.045, "mu": 0.3, "drag_coefficient": 0.5}}
SHARED = ("e", "mu")


def run(shots: int, seed: int, views, engine: str, e: float | None = None, shared=SHARED) -> list[dict]:
    scene = estim.load_scene(SCENE)
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 0.6, 1.0 / FPS)
    ball = {**BALL["estim"], **({} if e is None else {"e": e})}
    drawn = [draw_shot(rng, scene, t, ball) if engine == "estim"
             else draw_mujoco_shot(rng, t, ball=BALL["mujoco"]) for _ in range(shots)]
    rows = []
    for name in views:
        cam = VIEWS[name]
        clips = {}
        for k, (_, path) in enumerate(drawn):
            uv = np.asarray(cam.project(path)) + NOISE_PX * rng.normal(0.0, 1.0, (t.size, 2))
            clips[f"shot{k}"] = ImageTracks(f"shot {k}", ("pingpong",), (cam,), {"pingpong": t}, {"pingpong": uv},
                                            {"pingpong": np.zeros(t.size, np.int64)})
        start = time.perf_counter()
        with estim.optimised_programs():
            alone = {k: estim.fit_image(scene, tracks).balls["pingpong"] for k, tracks in clips.items()}
            seconds_alone = time.perf_counter() - start
            pooled = estim.fit_image_clips(scene, clips, shared=shared)
        seconds = time.perf_counter() - start - seconds_alone
        true_e = np.array([truth["e"] for truth, _ in drawn])
        sf = pooled.shared["pingpong"]
        row = {
            "view": name, "shots": shots, "engine": engine, "true_e_mean": float(true_e.mean()),
            "e_alone": [bf.values["e"] for bf in alone.values()],
            "e_alone_stderr": [bf.stderr["e"] for bf in alone.values()],
            "e_shared": sf.values["e"], "e_shared_stderr": sf.stderr["e"], "shared": list(shared),
            "path_alone_m": [float(np.mean(np.linalg.norm(bf.model_position - path, axis=1)))
                             for bf, (_, path) in zip(alone.values(), drawn, strict=True)],
            "path_shared_m": [float(np.mean(np.linalg.norm(pooled.clips.balls[k].model_position - path, axis=1)))
                              for k, (_, path) in zip(clips, drawn, strict=True)],
            "seconds_alone": seconds_alone, "seconds_together": seconds,
        }
        rows.append(row)
        print(f"{name:>7}: e alone {np.median(np.abs(np.array(row['e_alone']) - true_e)):.3f} off at the median, "
              f"together {row['e_shared']:.3f} +- {row['e_shared_stderr']:.3f} (truth {row['true_e_mean']:.3f}); "
              f"path {np.mean(row['path_alone_m']) * 100:.1f} -> {np.mean(row['path_shared_m']) * 100:.1f} cm; "
              f"{seconds_alone:.0f} s and {seconds:.0f} s", flush=True)
    return rows


def table(rows: list[dict]) -> str:
    out = ["| view | shots | e alone: error, median (max) | e alone: standard error, median | e together: error | "
           "e together: standard error | mean path error alone (cm) | together (cm) | worst alone (cm) | "
           "worst together (cm) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        err = np.abs(np.array(r["e_alone"]) - r["true_e_mean"])
        out.append(f"| {r['view']} | {r['shots']} | {np.median(err):.3f} ({err.max():.3f}) | "
                   f"{np.median(r['e_alone_stderr']):.3f} | {r['e_shared'] - r['true_e_mean']:+.3f} | "
                   f"{r['e_shared_stderr']:.3f} | {np.mean(r['path_alone_m']) * 100:.1f} | "
                   f"{np.mean(r['path_shared_m']) * 100:.1f} | {np.max(r['path_alone_m']) * 100:.1f} | "
                   f"{np.max(r['path_shared_m']) * 100:.1f} |")
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shots", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--views", nargs="+", default=["side", "angle", "behind"], choices=list(VIEWS))
    parser.add_argument("--engine", default="estim", choices=("estim", "mujoco"))
    parser.add_argument("--e", type=float, default=None,
                        help="estim's shots: the ball's restitution (default 0.88, the scene's prior mean)")
    parser.add_argument("--shared", nargs="+", default=list(SHARED), help="the shared parameters (e among them)")
    parser.add_argument("--json", default=None, help="write every row to this file")
    args = parser.parse_args()
    rows = run(args.shots, args.seed, tuple(args.views), args.engine, args.e, tuple(args.shared))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    print(table(rows))


if __name__ == "__main__":
    main()
