"""One camera, four views: synthetic table-tennis shots fitted from their pixels.

Run from the repository root: ``python docs/scripts/camera_views.py [--shots N] [--json F]
[--engine mujoco [--magnus C_M] [--angular-drag C]] [--kind drive|serve|lob|chop]``.
Shots of a rally (:func:`draw_shot`) in estim's own 3-D physics (drag, Magnus, the
friction law's bounce; spin drawn per shot), or with ``--engine mujoco`` in MuJoCo's
(:func:`mujoco_shot`: its fluid model and soft frictional contact, the drag coefficient
and restitution drawn per shot; the independent engine, whose mismatch with estim's model
stands in for a real ball's), or with ``--kind`` drives, serves, lobs and chops
(:data:`KINDS`) in either, 25 fps, seen by one camera at a time (from the side, at an
angle from a corner, far behind the end the ball leaves, far behind the end it comes at:
"front", and as television films a rally: 10 m behind the end the ball leaves, 3.5 m up,
through a long lens: "broadcast"), 2 px of Gaussian noise on every pixel (``--noise``).
Each is fitted with ``estim.fit_image`` and its defaults (what ``estim fit TRACK.csv
--camera CAM.yaml --scene data/scenes/table_tennis.xml`` runs), and compared with the
truth: the mean 3-D distance of the fitted path from the true one at the frames, e, and
the spin across the flight (the part perpendicular to the release velocity, which the
Magnus force and the bounce read).
Next to each fit's error, the error the data allow (:func:`bound`): the Bayesian
Cramer-Rao (van Trees) bound on the path from the pixels' Fisher information at the truth
and the scene's priors, the same parameters free as the fit. Prints a Markdown table
(docs/pages/cameras.md holds one run of it).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import mujoco
import numpy as np

import estim
from estim.fitting import _registry as registry
from estim.tracks._camera import Camera
from estim.tracks._image import ImageTracks

SCENE = str(pathlib.Path(__file__).resolve().parents[2] / "data" / "scenes" / "table_tennis.xml")
FPS = 25.0
NOISE_PX = 2.0
SIZE = (1920, 1080)
FOCAL = 1500.0
VIEWS = {
    "side": Camera.look_at((3.2, 0.0, 0.8), (0.0, 0.0, 0.1), focal=FOCAL, size=SIZE, name="side"),
    "angle": Camera.look_at((2.6, -3.4, 1.4), (0.0, 0.0, 0.1), focal=FOCAL, size=SIZE, name="angle"),
    "behind": Camera.look_at((0.0, -5.5, 1.6), (0.0, 0.0, 0.1), focal=FOCAL, size=SIZE, name="behind"),
    # Behind the other end: the ball comes at the camera (a rally's other half).
    "front": Camera.look_at((0.0, 5.5, 1.6), (0.0, 0.0, 0.1), focal=FOCAL, size=SIZE, name="front"),
    # As television films a rally: far behind the end the ball leaves and high, through a
    # long lens (perspective weaker, depth harder to read than from 5.5 m).
    "broadcast": Camera.look_at((0.0, -10.0, 3.5), (0.0, 0.0, 0.1), focal=2 * FOCAL, size=SIZE, name="broadcast"),
}
# Views added after the first runs draw their noise from streams of their own, so that the
# other views' shots and noise stay those of the runs before them (docs/pages/cameras.md).
OWN_STREAM = {"front": 1, "broadcast": 2}
# MuJoCo's Magnus coefficient (``--magnus``), 1 by default as in MuJoCo. Its lift on a
# table-tennis ball then is 1.6-1.9 times the textbook curve's that estim holds (Sawicki et
# al., estim.model._air) at 100-600 rad/s and 5-14 m/s (measured from MuJoCo's passive
# force with `mj_forward`); at 0.76 it is 0.84-0.98 of that curve's at spin ratios
# 0.4-0.9 (f_L kappa = 8 (C_M - 1/2) / 3 = 0.69: estim.model._air's docstring).
MAGNUS = 1.0
# MuJoCo's angular drag coefficient (its third fluidcoef, ``--angular-drag``), 1.5 by
# default as in MuJoCo: it halves a table-tennis ball's 300 rad/s in 0.25 s of flight.
ANGULAR_DRAG = 1.5
# The net's box, as the scene declares it (its centre and half sizes, m).
_NET = mujoco.MjModel.from_xml_path(SCENE).geom("net")
NET_CENTRE, NET_HALF = np.array(_NET.pos), np.array(_NET.size)


def clears_net(p, radius: float = 0.02) -> bool:
    """Whether a path ``p`` sampled about every millisecond stays clear of the net: the
    ball's centre never within its radius and 1 cm (what a 16 m/s ball moves between two
    samples) of the net's box. The height at which a path crosses the net does not say
    it: a ball that clips the net's top can still cross above it."""
    gap = np.linalg.norm(np.maximum(np.abs(np.asarray(p) - NET_CENTRE) - NET_HALF, 0.0), axis=1)
    return bool(np.min(gap) > radius + 0.01)


