"""``estim bench speed``, ``bench fit`` and ``bench accuracy``: timings and the
work-precision study on the seed scene, measured in this process."""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from .. import _config
from .._json import dump
from ..fitting._job import fit_csv, fit_files, fit_image_csv, fit_pixels
from ..forward import _ode
from ..forward._dispatch import NATIVE, jax_planner, path
from ..forward._ode import OdeSettings
from ..forward._simulate import simulate, solve_closed_form, solve_ode
from ..forward._trajectory import check_keep
from ..model._params import Params
from ..model._scene import load_scene
from ..tracks._camera import Camera
from ..tracks._csv import write_tracks_csv
from ..tracks._synthetic import synthesize_tracks
from ._demo import DEMO_TRACKS, SEED, default_scene_path, seed_params
from ._event_loop import event_loop

__all__ = ["run_speed", "format_speed", "run_fit_bench", "format_fit_bench", "TARGETS", "REFERENCE",
           "run_accuracy", "format_accuracy", "plot_accuracy", "write_accuracy", "run_air_speed",
           "format_air_speed", "AIR_TARGETS"]

# Targets of the issue; "le" = at most, "lt" = below, "ge" = at least.
TARGETS = {
    "forward_us": ("le", 30.0),
    "gradient_us": ("le", 60.0),
    "first_call_s": ("lt", 0.5),
    "batch_balls_per_s": ("ge", 1e6),
}
# Reference figures quoted in the issue.
REFERENCE = {
    "forward_us": "hybrid simulator 4500 us; diffrax event loop 2500 us",
    "gradient_us": "hybrid simulator 78000 us; diffrax event loop 8400 us",
    "first_call_s": "-",
    "batch_balls_per_s": "-",
}

_SETUP = r"""
import json, sys, time
t0 = time.perf_counter()
import jax
import estim
t1 = time.perf_counter()
scene = estim.load_scene(sys.argv[1])
e = json.loads(sys.argv[2])
balls = [b for b in scene.balls if b.name in e]
params = estim.Params([e[b.name] for b in balls], [float(sys.argv[3])] * len(balls),
                      [b.radius for b in balls], [b.position for b in balls],
                      [json.loads(sys.argv[4])] * len(balls))
t_end = float(sys.argv[5])
t2 = time.perf_counter()
"""
_FIRST_CALL = _SETUP + r"""
traj = estim.simulate(scene, params, t_end)
jax.block_until_ready(traj)
t3 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_call_s": t3 - t2}))
"""
# The same first call under jit, by stages (JAX's ahead-of-time API): where its time goes.
_FIRST_CALL_PARTS = _SETUP + r"""
f = jax.jit(lambda p: estim.simulate(scene, p, t_end))
traced = f.trace(params)
t3 = time.perf_counter()
lowered = traced.lower()
t4 = time.perf_counter()
compiled = lowered.compile()
t5 = time.perf_counter()
jax.block_until_ready(compiled(params))
t6 = time.perf_counter()
print(json.dumps({"trace_s": t3 - t2, "lower_s": t4 - t3, "compile_s": t5 - t4, "run_s": t6 - t5}))
"""


def _median_us(fn, arg, repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        jax.block_until_ready(fn(arg))
    times = []
    for _ in range(max(repeats, 1)):
        t = time.perf_counter()
        jax.block_until_ready(fn(arg))
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e6


def _cached_env(cache_dir: str) -> dict:
    """The environment of a subprocess that measures a warm cache: this process's, with the
    persistent compilation cache at ``cache_dir`` even where ``ESTIM_NO_CACHE`` turns it off
    here (the test suite does)."""
    env = {k: v for k, v in os.environ.items() if k != "ESTIM_NO_CACHE"}
    env["ESTIM_CACHE_DIR"] = cache_dir
    return env


def _first_call(scene_path: str, cache_dir: str | None = None, script: str = _FIRST_CALL) -> dict:
    cmd = [
        sys.executable, "-c", script, scene_path, json.dumps(SEED["e"]),
        str(SEED["mu_t"]), json.dumps(list(SEED["velocity"])), str(SEED["t_end"]),
    ]
    env = _cached_env(cache_dir) if cache_dir else dict(os.environ)
    if cache_dir:
        cmd[2] = "import estim; estim.enable_compilation_cache(" + repr(cache_dir) + ")\n" + script
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"first-call subprocess failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _met(key: str, value: float) -> bool:
    op, target = TARGETS[key]
    return {"le": value <= target, "lt": value < target, "ge": value >= target}[op]


def restrict_cpus(n: int) -> None:
    """Let this process (and the processes it starts) run on its first ``n`` allowed CPUs,
    as ``taskset`` does. Only before JAX starts its backend: XLA sizes its thread pool to
    the CPUs the process may use when the backend starts."""
    if not hasattr(os, "sched_setaffinity"):
        raise ValueError("--cpus needs os.sched_setaffinity (Linux); use the whole machine instead")
    allowed = sorted(os.sched_getaffinity(0))
    if not 1 <= n <= len(allowed):
        raise ValueError(f"--cpus must lie in [1, {len(allowed)}] (the CPUs this process may use), got {n}")
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        raise ValueError("--cpus must be set before JAX starts its backend: run the bench in a fresh process")
    os.sched_setaffinity(0, allowed[:n])


def _cpus_used() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def run_speed(*, batch: int = 10_000, repeats: int = 200, scene_path: str | None = None,
              seed: int = 0, cpus: int | None = None, air: bool = True) -> dict:
    """Measure the figures of ``estim bench speed`` and return them as a dict (on ``cpus``
    CPUs if given: ``restrict_cpus``); with ``air``, also the air path against a plain
    diffrax event loop (:func:`run_air_speed`, under the key ``"air"``)."""
    if cpus is not None:
        restrict_cpus(cpus)
    scene_path = scene_path or default_scene_path()
    scene = load_scene(scene_path)
    # The figures are the seed experiment's (its balls, the golf ball's gradient and batch),
    # timed in a scene without air: say so before minutes of timing, not after.
    missing = [b for b in SEED["e"] if b not in {ball.name for ball in scene.balls}]
    wrong = ([f"it lacks {', '.join(missing)}"] if missing else []) + (["it has air"] if scene.air is not None else [])
    if wrong:
        raise ValueError(f"bench speed times the seed experiment, in a scene with its balls "
                         f"({', '.join(SEED['e'])}) and no air: {scene_path}: {'; '.join(wrong)}")
    # First: the fresh-process first call, before this process compiles anything; then the
    # same with JAX's persistent compilation cache (as the estim command uses it), warmed
    # by one run in another process.
    first = _first_call(scene_path)
    parts = _first_call(scene_path, script=_FIRST_CALL_PARTS)
    with tempfile.TemporaryDirectory() as cache:
        _first_call(scene_path, cache)
        first_cached = _first_call(scene_path, cache)

    t_end = SEED["t_end"]
    three = seed_params(scene)

    # Forward: 3 balls in one batched call. Jitted wrapper (what a user's jitted code
    # pays) and the plain call (adds estim's eager argument checks).
    forward = jax.jit(lambda p: simulate(scene, p, t_end))
    forward_us = _median_us(forward, three, repeats)
    eager_us = _median_us(lambda p: simulate(scene, p, t_end), three, max(repeats // 4, 3))
    # Its floor: a jitted function with the same arguments and results that computes
    # nothing (JAX's dispatch and argument handling, and a buffer for each result).
    shapes = jax.eval_shape(forward, three)
    empty = jax.jit(lambda p: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes))
    floor_us = _median_us(empty, three, repeats)

    # Gradient: d(golf final x)/d(e, mu_t, vx0), jacfwd, jitted. It uses the final state
    # only, so it keeps nothing else (keep=(), as the simulate docstring advises); the
    # same with every part kept is reported beside it.
    golf = scene.ball("golf")
    vel = SEED["velocity"]

    def final_x(theta, keep):
        e, mu_t, vx0 = theta
        p = Params(e, mu_t, golf.radius, jnp.asarray(golf.position),
                         jnp.stack([vx0, jnp.asarray(vel[1]), jnp.asarray(vel[2])]))
        return simulate(scene, p, t_end, keep=keep).final.position[0]

    grad = jax.jit(jax.jacfwd(lambda theta: final_x(theta, ())))
    theta = jnp.array([SEED["e"]["golf"], SEED["mu_t"], vel[0]])
    gradient_us = _median_us(grad, theta, repeats)
    gradient_value = np.asarray(grad(theta)).tolist()
    grad_all = jax.jit(jax.jacfwd(lambda theta: final_x(theta, None)))
    gradient_all_us = _median_us(grad_all, theta, repeats)

    # Batch: `batch` golf balls, e ~ U[0.3, 0.95], same release, simulated to t_end. The
    # figure held against the target keeps what a batch of simulations is for, each ball's
    # final state and completion (keep=()); the same batch keeping its event lists, and
    # keeping every part (samples, events, dense solution: the rows a call writes grow
    # from 60 bytes per ball to some 16 kB, and the call becomes bound by memory), is
    # timed beside it (docs/pages/speed.md).
    rng = np.random.default_rng(seed)
    e_batch = rng.uniform(0.3, 0.95, size=batch)
    many = Params(e_batch, SEED["mu_t"], golf.radius, golf.position, vel)
    batch_us, row_bytes = {}, {}
    for name, keep in (("final", ()), ("events", ("events",)), ("all", None)):
        # throw=False: a ball that needs more than max_segments is counted, not raised.
        call = jax.jit(lambda p, keep=keep: simulate(scene, p, t_end, throw=False, keep=keep))
        batch_us[name] = _median_us(call, many, max(min(repeats, 20), 3), warmup=1)
        traj = call(many)
        row_bytes[name] = traj.record.shape[-1] * traj.record.dtype.itemsize + traj.flags.shape[-1] * traj.flags.dtype.itemsize
        if name == "final":
            incomplete = int(np.sum(~np.asarray(traj.complete)))

    result = {
        "forward_us": forward_us,
        "forward_eager_us": eager_us,
        "forward_floor_us": floor_us,
        "gradient_us": gradient_us,
        "gradient_all_us": gradient_all_us,
        "gradient": dict(zip(("e", "mu_t", "vx0"), gradient_value, strict=True)),
        "first_call_s": first["first_call_s"],
        "first_call_cached_s": first_cached["first_call_s"],
        "first_call_parts_s": parts,
        "import_s": first["import_s"],
        "batch": batch,
        "batch_final_us": batch_us["final"],
        "batch_events_us": batch_us["events"],
        "batch_all_us": batch_us["all"],
        "batch_balls_per_s": batch / (batch_us["final"] * 1e-6),
        "batch_events_balls_per_s": batch / (batch_us["events"] * 1e-6),
        "batch_all_balls_per_s": batch / (batch_us["all"] * 1e-6),
        "batch_row_bytes": row_bytes,
        "batch_incomplete": incomplete,
        "repeats": repeats,
    }
    result["targets"] = {
        key: {"target": f"{'<=' if op == 'le' else '<' if op == 'lt' else '>='} {target:g}",
              "met": bool(_met(key, result[key]))}
        for key, (op, target) in TARGETS.items()
    }
    result["reference"] = dict(REFERENCE)
    result["machine"] = {
        "cpu_count": os.cpu_count(),
        # The CPUs this process may run on (``--cpus``); XLA's thread pool has as many threads.
        "cpus_used": _cpus_used(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        # Whether XLA compiles small loops into one kernel (estim._config): off when JAX's
        # backend started before estim was imported, or XLA_FLAGS set its own threshold.
        "small_loops_as_kernels": bool(_config.SMALL_LOOPS_AS_KERNELS),
        # Whether JAX runs programs on the calling thread (estim._config, DISPATCH).
        "sync_dispatch": bool(_config.dispatch_is_sync()),
        # Whether the closed-form primal ran on the native kernels (estim.forward._dispatch):
        # built at install, not switched off with ESTIM_NATIVE=0, JAX's backend is the CPU.
        "native": path(scene) == NATIVE,
    }
    result["exact"] = run_exact_speed(scene, scene_path, repeats)
    if air:
        result["air"] = run_air_speed(repeats=min(repeats, 100))
    return result


# The seed forward on the same staircase with exact edges and corners (the issue of exact
# geometry): within 1.5 times the seed scene's forward, in the same process.
EXACT_TARGET = 1.5


def run_exact_speed(scene, scene_path: str, repeats: int) -> dict:
    """The seed forward (3 balls, jitted) on ``stairs_exact.xml`` against the same on the seed
    scene, both on their path (the native kernels, where built), and on the seed scene on
    the JAX planner, timed in alternating rounds in this process."""
    exact = load_scene(os.path.join(os.path.dirname(scene_path), "stairs_exact.xml"))
    t_end = SEED["t_end"]
    three = seed_params(scene)
    seed = jax.jit(lambda p: simulate(scene, p, t_end))
    on_exact = jax.jit(lambda p: simulate(exact, p, t_end))
    seed_jax = jax.jit(lambda p: simulate(scene, p, t_end))
    with jax_planner():  # traced here, it keeps that path
        jax.block_until_ready(seed_jax(three))
    us = _alternating_us({"seed": lambda: seed(three), "exact": lambda: on_exact(three),
                          "seed_jax": lambda: seed_jax(three)}, max(repeats // 2, 5))
    return {"seed_us": us["seed"], "seed_jax_us": us["seed_jax"], "exact_us": us["exact"],
            "ratio": us["exact"] / us["seed"], "ratio_jax": us["exact"] / us["seed_jax"],
            "target": EXACT_TARGET, "met": bool(us["exact"] / us["seed"] <= EXACT_TARGET)}


def format_exact_speed(x: dict) -> str:
    return (f"exact geometry (stairs_exact.xml), seed forward 3 balls: {x['exact_us']:.1f} us/call "
            f"against {x['seed_us']:.1f} us on stairs.xml ({x['ratio']:.2f}x; target <= {x['target']:g}x: "
            f"{'met' if x['met'] else 'NOT met'}) and {x['seed_jax_us']:.1f} us on stairs.xml on the JAX planner "
            f"({x['ratio_jax']:.2f}x)")


def format_speed(r: dict) -> str:
    t = r["targets"]

    def row(name, value, key):
        met = "met" if t[key]["met"] else "NOT met"
        return f"{name:<34} {value:>16} {t[key]['target']:>12} {met:>8}   {REFERENCE[key]}"

    lines = [
        f"{'metric':<34} {'measured':>16} {'target':>12} {'status':>8}   reference",
        row("forward, 3 balls (us/call, jit)", f"{r['forward_us']:.1f}", "forward_us"),
        row("gradient, jacfwd, keep=() (us, jit)", f"{r['gradient_us']:.1f}", "gradient_us"),
        row("first call, fresh process (s)", f"{r['first_call_s']:.3f}", "first_call_s"),
        row(f"batch {r['batch']} golf, final states (balls/s)", f"{r['batch_balls_per_s']:.3g}", "batch_balls_per_s"),
        "",
        f"first call with the persistent compilation cache warm: {r['first_call_cached_s']:.3f} s",
        "first call under jit, by stages (fresh process): "
        + ", ".join(f"{k[:-2]} {v:.3f} s" for k, v in r["first_call_parts_s"].items()),
        f"forward floor (a jitted call with the same arguments and results, computing nothing): "
        f"{r['forward_floor_us']:.1f} us/call",
        f"forward without jit (simulate, eager checks): {r['forward_eager_us']:.1f} us/call",
        f"gradient keeping every part (keep=None): {r['gradient_all_us']:.1f} us/call",
        f"batch of {r['batch']}, final states (keep=()): {r['batch_final_us']:.0f} us/call, "
        f"{r['batch_row_bytes']['final']} bytes per ball ({r['batch_incomplete']} balls incomplete within max_segments); "
        f"keeping the events (keep=('events',)): {r['batch_events_us']:.0f} us/call, "
        f"{r['batch_events_balls_per_s']:.3g} balls/s, {r['batch_row_bytes']['events']} bytes per ball; "
        f"keeping every part (the default): {r['batch_all_us']:.0f} us/call, {r['batch_all_balls_per_s']:.3g} balls/s, "
        f"{r['batch_row_bytes']['all']} bytes per ball",
        f"import estim: {r['import_s']:.2f} s",
        "gradient d(golf final x)/d(e, mu_t, vx0) = "
        + ", ".join(f"{v:.8f}" for v in r["gradient"].values()),
        f"machine: {r['machine']['cpu_count']} CPUs ({r['machine'].get('cpus_used', r['machine']['cpu_count'])} used), "
        f"{r['machine']['processor']}, "
        f"jax {r['machine']['jax']} ({r['machine']['backend']}); median of {r['repeats']} calls; "
        f"small loops as one kernel: {'yes' if r['machine'].get('small_loops_as_kernels') else 'NO'}; "
        f"programs run on the calling thread: {'yes' if r['machine'].get('sync_dispatch') else 'NO'}; "
        f"native kernels: {'yes' if r['machine'].get('native') else 'NO (the JAX planner)'}",
    ]
    if "exact" in r:
        lines += ["", format_exact_speed(r["exact"])]
    if "air" in r:
        lines += ["", format_air_speed(r["air"])]
    return "\n".join(lines)


# ------------------------------------------------------------------ the air path, side by side

# Targets of the air-path issue: estim at least as fast as the plain diffrax loop in the same
# process (forward, 3 balls; its jacfwd against the loop's jax.grad) and within 1e-9 m of
# the reference; a table-tennis shot in air (its forward, and the Jacobian of its positions
# sampled at 180 Hz with respect to e, mu_t and the release position, velocity and spin: the
# spin issue's figure); the first call of the air path.
AIR_TARGETS = {
    "forward_ratio": ("le", 1.0),
    "final_position_error": ("le", 1e-9),
    "gradient_ratio": ("le", 1.0),
    "shot_forward_us": ("le", 100.0),
    "shot_jacobian_us": ("le", 1000.0),
    "first_call_s": ("le", 2.0),
}
SHOT_RATE = 180.0  # Hz: the shot's samples for its Jacobian, as a tracker gives them
# A table-tennis shot over the table of drop_air.xml: 40 mm, 2.7 g, 4.5 m/s with topspin,
# one bounce, 0.42 s.
SHOT = {"scene": "drop_air.xml", "ball": "pingpong", "position": (-0.9, 0.0, 0.25), "velocity": (4.5, 0.0, 0.6),
        "spin": (0.0, 120.0, 0.0), "e": 0.88, "mu_t": 0.75, "t_end": 0.42}
_AIR_FIRST_CALL = r"""
import json, sys, time
t0 = time.perf_counter()
import jax
import estim
from estim.app._demo import seed_params
scene = estim.load_scene(sys.argv[1])
params = seed_params(scene)
t1 = time.perf_counter()
jax.block_until_ready(estim.simulate(scene, params, float(sys.argv[2])))
print(json.dumps({"first_call_s": time.perf_counter() - t1}))
"""


def shot_params(scene) -> Params:
    """The table-tennis shot of ``SHOT`` as a batch of one ball of ``scene``."""
    p = Params.for_ball(scene, SHOT["ball"], e=SHOT["e"], mu_t=SHOT["mu_t"], position=SHOT["position"],
                        velocity=SHOT["velocity"], spin=SHOT["spin"])
    return jax.tree.map(lambda x: jnp.asarray(x)[None], p)


def _with_theta(params, ball, theta):
    """``params`` with ball ``ball``'s (e, mu_t, vx0) set to ``theta``."""
    return dataclasses.replace(params, e=params.e.at[ball].set(theta[0]), mu_t=params.mu_t.at[ball].set(theta[1]),
                               velocity=params.velocity.at[ball, 0].set(theta[2]))


def _alternating_us(fns: dict, repeats: int) -> dict:
    """Median time (us) of each zero-argument call of ``fns``, all timed once per round."""
    for fn in fns.values():
        jax.block_until_ready(fn())
    times = {k: [] for k in fns}
    for _ in range(max(int(repeats), 1)):
        for key, fn in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(fn())
            times[key].append(time.perf_counter() - t)
    return {k: statistics.median(v) * 1e6 for k, v in times.items()}


def run_air_speed(*, repeats: int = 100) -> dict:
    """The air path (``estim.forward._ode``) against a plain diffrax event loop
    (``estim.app._event_loop``) in this process: the seed's three balls in still air
    (data/scenes/stairs_air.xml, 2.3 s) forward, and the golf ball's d x_final / d(e, mu_t,
    vx0) (estim: ``jacfwd``; the loop: ``jax.grad``), with errors against a tight reference
    (Dopri8 at rtol 1e-13); a table-tennis shot (``SHOT``) forward, and the Jacobian
    (``jacfwd``) of its positions at ``SHOT_RATE`` with respect to its 11 parameters (e,
    mu_t, release position, velocity, spin); the first call of the air path in a fresh
    process."""
    scenes_dir = os.path.dirname(default_scene_path())
    air_path = os.path.join(scenes_dir, "stairs_air.xml")
    first = _first_call_air(air_path)
    scene = load_scene(air_path)
    params = seed_params(scene)
    t_end = SEED["t_end"]
    ref = simulate(scene, params, t_end, solver=diffrax.Dopri8(), rtol=1e-13, atol=1e-14, keep=("events",))
    forward = jax.jit(lambda p: simulate(scene, p, t_end, keep=()).final.position)
    events = simulate(scene, params, t_end, keep=("events",)).events
    loop = jax.jit(lambda p: event_loop(scene, p, t_end))
    golf = 1
    theta = jnp.array([params.e[golf], params.mu_t[golf], params.velocity[golf, 0]])
    grad_estim = jax.jit(jax.jacfwd(
        lambda th: simulate(scene, _with_theta(params, golf, th), t_end, keep=()).final.position[golf, 0]))
    grad_loop = jax.jit(jax.grad(lambda th: event_loop(scene, _with_theta(params, golf, th), t_end)[0][golf, 0]))

    shot_scene = load_scene(os.path.join(scenes_dir, SHOT["scene"]))
    shot = shot_params(shot_scene)
    shot_forward = jax.jit(lambda p: simulate(shot_scene, p, SHOT["t_end"], keep=()).final.position)
    shot_loop = jax.jit(lambda p: event_loop(shot_scene, p, SHOT["t_end"])[0])
    times = _alternating_us({
        "forward": lambda: forward(params), "loop_forward": lambda: loop(params)[0],
        "gradient": lambda: grad_estim(theta), "loop_gradient": lambda: grad_loop(theta),
        "shot": lambda: shot_forward(shot), "shot_loop": lambda: shot_loop(shot),
    }, repeats)

    # The shot's absolute figure as the seed's forward is timed (consecutive calls, warm);
    # the rounds above alternate six programs, which also measures them with cold caches.
    shot_alone_us = _median_us(lambda p: shot_forward(p), shot, repeats)
    shot_ts = jnp.arange(0.0, SHOT["t_end"], 1.0 / SHOT_RATE)

    def shot_positions(th):
        p = dataclasses.replace(shot, e=th[0:1], mu_t=th[1:2], position=th[None, 2:5], velocity=th[None, 5:8],
                                spin=th[None, 8:11])
        return simulate(shot_scene, p, SHOT["t_end"], ts=shot_ts, keep=("samples",)).position[0]

    shot_theta = jnp.concatenate([shot.e, shot.mu_t, shot.position[0], shot.velocity[0], shot.spin[0]])
    shot_jacobian = jax.jit(jax.jacfwd(shot_positions))
    shot_jacobian_us = _median_us(shot_jacobian, shot_theta, repeats)
    loop_final, _, loop_times = loop(params)
    ref_final = np.asarray(ref.final.position)
    ref_counts = np.asarray(ref.events.count)
    shot_ref = simulate(shot_scene, shot, SHOT["t_end"], solver=diffrax.Dopri8(), rtol=1e-13, atol=1e-14,
                        keep=("events",))
    result = {
        "forward_us": times["forward"], "loop_forward_us": times["loop_forward"],
        "forward_ratio": times["forward"] / times["loop_forward"],
        "final_position_error": float(np.max(np.linalg.norm(np.asarray(forward(params)) - ref_final, axis=1))),
        "loop_final_position_error": float(np.max(np.linalg.norm(np.asarray(loop_final) - ref_final, axis=1))),
        "events": np.asarray(events.count).tolist(),
        "loop_events": np.sum(np.isfinite(np.asarray(loop_times)), axis=1).tolist(),
        "reference_events": ref_counts.tolist(),
        "gradient_us": times["gradient"], "loop_gradient_us": times["loop_gradient"],
        "gradient_ratio": times["gradient"] / times["loop_gradient"],
        "gradient": np.asarray(grad_estim(theta)).tolist(), "loop_gradient": np.asarray(grad_loop(theta)).tolist(),
        "shot_forward_us": shot_alone_us, "shot_forward_alternating_us": times["shot"],
        "shot_jacobian_us": shot_jacobian_us,
        "shot_jacobian_shape": list(jax.eval_shape(shot_jacobian, shot_theta).shape),
        "shot_loop_forward_us": times["shot_loop"],
        "shot_events": int(np.asarray(shot_ref.events.count)[0]),
        "shot_final_position_error": float(np.linalg.norm(np.asarray(shot_forward(shot))[0]
                                                          - np.asarray(shot_ref.final.position)[0])),
        "first_call_s": first["first_call_s"],
        "settings": dict(DEFAULT_SETTING),
        "repeats": int(repeats),
    }
    result["targets"] = {
        key: {"target": f"{'<=' if op == 'le' else '<' if op == 'lt' else '>='} {target:g}",
              "met": bool({"le": result[key] <= target, "lt": result[key] < target,
                           "ge": result[key] >= target}[op])}
        for key, (op, target) in AIR_TARGETS.items()
    }
    return result


def _first_call_air(scene_path: str) -> dict:
    cmd = [sys.executable, "-c", _AIR_FIRST_CALL, scene_path, str(SEED["t_end"])]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, env=dict(os.environ))
    if proc.returncode != 0:
        raise RuntimeError(f"first-call subprocess failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def format_air_speed(r: dict) -> str:
    t = r["targets"]

    def status(key):
        return f"{t[key]['target']:>9} {'met' if t[key]['met'] else 'NOT met':>8}"

    return "\n".join([
        "The air path (seed staircase in still air, 3 balls, 2.3 s; estim's defaults "
        f"{r['settings']['solver']} rtol {r['settings']['rtol']:g}) against a plain diffrax event loop "
        "(Tsit5, PID rtol 1e-8 atol 1e-9, dtmax 0.004, Event + Newton, restarted per contact, vmapped), "
        "same process, alternating rounds:",
        f"{'metric':<44} {'estim':>10} {'loop':>10} {'ratio':>7} {'target':>9} {'status':>8}",
        f"{'forward, 3 balls (us)':<44} {r['forward_us']:>10.0f} {r['loop_forward_us']:>10.0f} "
        f"{r['forward_ratio']:>7.2f} {status('forward_ratio')}",
        f"{'final position error vs reference (m)':<44} {r['final_position_error']:>10.1e} "
        f"{r['loop_final_position_error']:>10.1e} {'':>7} {status('final_position_error')}",
        f"{'gradient, golf (us; estim jacfwd, loop grad)':<44} {r['gradient_us']:>10.0f} {r['loop_gradient_us']:>10.0f} "
        f"{r['gradient_ratio']:>7.2f} {status('gradient_ratio')}",
        f"{'table-tennis shot forward, in turn (us)':<44} {r['shot_forward_alternating_us']:>10.1f} "
        f"{r['shot_loop_forward_us']:>10.1f} {r['shot_forward_alternating_us'] / r['shot_loop_forward_us']:>7.2f}",
        f"{'table-tennis shot forward, alone (us)':<44} {r['shot_forward_us']:>10.1f} {'':>10} {'':>7} "
        f"{status('shot_forward_us')}",
        f"{'table-tennis shot Jacobian, alone (us)':<44} {r['shot_jacobian_us']:>10.1f} {'':>10} {'':>7} "
        f"{status('shot_jacobian_us')}",
        f"{'first call, fresh process (s)':<44} {r['first_call_s']:>10.2f} {'':>10} {'':>7} {status('first_call_s')}",
        "(in turn: the six programs timed once per round, for the ratios; alone: consecutive calls, as the "
        "forward figure of the table above)",
        f"contacts per ball: estim {r['events']}, loop {r['loop_events']}, reference {r['reference_events']}; "
        f"shot: {r['shot_events']} bounce(s), error {r['shot_final_position_error']:.1e} m, Jacobian of its "
        f"{r['shot_jacobian_shape'][0]} positions at {SHOT_RATE:g} Hz w.r.t. e, mu_t, release position, velocity "
        "and spin (jacfwd); "
        "gradients: estim " + ", ".join(f"{v:.8f}" for v in r["gradient"])
        + "; loop " + ", ".join(f"{v:.8f}" for v in r["loop_gradient"]) + f"; median of {r['repeats']} rounds",
    ])


# --------------------------------------------------------------------------- bench fit

FIT_TARGETS = {"cli_cold_s": 15.0, "cli_warm_s": 15.0, "steady_s": 0.5, "shot_cli_cold_s": 8.0, "shot_steady_s": 0.2,
               "camera_cli_json_s": 8.0, "camera_steady_s": 0.3}
# A 3D table-tennis shot on data/scenes/table_tennis.xml (a drive with topspin and sidespin,
# one bounce on the table, in air), tracked at 180 Hz with 2 mm noise for 0.65 s: the
# real-ball fit of the spin issue, with the scene's defaults.
TABLE_SHOT = {"scene": "table_tennis.xml", "ball": "pingpong", "e": 0.90, "mu": 0.12, "position": (0.2, -1.6, 0.2),
              "velocity": (-0.3, 8.0, 2.0), "spin": (-150.0, 10.0, 20.0), "t_end": 0.65, "rate": 180.0,
              "noise": 0.002}
# The same shot filmed from the side (the camera issue's one camera, one shot of about 15
# frames): 25 fps for 0.6 s, a camera 3.2 m beside the table at 1500 px focal length, 2 px
# of noise, fitted with `estim fit TRACK --camera CAM`.
CAMERA_SHOT = {"fps": 25.0, "t_end": 0.6, "noise_px": 2.0, "position": (3.2, 0.0, 0.8), "target": (0.0, 0.0, 0.1),
               "focal": 1500.0, "size": (1920, 1080)}


def _cli_fit_seconds(tracks: str, scene_path: str, out: str | None, env: dict, options: tuple[str, ...] = ()) -> float:
    """Seconds of ``estim fit`` in a fresh process, writing fit.json and the plots to ``out``,
    or with ``out=None`` printing the JSON only (``--json``: no plots drawn)."""
    written = ("--out", out) if out is not None else ("--json",)
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "estim", "fit", tracks, "--scene", scene_path, *written, *options],
        capture_output=True, text=True, env=env, check=False,
    )
    seconds = time.perf_counter() - t
    try:
        done = os.path.isfile(os.path.join(out, "fit.json")) if out is not None else bool(json.loads(proc.stdout))
    except json.JSONDecodeError:
        done = False
    if proc.returncode not in (0, 1) or not done:
        raise RuntimeError(f"estim fit failed:\n{proc.stderr[-2000:]}")
    return seconds


def _shot_path(t: np.ndarray) -> tuple[str, np.ndarray]:
    """``TABLE_SHOT``'s scene path and its true positions at the times ``t``."""
    s = TABLE_SHOT
    scene_path = os.path.join(os.path.dirname(default_scene_path()), s["scene"])
    scene = load_scene(scene_path)
    p = Params.for_ball(scene, s["ball"], e=s["e"], mu_t=1.0, mu=s["mu"], position=s["position"],
                        velocity=s["velocity"], spin=s["spin"])
    return scene_path, np.asarray(simulate(scene, p, s["t_end"], ts=t).position)


def _table_shot(path: str) -> str:
    """Write ``TABLE_SHOT``'s track (``t,ball,x,y,z``) to ``path``; returns its scene's path."""
    s = TABLE_SHOT
    t = np.arange(0.0, s["t_end"], 1.0 / s["rate"])
    scene_path, pos = _shot_path(t)
    pos = pos + np.random.default_rng(0).normal(0.0, s["noise"], pos.shape)
    with open(path, "w") as f:
        f.write("t,ball,x,y,z\n" + "".join(f"{a:.6f},{s['ball']},{x:.5f},{y:.5f},{z:.5f}\n"
                                           for a, (x, y, z) in zip(t, pos, strict=True)))
    return scene_path


def camera_shot(folder: str) -> tuple[str, str]:
    """Write ``TABLE_SHOT`` as ``CAMERA_SHOT``'s camera sees it into ``folder``: the pixel
    track ``shot_px.csv`` (``t,ball,u,v``) and the camera ``side.json`` (OpenCV's terms).
    Returns their paths."""
    c = CAMERA_SHOT
    t = np.arange(0.0, c["t_end"] - 0.5 / c["fps"], 1.0 / c["fps"])
    _, pos = _shot_path(t)
    camera = Camera.look_at(c["position"], c["target"], focal=c["focal"], size=c["size"], name="side")
    uv = np.asarray(camera.project(pos)) + np.random.default_rng(0).normal(0.0, c["noise_px"], (t.size, 2))
    track, camera_path = os.path.join(folder, "shot_px.csv"), os.path.join(folder, "side.json")
    with open(track, "w") as f:
        f.write("t,ball,u,v\n" + "".join(f"{a:.6f},{TABLE_SHOT['ball']},{u:.3f},{v:.3f}\n"
                                         for a, (u, v) in zip(t, uv, strict=True)))
    with open(camera_path, "w") as f:
        json.dump(camera.to_json(), f)
    return track, camera_path


def _steady(fit, repeats: int):
    """Median seconds of ``fit()`` compiled (after one call), and the last result."""
    fit()
    times = []
    for _ in range(max(repeats, 1)):
        t = time.perf_counter()
        result, _ = fit()
        times.append(time.perf_counter() - t)
    return statistics.median(times), result


def run_fit_bench(*, repeats: int = 5, scene_path: str | None = None) -> dict:
    """``estim fit`` from process start to written fit.json, without and with a warm
    compilation cache, and the steady-state (compiled) fit in-process: on the bundled tracks;
    on a table-tennis shot in air (``TABLE_SHOT``, without a cache and compiled); and on the
    same shot through one camera (``CAMERA_SHOT``, without a cache, and compiled as many
    shots in one process run it)."""

    scene_path = scene_path or default_scene_path()
    tracks = str(DEMO_TRACKS)
    with tempfile.TemporaryDirectory() as tmp:
        cold_env = dict(os.environ, ESTIM_NO_CACHE="1")
        cold = _cli_fit_seconds(tracks, scene_path, os.path.join(tmp, "cold"), cold_env)
        warm_env = _cached_env(os.path.join(tmp, "cache"))
        _cli_fit_seconds(tracks, scene_path, os.path.join(tmp, "fill"), warm_env)
        warm = _cli_fit_seconds(tracks, scene_path, os.path.join(tmp, "warm"), warm_env)
        shot_track = os.path.join(tmp, "shot.csv")
        shot_scene = _table_shot(shot_track)
        shot_cold = _cli_fit_seconds(shot_track, shot_scene, os.path.join(tmp, "shot"), cold_env)
        table = load_scene(shot_scene)
        # Compiled: the optimised program a process that fits many shots ends on
        # (estim._config.FIT_ODE_TIER_UP), from the first fit.
        with _config.optimised_programs():
            shot_steady, shot = _steady(lambda: fit_csv(shot_track, table), repeats)
        pixels, camera = camera_shot(tmp)
        # The camera issue's command (`estim fit TRACK --camera CAM --scene SCENE --json`),
        # and the same writing fit.json and its plots.
        camera_json = _cli_fit_seconds(pixels, shot_scene, None, cold_env, ("--camera", camera))
        camera_cold = _cli_fit_seconds(pixels, shot_scene, os.path.join(tmp, "camera"), cold_env, ("--camera", camera))
        with _config.optimised_programs():
            camera_steady, seen = _steady(lambda: fit_image_csv(pixels, [camera], table), repeats)

    scene = load_scene(scene_path)
    steady, result = _steady(lambda: fit_csv(tracks, scene), repeats)
    fitted, viewed = shot.balls[TABLE_SHOT["ball"]], seen.balls[TABLE_SHOT["ball"]]
    _, truth = _shot_path(viewed.model_t)
    out = {"cli_cold_s": cold, "cli_warm_s": warm, "steady_s": steady,
           "e": {b: f.values["e"] for b, f in result.balls.items()},
           "shot_cli_cold_s": shot_cold, "shot_steady_s": shot_steady,
           "shot": {"e": fitted.values["e"], "mu": fitted.values["mu"], "rms_mm": 1e3 * fitted.rms_m,
                    "true_e": TABLE_SHOT["e"], "true_mu": TABLE_SHOT["mu"], "noise_mm": 1e3 * TABLE_SHOT["noise"]},
           "camera_cli_json_s": camera_json, "camera_cli_cold_s": camera_cold, "camera_steady_s": camera_steady,
           "camera": {"e": viewed.values["e"], "rms_px": viewed.rms_m, "noise_px": CAMERA_SHOT["noise_px"],
                      "frames": int(viewed.model_t.size),
                      "path_error_mm": 1e3 * float(np.mean(np.linalg.norm(viewed.model_position - truth, axis=1)))}}
    out["targets"] = {k: {"target": f"< {v:g} s", "met": bool(out[k] < v)} for k, v in FIT_TARGETS.items()}
    return out


def format_fit_bench(r: dict) -> str:
    t = r["targets"]
    rows = [f"{'metric':<52} {'measured':>10} {'target':>9} {'status':>8}"]
    for key, name in (("cli_cold_s", "estim fit, bundled tracks, fresh process, no cache (s)"),
                      ("cli_warm_s", "estim fit, fresh process, compilation cache warm (s)"),
                      ("steady_s", "fit, compiled, in-process (s)"),
                      ("shot_cli_cold_s", "estim fit, table-tennis shot, fresh, no cache (s)"),
                      ("shot_steady_s", "fit of the shot, compiled, in-process (s)"),
                      ("camera_cli_json_s", "estim fit --camera --json, 25 fps shot, fresh (s)"),
                      ("camera_cli_cold_s", "the same with --out (fit.json, plots), fresh (s)"),
                      ("camera_steady_s", "fit of the camera shot, compiled, in-process (s)")):
        target, status = (t[key]["target"], "met" if t[key]["met"] else "NOT met") if key in t else ("", "")
        rows.append(f"{name:<52} {r[key]:>10.2f} {target:>9} {status:>8}")
    rows.append("fitted e: " + ", ".join(f"{b} {v:.4f}" for b, v in r["e"].items()))
    s = r["shot"]
    rows.append(f"shot: e {s['e']:.4f} (true {s['true_e']}), mu {s['mu']:.4f} (true {s['true_mu']}), "
                f"rms {s['rms_mm']:.2f} mm (noise {s['noise_mm']:.1f} mm)")
    c = r["camera"]
    rows.append(f"camera shot ({c['frames']} frames): e {c['e']:.4f} (true {TABLE_SHOT['e']}), 3-D path "
                f"{c['path_error_mm']:.1f} mm from the truth on average, rms {c['rms_px']:.2f} px "
                f"(noise {c['noise_px']:.1f} px)")
    return "\n".join(rows)


# --------------------------------------------------------------------------- bench clips

# `estim bench clips`: many clips fitted together (estim.fitting._pooled). Targets for the
# staircase clips on a 2-core machine: from process start without a compilation cache, and
# compiled.
CLIPS_TARGETS = {"stairs_cli_cold_s": 30.0, "stairs_compiled_s": 3.0}
PIXEL_SCALE = 1.5e-3  # m/px of the synthetic pixel clips (about the real table drops')


def _stairs_clips(folder: str, n: int, scene, first: int = 0) -> list[str]:
    """``n`` tracks CSVs of the bundled staircase (its three balls at the seed's e, each
    clip with its own release speed and noise draw: 60 fps, 2 mm, 5% dropped frames),
    clips ``first``, ``first + 1``, ... of one sequence."""
    paths = []
    rng = np.random.default_rng(0)
    rng.uniform(-0.05, 0.05, first)
    for k in range(first, first + n):
        vx = SEED["velocity"][0] + rng.uniform(-0.05, 0.05)
        truth = {b: {"e": e, "mu_t": SEED["mu_t"], "vx0": vx} for b, e in SEED["e"].items()}
        tracks = synthesize_tracks(scene, truth, seed=k, n_outliers=0)
        paths.append(os.path.join(folder, f"stairs-{k:03d}.csv"))
        write_tracks_csv(paths[-1], tracks, digits=5)
    return paths


def _pixel_clips(folder: str, n: int, scene, seed: int = 1) -> list[str]:
    """``n`` pixel tracks (``a;b;`` lines) of the size of the real table drops: the drop
    scene's ping-pong ball (e = 0.82) dropped from about 1 m, 300 frames at 100 fps,
    ``PIXEL_SCALE`` m/px, 0.5 px noise; ``seed`` draws them."""
    rng = np.random.default_rng(seed)
    ts = np.arange(300) / 100.0
    paths = []
    for k in range(n):
        p = Params.for_ball(scene, "pingpong", e=0.82, mu_t=0.9, position=(0.0, 0.0, rng.uniform(0.9, 1.1)),
                            velocity=(rng.uniform(-0.1, 0.1), 0.0, 0.0))
        pos = np.asarray(simulate(scene, p, float(ts[-1]), ts=ts).position)
        a = 600.0 + pos[:, 0] / PIXEL_SCALE + rng.normal(0, 0.5, len(ts))
        b = 1830.0 - pos[:, 2] / PIXEL_SCALE + rng.normal(0, 0.5, len(ts))
        paths.append(os.path.join(folder, f"drop-{seed}-{k:03d}.txt"))
        with open(paths[-1], "w") as f:
            f.writelines(f"{x:.2f};{y:.2f};\n" for x, y in zip(a, b, strict=True))
    return paths


def _cli_seconds(argv: list[str], env: dict) -> float:
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "estim", *argv], capture_output=True, text=True, env=env,
                          check=False)
    if proc.returncode not in (0, 1):
        raise RuntimeError(f"estim {' '.join(argv[:3])} ... failed:\n{proc.stderr[-2000:]}")
    return time.perf_counter() - t


def _timed(fn) -> tuple[float, object]:
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def run_clips_bench(*, n: int = 100) -> dict:
    """``estim fit`` of ``n`` staircase clips (3 balls each, e shared per ball) and of ``n``
    pixel drops (e shared) together: from process start without a compilation cache, and
    compiled in-process; beside them one clip's single fit, compiled, in the same process."""
    stairs_path = default_scene_path()
    drop_path = os.path.join(os.path.dirname(stairs_path), "drop.xml")
    stairs, drop = load_scene(stairs_path), load_scene(drop_path)
    cold_env = dict(os.environ, ESTIM_NO_CACHE="1")
    pixel_options = dict(pixels=True, ball="pingpong", frame_interval=0.01)
    out = {"n_clips": n, "devices": len(jax.devices())}
    with tempfile.TemporaryDirectory() as tmp:
        csvs, pixels = _stairs_clips(tmp, n, stairs), _pixel_clips(tmp, n, drop)
        out["stairs_cli_cold_s"] = _cli_seconds(["fit", *csvs, "--scene", stairs_path, "--shared", "e"], cold_env)
        out["pixels_cli_cold_s"] = _cli_seconds(
            ["fit", *pixels, "--scene", drop_path, "--shared", "e", "--pixels", "--ball", "pingpong",
             "--frame-interval", "0.01"], cold_env)
        # Compiled: the programs compiled on other clips of the same sizes, timed on these
        # (a repeat on the same files would find the units' checks cached).
        warm = {"stairs": _stairs_clips(tmp, n, stairs, first=n), "pixels": _pixel_clips(tmp, n, drop, seed=2)}
        for key, scene, files, options in (("stairs", stairs, csvs, {}), ("pixels", drop, pixels, pixel_options)):
            fit_files(warm[key], scene, shared=("e",), **options)  # compile
            out[f"{key}_compiled_s"], result = _timed(lambda s=scene, f=files, o=options: fit_files(f, s, shared=("e",), **o))
            if options:
                fit_pixels(warm[key][1], scene, ball="pingpong", frame_interval=0.01)
                out[f"{key}_single_s"], _ = _timed(lambda s=scene, f=files: fit_pixels(f[0], s, ball="pingpong",
                                                                                       frame_interval=0.01))
            else:
                fit_csv(warm[key][1], scene)
                out[f"{key}_single_s"], _ = _timed(lambda s=scene, f=files: fit_csv(f[0], s))
            out[f"{key}_per_clip_s"] = out[f"{key}_compiled_s"] / n
            out[f"{key}_shared"] = {g: {"e": sf.values["e"], "stderr": sf.stderr["e"]}
                                    for g, sf in result[0].shared.items()}
    out["targets"] = {k: {"target": f"< {v:g} s", "met": bool(out[k] < v)} for k, v in CLIPS_TARGETS.items()}
    return out


def format_clips_bench(r: dict) -> str:
    n = r["n_clips"]
    rows = [f"{'metric':<62} {'measured':>10} {'target':>9} {'status':>8}"]
    for key, name in (("stairs_cli_cold_s", f"estim fit, {n} staircase clips (3 balls), fresh process, no cache"),
                      ("stairs_compiled_s", f"the same {n} clips together, compiled, in-process"),
                      ("stairs_single_s", "one staircase clip alone, compiled, in-process"),
                      ("pixels_cli_cold_s", f"estim fit --pixels, {n} drop clips, fresh process, no cache"),
                      ("pixels_compiled_s", f"the same {n} pixel clips together, compiled, in-process"),
                      ("pixels_single_s", "one pixel clip alone, compiled, in-process")):
        t = r["targets"].get(key)
        target, status = (t["target"], "met" if t["met"] else "NOT met") if t else ("", "")
        rows.append(f"{name + ' (s)':<62} {r[key]:>10.2f} {target:>9} {status:>8}")
    for key in ("stairs", "pixels"):
        ratio = r[f"{key}_per_clip_s"] / r[f"{key}_single_s"]
        rows.append(f"{key}: per clip {r[f'{key}_per_clip_s'] * 1e3:.1f} ms together against "
                    f"{r[f'{key}_single_s'] * 1e3:.1f} ms alone ({ratio:.2f}x); shared e "
                    + ", ".join(f"{g} {v['e']:.4f} +- {v['stderr']:.4f}" for g, v in r[f"{key}_shared"].items()))
    rows.append(f"devices: {r['devices']}")
    return "\n".join(rows)


# --------------------------------------------------------------------------- bench accuracy

# The work-precision study of `estim bench accuracy`. Its docs page (docs/pages/accuracy.md,
# .json, .png) is written by docs/scripts/accuracy.py, which calls run_accuracy and the
# formatters below: the package writes only where it is told to (--out).
ACCURACY_SOLVERS = ("Tsit5", "Dopri5", "Dopri8")
ACCURACY_RTOLS = tuple(10.0**-k for k in range(3, 13))
ATOL_RATIO = 0.1  # atol = rtol / 10 everywhere
# The drag scene's reference, and the run that checks it is converged.
ACCURACY_REFERENCE = ("Dopri8", 1e-13)
ACCURACY_CHECK = ("Tsit5", 1e-13)
# Quick mode: one solver, two tolerances, the same solver at a tight tolerance as reference.
QUICK_SOLVERS = ("Tsit5",)
QUICK_RTOLS = (1e-4, 1e-9)
QUICK_REFERENCE = ("Tsit5", 1e-12)
# estim's defaults (simulate) and the other settings measured around them.
DEFAULT_SETTING = {"solver": "Tsit5", "rtol": _ode.RTOL, "atol": _ode.ATOL, "contact_slack": _ode.SLACK,
                   "max_steps": _ode.MAX_STEPS}
SLACKS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7)
SMALL_MAX_STEPS = 512
MAX_EVENTS = 64
ACCURACY_FILES = ("accuracy_table.md", "accuracy.png", "accuracy.json")
# The plain diffrax event loop's row (estim.app._event_loop; its own tolerances).
LOOP_KEY = ("diffrax event loop", 1e-8)