def draw_shot(rng, scene, t, ball: dict | None = None) -> tuple[dict, np.ndarray]:
    """A shot from behind one end of the table that clears the net and bounces once on the
    far half within the frames (drawn until one does): release 0.15-0.3 m above the table
    beyond its end, 4-7 m/s along y, spin about x (topspin to backspin, up to 150 rad/s)
    with some sidespin. ``ball``: its ``e`` and ``mu`` (drawn, then replaced: the same
    draws of the rest). Returns the truth and the path at the times ``t``."""
    while True:
        truth = {
            "e": float(rng.uniform(0.85, 0.92)),
            "mu": float(rng.uniform(0.2, 0.4)),
            "position": np.array([rng.uniform(-0.4, 0.4), -1.6, rng.uniform(0.15, 0.3)]),
            "velocity": np.array([rng.uniform(-0.6, 0.6), rng.uniform(4.0, 7.0), rng.uniform(0.3, 1.5)]),
            "spin": np.array([rng.uniform(-150.0, 100.0), rng.uniform(-20.0, 20.0), rng.uniform(-60.0, 60.0)]),
        }
        truth.update(ball or {})
        params = estim.Params.for_ball(scene, "pingpong", e=truth["e"], mu_t=0.0, mu=truth["mu"],
                                       position=truth["position"], velocity=truth["velocity"], spin=truth["spin"])
        fine = np.linspace(0.0, float(t[-1]), 601)
        run = estim.simulate(scene, params, float(t[-1]), ts=fine)
        p = np.asarray(run.position)
        low = np.flatnonzero((p[1:-1, 2] < p[:-2, 2]) & (p[1:-1, 2] <= p[2:, 2])) + 1
        net = np.interp(0.0, p[:, 1], p[:, 2]) if p[0, 1] < 0 < p[-1, 1] else -1.0
        if (net > 0.2 and clears_net(p) and len(low) == 1 and abs(p[low[0], 2] - 0.02) < 1e-3
                and 0.2 < p[low[0], 1] < 1.3 and fine[low[0]] < float(t[-1]) - 0.12):
            return truth, np.asarray(estim.simulate(scene, params, float(t[-1]), ts=t).position)


def mujoco_shot(position, velocity, spin, t, *, blunt_drag: float = 0.5, damping: float = 0.1,
                friction: float = 0.2, magnus: float = MAGNUS,
                angular_drag: float = ANGULAR_DRAG) -> tuple[np.ndarray, float | None]:
    """A shot in MuJoCo's own physics: the table-tennis scene with the ball's ellipsoid
    fluid model (``fluidshape="ellipsoid"``: drag, Magnus and added mass, and an angular
    drag that slows the spin; ``blunt_drag`` its first ``fluidcoef``, ``C_blunt rho A |v| v``,
    so C_D = 2 C_blunt in estim's terms, ``angular_drag`` its third, ``magnus`` its fifth,
    the Magnus coefficient C_M) and a soft frictional contact with the table
    (``condim="6"``, ``friction``, elliptic cone, impratio 100, ``solref="0.0005
    damping"``), stepped at 20 us from the release state (the free joint's angular velocity
    is in the body's frame, the world's at release). Returns the positions at the times
    ``t`` (from 0) and the restitution the table's contact shows (the normal speed after
    the bounce's last contact over that before its first; ``None`` without a bounce)."""
    contact = f'condim="6" friction="{friction} 0 0" solref="0.0005 {damping}"'
    xml = open(SCENE).read().replace('timestep="0.0005"', 'timestep="2e-5" cone="elliptic" impratio="100"')
    xml = xml.replace('shellinertia="true"', f'shellinertia="true" fluidshape="ellipsoid" '
                                              f'fluidcoef="{blunt_drag} 0.25 {angular_drag} 1.0 {magnus}" {contact}')
    xml = xml.replace('<geom name="table" type="box"', f'<geom name="table" type="box" {contact}')
    model = mujoco.MjModel.from_xml_string(xml)
    table = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table")
    data = mujoco.MjData(model)
    data.qpos[:3] = position
    data.qvel[:] = [*velocity, *spin]
    out, before, start, after = [], None, None, None
    while len(out) < len(t):
        if data.time >= t[len(out)] - 1e-12:
            out.append(data.qpos[:3].copy())
        vz = float(data.qvel[2])
        mujoco.mj_step(model, data)
        touching = any(table in data.contact[i].geom for i in range(data.ncon))
        if touching and before is None:
            before, start = vz, data.time
        elif touching and data.time < start + 0.005:  # the bounce's contacts, however they flicker
            after = None
        elif start is not None and after is None and data.time < start + 0.01:
            after = float(data.qvel[2])
    return np.array(out), (None if after is None else -after / before)