def _programs(scene, params, t_end, ts, ball: int = 1):
    """The compiled programs of the study for one scene and its balls: forward (all balls)
    and the gradient of ball ``ball``'s final x w.r.t. (e, mu_t, vx0) (``jax.jacfwd``, as
    the fits take it), on either path (``settings=None``: the closed form). They call the
    solvers behind ``simulate`` directly, because ``simulate`` checks its tolerances in
    Python (they cannot be traced through it); here the tolerances and the slack are
    traced, so one program per path and solver class serves every setting. ``ball`` 1 is
    the golf ball of the seed order (bocce, golf, pingpong)."""
    everything = check_keep(None)

    def solve(prm, settings):
        if settings is None:
            return solve_closed_form(scene, prm, t_end, ts, 48, MAX_EVENTS, False, everything, path(scene) == NATIVE)
        return solve_ode(scene, prm, t_end, ts, settings, MAX_EVENTS, False, everything)

    def final_x(theta, settings):
        return solve(_with_theta(params, ball, theta), settings).final.position[ball, 0]

    forward = jax.jit(lambda settings: solve(params, settings))
    gradient = jax.jit(jax.jacfwd(final_x))
    theta = jnp.array([params.e[ball], params.mu_t[ball], params.velocity[ball, 0]])
    return forward, (lambda settings: gradient(theta, settings))