def draw_mujoco_shot(rng, t, magnus: float = MAGNUS, angular_drag: float = ANGULAR_DRAG,
                     ball: dict | None = None) -> tuple[dict, np.ndarray]:
    """A shot as :func:`draw_shot` draws them, flown in MuJoCo (:func:`mujoco_shot`), with
    its drag coefficient (0.4-0.6, C_D = 2 C_blunt), friction (0.2-0.4) and contact
    damping drawn too (``ball``: those of one ball, drawn and replaced); kept where the
    restitution its contact shows lies within 0.8-0.95 (the scene's prior on e: 0.88 +-
    0.05) and it clears the net and bounces once on the far half within the frames.
    Returns the truth (``e`` the contact's) and the path at ``t``."""
    fine = np.arange(0.0, float(t[-1]) + 1e-9, 0.001)
    while True:
        truth = {
            "drag_coefficient": float(rng.uniform(0.4, 0.6)), "mu": float(rng.uniform(0.2, 0.4)),
            "damping": float(rng.uniform(0.035, 0.055)),
            "position": np.array([rng.uniform(-0.4, 0.4), -1.6, rng.uniform(0.15, 0.3)]),
            "velocity": np.array([rng.uniform(-0.6, 0.6), rng.uniform(4.0, 7.0), rng.uniform(0.3, 1.5)]),
            "spin": np.array([rng.uniform(-150.0, 100.0), rng.uniform(-20.0, 20.0), rng.uniform(-60.0, 60.0)]),
        }
        truth.update(ball or {})
        p, e = mujoco_shot(truth["position"], truth["velocity"], truth["spin"], fine,
                           blunt_drag=truth["drag_coefficient"] / 2, damping=truth["damping"], friction=truth["mu"],
                           magnus=magnus, angular_drag=angular_drag)
        if e is None or not 0.8 < e < 0.95:
            continue
        truth["e"] = e
        low = np.flatnonzero((p[1:-1, 2] < p[:-2, 2]) & (p[1:-1, 2] <= p[2:, 2])) + 1
        net = np.interp(0.0, p[:, 1], p[:, 2]) if p[0, 1] < 0 < p[-1, 1] else -1.0
        if (net > 0.2 and clears_net(p) and len(low) == 1 and abs(p[low[0], 2] - 0.02) < 2e-3
                and 0.2 < p[low[0], 1] < 1.3 and fine[low[0]] < float(t[-1]) - 0.12):
            return truth, p[np.round(np.asarray(t) / 0.001).astype(int)]


# Other kinds of shot (``--kind``, either engine's physics): ranges of the release position (m),
# velocity (m/s) and spin (rad/s) per component; a serve bounces on the server's half
# first. Their spins are a real ball's, flown by MuJoCo's Magnus force, which at these
# spins is 1.6 to 1.9 times the textbook curve's at MuJoCo's default (a constant lift
# coefficient; ``MAGNUS``, ``--magnus``): a harder bend than real shots have.
KINDS = {
    "drive": {"position": ((-0.5, 0.5), (-2.2, -1.5), (0.1, 0.5)), "velocity": ((-1.0, 1.0), (9.0, 16.0), (-0.5, 1.5)),
              "spin": ((-600.0, -200.0), (-50.0, 50.0), (-100.0, 100.0))},
    "serve": {"position": ((-0.5, 0.5), (-1.6, -1.4), (0.15, 0.35)), "velocity": ((-0.5, 0.5), (3.0, 6.0), (-2.0, -0.5)),
              "spin": ((50.0, 300.0), (-50.0, 50.0), (-200.0, 200.0))},
    "lob": {"position": ((-0.6, 0.6), (-3.5, -2.5), (-0.2, 0.4)), "velocity": ((-0.8, 0.8), (3.5, 6.0), (3.0, 5.0)),
            "spin": ((-400.0, -100.0), (-50.0, 50.0), (-100.0, 100.0))},
    "chop": {"position": ((-0.5, 0.5), (-2.8, -1.8), (0.0, 0.4)), "velocity": ((-0.5, 0.5), (5.0, 9.0), (0.5, 2.0)),
             "spin": ((150.0, 400.0), (-50.0, 50.0), (-80.0, 80.0))},
}


def draw_kind(rng, kind: str, magnus: float = MAGNUS, angular_drag: float = ANGULAR_DRAG,
              scene=None) -> tuple[dict, np.ndarray, np.ndarray]:
    """A shot of ``kind`` (``KINDS``) flown by MuJoCo (:func:`mujoco_shot`, its drag
    coefficient, friction and contact damping drawn as :func:`draw_mujoco_shot` draws them,
    kept where its contact's restitution lies within 0.75-0.97) or, given ``scene``, by
    estim in that scene (e and mu drawn as :func:`draw_shot` draws them); kept where it
    clears the net by 0.2 m (its centre's height over the net), never touching it, and
    bounces on the far half (a serve on its own half first, then on the far half; any
    other shot on the far half first); tracked at 25 fps from its release until the
    opponent's hit, 0.1 to 0.3 s after that bounce (or until it falls below the table's
    top). Returns the truth, the path and the frames' times."""
    fine = np.arange(0.0, 2.5, 0.001)  # (with a spin that barely decays a chop flew past 1.5 s)
    spec = KINDS[kind]
    while True:
        truth = {k: np.array([rng.uniform(*r) for r in spec[k]]) for k in ("position", "velocity", "spin")}
        if scene is None:
            truth.update(drag_coefficient=float(rng.uniform(0.4, 0.6)), damping=float(rng.uniform(0.035, 0.055)),
                         mu=float(rng.uniform(0.2, 0.4)))
            p, e = mujoco_shot(truth["position"], truth["velocity"], truth["spin"], fine,
                               blunt_drag=truth["drag_coefficient"] / 2, damping=truth["damping"],
                               friction=truth["mu"], magnus=magnus, angular_drag=angular_drag)
            if e is None or not 0.75 < e < 0.97:
                continue
            truth["e"] = e
        else:
            truth.update(e=float(rng.uniform(0.85, 0.92)), mu=float(rng.uniform(0.2, 0.4)))
            params = estim.Params.for_ball(scene, "pingpong", e=truth["e"], mu_t=0.0, mu=truth["mu"],
                                           position=truth["position"], velocity=truth["velocity"],
                                           spin=truth["spin"])
            p = np.asarray(estim.simulate(scene, params, float(fine[-1]), ts=fine).position)
        y, z = p[:, 1], p[:, 2]
        low = np.flatnonzero((z[1:-1] < z[:-2]) & (z[1:-1] <= z[2:]) & (np.abs(z[1:-1] - 0.02) < 3e-3)) + 1
        far = [i for i in low if 0.0 < y[i] < 1.37]
        cross = np.flatnonzero((y[:-1] < 0.0) & (y[1:] >= 0.0))
        if not far or not cross.size or z[cross[0]] < 0.2 or not clears_net(p):
            continue
        if (kind == "serve") != (len(low) >= 2 and -1.37 < y[low[0]] < 0.0 and low[1] == far[0]):
            continue
        if kind != "serve" and low[0] != far[0]:
            continue
        t_end = fine[far[0]] + rng.uniform(0.1, 0.3)
        below = np.flatnonzero((fine > fine[far[0]]) & (z < 0.0))
        t = np.arange(0.0, min(t_end, fine[below[0]]) if below.size else t_end, 1.0 / FPS)
        if t.size >= 5:
            return truth, p[np.round(t / 0.001).astype(int)], t