def _loop_programs(scene, params, t_end, ball: int = 1):
    """The plain diffrax event loop's programs, as ``_programs``'s (the settings ignored):
    its gradient is ``jax.grad`` (reverse mode, diffrax's default adjoint)."""
    forward = jax.jit(lambda: event_loop(scene, params, t_end))
    gradient = jax.jit(jax.grad(lambda th: event_loop(scene, _with_theta(params, ball, th), t_end)[0][ball, 0]))
    theta = jnp.array([params.e[ball], params.mu_t[ball], params.velocity[ball, 0]])
    return (lambda settings: forward()), (lambda settings: gradient(theta))


def _settings(solver: str, rtol: float, slack: float = 1e-6, max_steps: int = 2048):
    return OdeSettings(getattr(diffrax, solver)(), jnp.asarray(rtol), jnp.asarray(rtol * ATOL_RATIO),
                       jnp.asarray(slack), int(max_steps))


def _compare(run: dict, ref: dict) -> dict:
    """Errors of ``run`` against ``ref``: event times over the events both have, final
    position (largest distance over the balls), gradient (largest component)."""
    counts, ref_counts = run["counts"], ref["counts"]
    err_t = 0.0
    for i in range(len(counts)):
        n = min(counts[i], ref_counts[i])
        if n:
            err_t = max(err_t, float(np.max(np.abs(run["t"][i, :n] - ref["t"][i, :n]))))
    return {
        "event_time_error": err_t,
        "events_match": bool(np.array_equal(counts, ref_counts)),
        "final_position_error": float(np.max(np.linalg.norm(run["final"] - ref["final"], axis=1))),
        "gradient_error": float(np.max(np.abs(run["gradient"] - ref["gradient"]))),
    }