# The fit's free parameters in the order of ``theta`` (``bound``): what ``fit_image``
# estimates by default in the table-tennis scene.
FREE = ("x0", "y0", "z0", "vx0", "vy0", "vz0", "spin_x", "spin_y", "spin_z", "e", "mu")


def bound(scene, truth, t, cam, noise: float, draws: int = 4000) -> float:
    """The least mean 3-D path error (m) an unbiased fit can expect, linearised at the truth:
    the pixels' Fisher information ``J^T J / noise^2`` (J: the pixels' derivative in the
    fit's free parameters, through the events) plus the precision of the scene's priors
    (van Trees 1968: the Bayesian form of the Cramer-Rao bound), inverted, mapped onto the
    path at the frames, and the mean distance averaged over Gaussian draws of it."""
    if noise <= 0:
        return 0.0

    def path_of(theta):
        params = estim.Params.for_ball(scene, "pingpong", e=theta[9], mu_t=0.0, mu=theta[10], position=theta[0:3],
                                       velocity=theta[3:6], spin=theta[6:9])
        return estim.simulate(scene, params, float(t[-1]), ts=t).position

    theta = np.concatenate([truth["position"], truth["velocity"], truth["spin"], [truth["e"], truth["mu"]]])
    dpath = np.asarray(jax.jacfwd(path_of)(theta))  # (frames, 3, free)
    dpixel = np.asarray(jax.vmap(jax.jacfwd(lambda x: cam.project(x[None])[0]))(path_of(theta)))  # (frames, 2, 3)
    j = np.einsum("fij,fjk->fik", dpixel, dpath).reshape(-1, len(FREE))
    information = j.T @ j / noise**2
    for name, (_, sd) in registry.priors(scene).items():
        if name in FREE:
            information[FREE.index(name), FREE.index(name)] += 1.0 / sd**2
    z = np.random.default_rng(0).normal(size=(draws, len(FREE))) @ np.linalg.cholesky(np.linalg.inv(information)).T
    return float(np.mean(np.linalg.norm(np.einsum("fik,nk->nfi", dpath, z), axis=2)))


def across(spin, velocity):
    v = np.asarray(velocity) / np.linalg.norm(velocity)
    return np.asarray(spin) - np.dot(spin, v) * v


def run(shots: int, seed: int = 0, views=tuple(VIEWS), noise: float = NOISE_PX, engine: str = "estim",
        kind: str = "rally", magnus: float = MAGNUS, angular_drag: float = ANGULAR_DRAG) -> list[dict]:
    scene = estim.load_scene(SCENE)
    rng = np.random.default_rng(seed)
    own = {name: np.random.default_rng([seed, k]) for name, k in OWN_STREAM.items()}
    rows = []
    for k in range(shots):
        t = np.arange(0.0, 0.6, 1.0 / FPS)
        if kind != "rally":
            truth, path, t = draw_kind(rng, kind, magnus, angular_drag, scene if engine == "estim" else None)
        elif engine == "estim":
            truth, path = draw_shot(rng, scene, t)
        else:
            truth, path = draw_mujoco_shot(rng, t, magnus, angular_drag)
        for name in views:
            cam = VIEWS[name]
            # The same draws at every noise level: the shots' noise differs only in its size.
            uv = np.asarray(cam.project(path)) + noise * own.get(name, rng).normal(0.0, 1.0, (t.size, 2))
            tracks = ImageTracks(f"shot {k}", ("pingpong",), (cam,), {"pingpong": t}, {"pingpong": uv},
                                 {"pingpong": np.zeros(t.size, np.int64)})
            start = time.perf_counter()
            try:
                with estim.optimised_programs():  # (many shots: the optimised program from the first)
                    bf = estim.fit_image(scene, tracks).balls["pingpong"]
            except Exception as err:  # a shot left without an answer is a result too
                rows.append({"shot": k, "view": name, "error": f"{type(err).__name__}: {err}"})
                continue
            seconds = time.perf_counter() - start
            spin = np.array([bf.values.get(f"spin_{c}", 0.0) for c in "xyz"])
            want = across(truth["spin"], truth["velocity"])
            rows.append({
                "shot": k, "view": name, "kind": kind, "frames": int(t.size), "seconds": seconds,
                "path_error_m": float(np.mean(np.linalg.norm(bf.model_position - path, axis=1))),
                # (No bound for MuJoCo's shots: its pixels are not of estim's model.)
                "bound_m": bound(scene, truth, t, cam, noise) if engine == "estim" else None,
                "e_error": abs(bf.values["e"] - truth["e"]), "e_signed": bf.values["e"] - truth["e"],
                "spin_error": float(np.linalg.norm(across(spin, truth["velocity"]) - want) / np.linalg.norm(want)),
                "rms_px": bf.rms_m, "converged": bf.converged, "at_noise_floor": bf.at_noise_floor,
                "bounces": bf.n_bounces, "depth_m": bf.depth["along_axis_m"],
                "second_path_m": (bf.depth["alternative"] or {}).get("distance_m"),
            })
            r = rows[-1]
            said = "" if r["bound_m"] is None else f" (bound {r['bound_m'] * 100:4.1f})"
            print(f"shot {k} {name:>6}: path {r['path_error_m'] * 100:5.1f} cm{said}  "
                  f"e {r['e_signed']:+.3f}  "
                  f"spin {r['spin_error']:5.0%}  rms {r['rms_px']:.2f} px  bounces {r['bounces']}  {seconds:5.1f} s", flush=True)
    return rows