def run_accuracy(*, repeats: int = 7, quick: bool = False, solvers=None, rtols=None,
                 reference=None, slacks=None, say=None) -> dict:
    """Measure the work-precision study of ``estim bench accuracy`` and return it as a dict.

    (a) the drag-free seed scene: the closed form (exact) against the ODE path forced with
    each diffrax solver at each rtol (atol = rtol / 10); (b) the seed scene in still air
    (data/scenes/stairs_air.xml): the same runs against a high-precision reference (Dopri8
    at rtol 1e-13, checked against Tsit5 at 1e-13). Every figure is measured here: errors
    of event times, final positions and the golf ball's gradient d x_final/d(e, mu_t, vx0)
    (``jax.grad``), median times per forward (three balls) and per gradient over
    ``repeats`` rounds (all settings timed in turn in every round, so that ratios are
    taken within one run), and accepted steps. Full mode also varies the contact slack and
    ``max_steps`` around estim's default.
    """
    say = say or (lambda msg: None)
    solvers_arg, rtols_arg, reference_arg, slacks_arg = solvers, rtols, reference, slacks
    solvers = tuple(solvers or (QUICK_SOLVERS if quick else ACCURACY_SOLVERS))
    rtols = tuple(rtols or (QUICK_RTOLS if quick else ACCURACY_RTOLS))
    reference = tuple(reference or (QUICK_REFERENCE if quick else ACCURACY_REFERENCE))
    check = None if quick else ACCURACY_CHECK
    slacks = tuple(() if quick else SLACKS) if slacks is None else tuple(slacks)
    t_end = jnp.asarray(SEED["t_end"])
    ts = jnp.stack([jnp.zeros(()), t_end])

    def measure(programs, settings, label):
        """Values of one setting (compiling on first use)."""
        forward, gradient = programs
        t0 = time.perf_counter()
        out = jax.block_until_ready(forward(settings))
        grad = np.asarray(gradient(settings))
        say(f"{label}: {time.perf_counter() - t0:.1f} s")
        if isinstance(out, tuple):  # the diffrax loop: final position, velocity, contact times
            times = np.asarray(out[2])
            return {"t": times, "counts": np.sum(np.isfinite(times), axis=1), "final": np.asarray(out[0]),
                    "gradient": grad, "complete": True, "steps": None, "call": (programs, settings)}
        steps = (np.asarray(jnp.sum(out.solution.steps.kind < 5, axis=-1)).tolist()
                 if settings is not None else None)
        return {
            "t": np.asarray(out.events.t), "counts": np.asarray(out.events.count),
            "final": np.asarray(out.final.position), "gradient": grad,
            "complete": bool(np.all(np.asarray(out.complete))), "steps": steps,
            "call": (programs, settings),
        }

    def time_all(runs):
        """Median times (ms) of every run, all runs timed once per round."""
        fwd = {k: [] for k in runs}
        grd = {k: [] for k in runs}
        for _ in range(max(int(repeats), 1)):
            for key, run in runs.items():
                (forward, gradient), settings = run["call"]
                t = time.perf_counter()
                jax.block_until_ready(forward(settings))
                fwd[key].append(time.perf_counter() - t)
                t = time.perf_counter()
                jax.block_until_ready(gradient(settings))
                grd[key].append(time.perf_counter() - t)
        for key, run in runs.items():
            run["forward_ms"] = statistics.median(fwd[key]) * 1e3
            run["gradient_ms"] = statistics.median(grd[key]) * 1e3

    def row(key, run, ref, ratio_to):
        solver, rtol = key[0], key[1]
        out = {"solver": solver, "rtol": rtol, "atol": None if rtol is None else rtol * ATOL_RATIO}
        out.update(_compare(run, ref))
        out.update({
            "forward_ms": run["forward_ms"], "gradient_ms": run["gradient_ms"],
            "forward_ratio": run["forward_ms"] / ratio_to["forward_ms"],
            "gradient_ratio": run["gradient_ms"] / ratio_to["gradient_ms"],
            "steps": None if run["steps"] is None else int(sum(run["steps"])),
            "steps_per_ball": run["steps"], "events": run["counts"].tolist(),
            "complete": run["complete"], "gradient": run["gradient"].tolist(),
        })
        return out

    scenes_dir = os.path.dirname(default_scene_path())
    custom = any(x is not None for x in (solvers_arg, rtols_arg, reference_arg, slacks_arg))
    command = "estim bench accuracy" + (" --quick" if quick else "")
    result = {"repeats": int(repeats), "quick": bool(quick), "t_end": float(t_end),
              "command": f"estim.app._bench.run_accuracy(...) (custom settings, quick={quick})" if custom else command,
              "balls": list(SEED["e"]), "atol_ratio": ATOL_RATIO, "default": dict(DEFAULT_SETTING)}

    # (a) Vacuum: the closed form against the ODE path forced on.
    vacuum = load_scene(os.path.join(scenes_dir, "stairs.xml"))
    programs = _programs(vacuum, seed_params(vacuum), t_end, ts)
    runs = {("closed form", None): measure(programs, None, "vacuum, closed form")}
    for solver in solvers:
        for rtol in rtols:
            runs[(solver, rtol)] = measure(programs, _settings(solver, rtol), f"vacuum, {solver} rtol {rtol:g}")
    say("vacuum: timing")
    time_all(runs)
    exact = runs[("closed form", None)]
    result["vacuum"] = {
        "scene": "data/scenes/stairs.xml",
        "reference": "closed form",
        "rows": [row(k, r, exact, exact) for k, r in runs.items()],
        "closed_form_gradient": exact["gradient"].tolist(),
    }

    # (b) Still air: the solvers against a high-precision reference.
    air = load_scene(os.path.join(scenes_dir, "stairs_air.xml"))
    programs = _programs(air, seed_params(air), t_end, ts)
    ref = measure(programs, _settings(*reference), f"air, reference {reference[0]} rtol {reference[1]:g}")
    runs = {}
    for solver in solvers:
        for rtol in rtols:
            runs[(solver, rtol)] = measure(programs, _settings(solver, rtol), f"air, {solver} rtol {rtol:g}")
    default_key = (DEFAULT_SETTING["solver"], DEFAULT_SETTING["rtol"])
    if default_key not in runs:
        runs[default_key] = measure(programs, _settings(*default_key), "air, default")
    settings_runs = {}
    for slack in slacks:
        if slack != DEFAULT_SETTING["contact_slack"]:
            settings_runs[("slack", slack)] = measure(
                programs, _settings(*default_key, slack=slack), f"air, default, slack {slack:g}")
    if not quick:
        settings_runs[("max_steps", SMALL_MAX_STEPS)] = measure(
            programs, _settings(*default_key, max_steps=SMALL_MAX_STEPS), f"air, default, max_steps {SMALL_MAX_STEPS}")
    loop = measure(_loop_programs(air, seed_params(air), t_end), None, "air, diffrax event loop")
    say("air: timing")
    time_all({**runs, **settings_runs, ("reference", None): ref, ("loop", None): loop})
    base = runs[default_key]
    result["air"] = {
        "scene": "data/scenes/stairs_air.xml",
        "reference": {"solver": reference[0], "rtol": reference[1], "atol": reference[1] * ATOL_RATIO,
                      "forward_ms": ref["forward_ms"], "gradient_ms": ref["gradient_ms"],
                      "steps": int(sum(ref["steps"])), "events": ref["counts"].tolist(),
                      "complete": ref["complete"], "gradient": ref["gradient"].tolist()},
        "rows": [row(k, r, ref, base) for k, r in runs.items() if k[1] in rtols and k[0] in solvers],
        "event_loop": row(LOOP_KEY, loop, ref, base),
    }
    if check is not None:
        other = measure(programs, _settings(*check), f"air, check {check[0]} rtol {check[1]:g}")
        result["air"]["reference_check"] = {"solver": check[0], "rtol": check[1], **_compare(other, ref)}
    settings_rows = []
    for (what, value), run in [(("default", None), base), *settings_runs.items()]:
        r = row(default_key, run, ref, base)
        r["contact_slack"] = value if what == "slack" else DEFAULT_SETTING["contact_slack"]
        r["max_steps"] = value if what == "max_steps" else DEFAULT_SETTING["max_steps"]
        settings_rows.append(r)
    settings_rows.sort(key=lambda r: (r["max_steps"] != DEFAULT_SETTING["max_steps"], -r["contact_slack"]))
    result["air"]["settings_rows"] = settings_rows if len(settings_rows) > 1 else []
    # (d) A spinning table-tennis shot in air: the solvers and the loop against a reference.
    shot_scene = load_scene(os.path.join(scenes_dir, SHOT["scene"]))
    shot = shot_params(shot_scene)
    shot_end = jnp.asarray(SHOT["t_end"])
    shot_ts = jnp.stack([jnp.zeros(()), shot_end])
    programs = _programs(shot_scene, shot, shot_end, shot_ts, ball=0)
    shot_ref = measure(programs, _settings(*reference), f"shot, reference {reference[0]} rtol {reference[1]:g}")
    shot_runs = {}
    for solver in solvers:
        for rtol in rtols:
            shot_runs[(solver, rtol)] = measure(programs, _settings(solver, rtol), f"shot, {solver} rtol {rtol:g}")
    if default_key not in shot_runs:
        shot_runs[default_key] = measure(programs, _settings(*default_key), "shot, default")
    shot_loop = measure(_loop_programs(shot_scene, shot, shot_end, ball=0), None, "shot, diffrax event loop")
    say("shot: timing")
    time_all({**shot_runs, ("reference", None): shot_ref, ("loop", None): shot_loop})
    shot_base = shot_runs[default_key]
    result["shot"] = {
        "scene": f"data/scenes/{SHOT['scene']}", "shot": dict(SHOT),
        "reference": {"solver": reference[0], "rtol": reference[1], "forward_ms": shot_ref["forward_ms"],
                      "gradient_ms": shot_ref["gradient_ms"], "steps": int(sum(shot_ref["steps"])),
                      "events": shot_ref["counts"].tolist(), "gradient": shot_ref["gradient"].tolist()},
        "rows": [row(k, r, shot_ref, shot_base) for k, r in shot_runs.items() if k[1] in rtols and k[0] in solvers],
        "event_loop": row(LOOP_KEY, shot_loop, shot_ref, shot_base),
    }
    result["machine"] = {
        "cpu_count": os.cpu_count(), "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(), "python": platform.python_version(),
        "jax": jax.__version__, "backend": jax.default_backend(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    return result


def _e(x) -> str:
    return "0" if x == 0 else f"{x:.1e}"


def format_accuracy(r: dict) -> str:
    """The study as Markdown: one table per scene, the settings table, notes."""

    def table(rows, ratio_name):
        lines = [
            "| solver | rtol | event times (s) | final position (m) | gradient | forward (ms) "
            f"| {ratio_name} | gradient (ms) | steps |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for x in rows:
            mark = "" if x["events_match"] else " †"
            steps = "-" if x["steps"] is None else str(x["steps"])
            rtol = "-" if x["rtol"] is None else f"{x['rtol']:.0e}"
            lines.append(
                f"| {x['solver']} | {rtol} | {_e(x['event_time_error'])}{mark} | {_e(x['final_position_error'])} "
                f"| {_e(x['gradient_error'])} | {x['forward_ms']:.3g} | {x['forward_ratio']:.3g} "
                f"| {x['gradient_ms']:.3g} | {steps} |")
        return "\n".join(lines)

    vac, air = r["vacuum"], r["air"]
    ref = air["reference"]
    out = [
        "**(a) Seed scene without air** (`data/scenes/stairs.xml`): the ODE path forced on "
        "(`solver=`), against the closed form. Errors are rounding: every Runge-Kutta method "
        "integrates a parabola exactly, so this table measures cost only. "
        "*× closed form*: forward time over the closed form's, same run.",
        "",
        table(vac["rows"], "× closed form"),
        "",
        f"**(b) Seed scene in still air** (`data/scenes/stairs_air.xml`), against {ref['solver']} at "
        f"rtol {ref['rtol']:.0e} (forward {ref['forward_ms']:.3g} ms, gradient {ref['gradient_ms']:.3g} ms, "
        f"{ref['steps']} steps). *× default*: forward time over Tsit5 at rtol {DEFAULT_SETTING['rtol']:.0e} "
        "(estim's default), same run. Last row: a plain diffrax event loop (`estim.app._event_loop`: Tsit5, "
        "PID rtol 1e-8 atol 1e-9, dtmax 0.004, `diffrax.Event` with Newton, restarted per contact, vmapped; "
        "its gradient by `jax.grad`), timed in the same rounds.",
        "",
        table(air["rows"] + ([air["event_loop"]] if "event_loop" in air else []), "× default"),
    ]
    shot = r.get("shot")
    if shot:
        sh, sref = shot["shot"], shot["reference"]
        out += [
            "",
            f"**(d) A spinning table-tennis shot** (`{shot['scene']}`: 40 mm, 2.7 g, from {list(sh['position'])} m "
            f"at {list(sh['velocity'])} m/s, spin {list(sh['spin'])} rad/s, e {sh['e']}, mu_t {sh['mu_t']}, "
            f"{sh['t_end']} s, {sref['events'][0]} bounce), against {sref['solver']} at rtol {sref['rtol']:.0e}; "
            "gradient of its final x. Last row: the diffrax loop.",
            "",
            table(shot["rows"] + [shot["event_loop"]], "× default"),
        ]
    chk = air.get("reference_check")
    if chk:
        out += ["", f"Reference check: {chk['solver']} at rtol {chk['rtol']:.0e} differs from the reference by "
                    f"{_e(chk['event_time_error'])} s in event times, {_e(chk['final_position_error'])} m in final "
                    f"position and {_e(chk['gradient_error'])} in the gradient"
                    + ("" if chk["events_match"] else " (event counts differ)") + "."]
    if air.get("settings_rows"):
        out += [
            "",
            f"**(c) Around the default** (still air, Tsit5, rtol {DEFAULT_SETTING['rtol']:.0e}, atol "
            f"{DEFAULT_SETTING['atol']:.0e}): the contact slack"
            + (" and the step budget `max_steps`" if any(x["max_steps"] != DEFAULT_SETTING["max_steps"]
                                                          for x in air["settings_rows"]) else "")
            + ", against the same reference.",
            "",
            "| contact_slack (m) | max_steps | event times (s) | final position (m) | gradient | forward (ms) "
            "| × default | gradient (ms) | steps | complete |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        ]
        for x in air["settings_rows"]:
            mark = "" if x["events_match"] else " †"
            out.append(
                f"| {x['contact_slack']:.0e} | {x['max_steps']} | {_e(x['event_time_error'])}{mark} "
                f"| {_e(x['final_position_error'])} | {_e(x['gradient_error'])} | {x['forward_ms']:.3g} "
                f"| {x['forward_ratio']:.3g} | {x['gradient_ms']:.3g} | {x['steps']} | {'yes' if x['complete'] else 'no'} |")
    mismatched = [x for x in vac["rows"] + air["rows"] + air.get("settings_rows", []) + (shot or {}).get("rows", [])
                  if not x["events_match"]]
    m = r["machine"]
    out += ["", "Errors: largest over the three balls (event times: over the events both runs list; "
                "final position: distance) and over the three components of the golf ball's "
                "d x_final/d(e, mu_t, vx0) (estim: `jax.jacfwd`; the loop: `jax.grad`). Times: medians over "
                f"{r['repeats']} rounds; forward = three balls in one call, gradient = the golf ball; "
                "steps = accepted steps of the three balls."
                + (" †: the event counts differ from the reference's (" + "; ".join(
                    f"{x['solver']} rtol {x['rtol']:.0e}: {x['events']}" for x in mismatched) + ")." if mismatched else ""),
            "",
            f"Measured with `{r.get('command') or 'estim bench accuracy' + (' --quick' if r['quick'] else '')}` on {m['cpu_count']} CPU cores "
            f"({m['processor']}, {m['platform']}), jax {m['jax']} ({m['backend']})"
            + (f", load average {m['load_average'][0]:.1f} at the end" if m.get("load_average") else "") + "."]
    return "\n".join(out)


def plot_accuracy(r: dict, path: str) -> None:
    """Work-precision plot: error against time, one line per solver, one column per scene
    (top: forward, final position; bottom: gradient)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import ticker

    floor = 1e-17
    panels = [("vacuum", "(a) no air: ODE path vs closed form"), ("air", "(b) still air: vs reference")]
    if "shot" in r:
        panels.append(("shot", "(d) table-tennis shot: vs reference"))
    fig, axes = plt.subplots(2, len(panels), figsize=(5.5 * len(panels), 8), sharey="row")
    for col, (key, title) in enumerate(panels):
        rows = r[key]["rows"]
        for top, (tkey, ekey, ylabel) in enumerate((("forward_ms", "final_position_error", "final position error (m)"),
                                                   ("gradient_ms", "gradient_error", "gradient error"))):
            ax = axes[top, col]
            for i, solver in enumerate(dict.fromkeys(x["solver"] for x in rows if x["rtol"] is not None)):
                pts = [x for x in rows if x["solver"] == solver]
                xs = [x[tkey] for x in pts]
                ys = [max(x[ekey], floor) for x in pts]
                ax.loglog(xs, ys, "o-", color=f"C{i}", label=solver, ms=4)
                for x, xv, yv in zip(pts, xs, ys, strict=True):
                    ax.annotate(f"{np.log10(x['rtol']):.0f}", (xv, yv), fontsize=6, xytext=(3, 2),
                                textcoords="offset points", color=f"C{i}")
            closed = [x for x in rows if x["rtol"] is None]
            if closed:
                ax.loglog([closed[0][tkey]], [floor], "k*", ms=11, label="closed form (exact)")
            extra = []
            if key != "vacuum":
                ref = r[key]["reference"]
                ax.loglog([ref[tkey]], [floor], "k^", ms=9,
                          label=f"reference ({ref['solver']}, rtol {ref['rtol']:.0e})")
                extra.append(ref[tkey])
                loop = r[key].get("event_loop")
                if loop:
                    ax.loglog([loop[tkey]], [max(loop[ekey], floor)], "kX", ms=10, label="plain diffrax event loop")
                    extra.append(loop[tkey])
            if key != "vacuum" and top == 0:
                d = [x for x in rows if x["solver"] == DEFAULT_SETTING["solver"] and x["rtol"] == DEFAULT_SETTING["rtol"]]
                if d:
                    ax.loglog([d[0][tkey]], [max(d[0][ekey], floor)], "s", mfc="none", mec="k", ms=12,
                              label="estim's default")
            times = [x[tkey] for x in rows] + extra
            ax.set_xlim(min(times) / 1.6, max(times) * 1.6)
            ax.xaxis.set_major_locator(ticker.LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
            ax.xaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
            ax.xaxis.set_minor_formatter(ticker.NullFormatter())
            what = ("forward, 1 ball" if key == "shot" else "forward, 3 balls") if top == 0 else (
                "gradient" if key == "shot" else "gradient, golf")
            ax.set_xlabel(f"time per {what} (ms)")
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3, which="both")
            if top == 0:
                ax.set_title(title)
            ax.legend(fontsize=7)
    fig.suptitle("Work-precision: seed staircase, 2.3 s; table-tennis shot, 0.42 s "
                 "(labels: log10 rtol; zero error drawn at 1e-17)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_accuracy(r: dict, out_dir: str) -> list[str]:
    """Write the study ``r`` of :func:`run_accuracy` into ``out_dir`` (created if missing):
    ``accuracy_table.md`` (:func:`format_accuracy`), ``accuracy.png``
    (:func:`plot_accuracy`) and ``accuracy.json`` (every measured value). Returns the paths.
    Nothing else is touched: the docs page is docs/scripts/accuracy.py's."""
    os.makedirs(out_dir, exist_ok=True)
    paths = [os.path.join(out_dir, name) for name in ACCURACY_FILES]
    with open(paths[0], "w") as fh:
        fh.write(format_accuracy(r) + "\n")
    plot_accuracy(r, paths[1])
    with open(paths[2], "w") as fh:
        dump(r, fh, indent=1)
        fh.write("\n")
    return paths