def table(rows: list[dict]) -> str:
    out = ["| view | shots | mean 3-D error of the path (cm) | bound (cm) | worst (cm) | e error, median (max) | "
           "e error, mean (signed) | spin across the flight, median error | rms (px) | second path reported | "
           "no answer |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in VIEWS:
        ok = [r for r in rows if r["view"] == name and "error" not in r]
        failed = sum(1 for r in rows if r["view"] == name and "error" in r)
        if not ok:
            continue
        path = np.array([r["path_error_m"] for r in ok]) * 100
        e = np.array([r["e_error"] for r in ok])
        bounds = [r["bound_m"] for r in ok if r["bound_m"] is not None]
        out.append(f"| {name} | {len(ok) + failed} | {path.mean():.1f} | "
                   f"{f'{np.mean(bounds) * 100:.1f}' if bounds else '-'} | "
                   f"{path.max():.1f} | {np.median(e):.3f} ({e.max():.3f}) | {np.mean([r['e_signed'] for r in ok]):+.3f} | "
                   f"{np.median([r['spin_error'] for r in ok]):.0%} | "
                   f"{np.median([r['rms_px'] for r in ok]):.2f} | "
                   f"{sum(r['second_path_m'] is not None for r in ok)} | {failed} |")
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shots", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--views", nargs="+", default=list(VIEWS), choices=list(VIEWS))
    parser.add_argument("--noise", type=float, default=NOISE_PX, help="pixels' noise (px; 0: exact pixels)")
    parser.add_argument("--json", default=None, help="write every row to this file")
    parser.add_argument("--engine", default="estim", choices=("estim", "mujoco"),
                        help="whose physics flies the shots (mujoco: the independent engine)")
    parser.add_argument("--kind", default="rally", choices=("rally", *KINDS),
                        help="the shots: a rally's (the default), or another kind (KINDS) in the engine's physics")
    parser.add_argument("--magnus", type=float, default=MAGNUS,
                        help="MuJoCo's Magnus coefficient C_M (its fifth fluidcoef; at 1, MuJoCo's default, its lift is "
                             "1.6-1.9 times the textbook curve estim holds, at 0.76 about that curve's: MAGNUS)")
    parser.add_argument("--angular-drag", type=float, default=ANGULAR_DRAG,
                        help="MuJoCo's angular drag coefficient (its third fluidcoef; 1.5, MuJoCo's default, halves "
                             "300 rad/s in a quarter of a second: ANGULAR_DRAG)")
    args = parser.parse_args()
    rows = run(args.shots, args.seed, tuple(args.views), args.noise, args.engine, args.kind, args.magnus,
               args.angular_drag)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    print(table(rows))


if __name__ == "__main__":
    main()
