"""``estim bench speed``: timings on the seed scene, measured in this process."""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from ._demo import SEED, default_scene_path

__all__ = ["run_speed", "format_speed", "run_fit_bench", "format_fit_bench", "TARGETS", "REFERENCE"]

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

_FIRST_CALL = r"""
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
t2 = time.perf_counter()
traj = estim.simulate(scene, params, float(sys.argv[5]))
jax.block_until_ready(traj)
t3 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_call_s": t3 - t2}))
"""


def _median_us(fn, arg, repeats: int, warmup: int = 3) -> float:
    import jax

    for _ in range(warmup):
        jax.block_until_ready(fn(arg))
    times = []
    for _ in range(max(repeats, 1)):
        t = time.perf_counter()
        jax.block_until_ready(fn(arg))
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e6


def _first_call(scene_path: str, cache_dir: str | None = None) -> dict:
    cmd = [
        sys.executable, "-c", _FIRST_CALL, scene_path, json.dumps(SEED["e"]),
        str(SEED["mu_t"]), json.dumps(list(SEED["velocity"])), str(SEED["t_end"]),
    ]
    env = dict(os.environ)
    if cache_dir:
        cmd[2] = "import estim; estim.enable_compilation_cache(" + repr(cache_dir) + ")\n" + _FIRST_CALL
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"first-call subprocess failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _met(key: str, value: float) -> bool:
    op, target = TARGETS[key]
    return {"le": value <= target, "lt": value < target, "ge": value >= target}[op]


def run_speed(*, batch: int = 10_000, repeats: int = 200, scene_path: str | None = None,
              seed: int = 0) -> dict:
    """Measure the figures of ``estim bench speed`` and return them as a dict."""
    scene_path = scene_path or default_scene_path()
    # First: the fresh-process first call, before this process compiles anything; then the
    # same with JAX's persistent compilation cache (as the estim command uses it), warmed
    # by one run in another process.
    first = _first_call(scene_path)
    with tempfile.TemporaryDirectory() as cache:
        _first_call(scene_path, cache)
        first_cached = _first_call(scene_path, cache)

    import jax
    import jax.numpy as jnp

    import estim

    scene = estim.load_scene(scene_path)
    t_end = SEED["t_end"]
    balls = [b for b in scene.balls if b.name in SEED["e"]]
    three = estim.Params(
        [SEED["e"][b.name] for b in balls], [SEED["mu_t"]] * len(balls),
        [b.radius for b in balls], [b.position for b in balls], [SEED["velocity"]] * len(balls),
    )

    # Forward: 3 balls in one batched call. Jitted wrapper (what a user's jitted code
    # pays) and the plain call (adds estim's eager argument checks).
    forward = jax.jit(lambda p: estim.simulate(scene, p, t_end))
    forward_us = _median_us(forward, three, repeats)
    eager_us = _median_us(lambda p: estim.simulate(scene, p, t_end), three, max(repeats // 4, 3))

    # Gradient: d(golf final x)/d(e, mu_t, vx0), jacfwd, jitted.
    golf = scene.ball("golf")
    vel = SEED["velocity"]

    def final_x(theta):
        e, mu_t, vx0 = theta
        p = estim.Params(e, mu_t, golf.radius, jnp.asarray(golf.position),
                         jnp.stack([vx0, jnp.asarray(vel[1]), jnp.asarray(vel[2])]))
        return estim.simulate(scene, p, t_end).final.position[0]

    grad = jax.jit(jax.jacfwd(final_x))
    theta = jnp.array([SEED["e"]["golf"], SEED["mu_t"], vel[0]])
    gradient_us = _median_us(grad, theta, repeats)
    gradient_value = np.asarray(grad(theta)).tolist()

    # Batch: `batch` golf balls, e ~ U[0.3, 0.95], same release.
    rng = np.random.default_rng(seed)
    e_batch = rng.uniform(0.3, 0.95, size=batch)
    many = estim.Params(e_batch, SEED["mu_t"], golf.radius, golf.position, vel)
    # throw=False: a ball that needs more than max_segments is counted, not raised.
    forward_batch = jax.jit(lambda p: estim.simulate(scene, p, t_end, throw=False))
    batch_us = _median_us(forward_batch, many, max(min(repeats, 20), 3), warmup=1)
    incomplete = int(np.sum(~np.asarray(forward_batch(many).complete)))

    result = {
        "forward_us": forward_us,
        "forward_eager_us": eager_us,
        "gradient_us": gradient_us,
        "gradient": dict(zip(("e", "mu_t", "vx0"), gradient_value, strict=True)),
        "first_call_s": first["first_call_s"],
        "first_call_cached_s": first_cached["first_call_s"],
        "import_s": first["import_s"],
        "batch": batch,
        "batch_us": batch_us,
        "batch_balls_per_s": batch / (batch_us * 1e-6),
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
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
    }
    return result


def format_speed(r: dict) -> str:
    t = r["targets"]

    def row(name, value, key):
        met = "met" if t[key]["met"] else "NOT met"
        return f"{name:<34} {value:>16} {t[key]['target']:>12} {met:>8}   {REFERENCE[key]}"

    lines = [
        f"{'metric':<34} {'measured':>16} {'target':>12} {'status':>8}   reference",
        row("forward, 3 balls (us/call, jit)", f"{r['forward_us']:.1f}", "forward_us"),
        row("gradient, jacfwd (us/call, jit)", f"{r['gradient_us']:.1f}", "gradient_us"),
        row("first call, fresh process (s)", f"{r['first_call_s']:.3f}", "first_call_s"),
        row(f"batch {r['batch']} golf (balls/s)", f"{r['batch_balls_per_s']:.3g}", "batch_balls_per_s"),
        "",
        f"first call with the persistent compilation cache warm: {r['first_call_cached_s']:.3f} s",
        f"forward without jit (estim.simulate, eager checks): {r['forward_eager_us']:.1f} us/call",
        f"batch of {r['batch']}: {r['batch_us']:.1f} us/call "
        f"({r['batch_incomplete']} balls incomplete within max_segments); "
        f"import estim: {r['import_s']:.2f} s",
        "gradient d(golf final x)/d(e, mu_t, vx0) = "
        + ", ".join(f"{v:.8f}" for v in r["gradient"].values()),
        f"machine: {r['machine']['cpu_count']} CPUs, {r['machine']['processor']}, "
        f"jax {r['machine']['jax']} ({r['machine']['backend']}); median of {r['repeats']} calls",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------- bench fit

FIT_TARGETS = {"cli_cold_s": 15.0, "cli_warm_s": 15.0, "steady_s": 0.5}


def _cli_fit_seconds(tracks: str, scene_path: str, out: str, env: dict) -> float:
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "estim", "fit", tracks, "--scene", scene_path, "--out", out],
        capture_output=True, text=True, env=env, check=False,
    )
    seconds = time.perf_counter() - t
    if proc.returncode not in (0, 1) or not os.path.isfile(os.path.join(out, "fit.json")):
        raise RuntimeError(f"estim fit failed:\n{proc.stderr[-2000:]}")
    return seconds


def run_fit_bench(*, repeats: int = 5, scene_path: str | None = None) -> dict:
    """``estim fit`` on the bundled tracks from process start to written fit.json, without
    and with a warm compilation cache, and the steady-state (compiled) fit in-process."""
    from ._demo import DEMO_TRACKS

    scene_path = scene_path or default_scene_path()
    tracks = str(DEMO_TRACKS)
    with tempfile.TemporaryDirectory() as tmp:
        cold_env = dict(os.environ, ESTIM_NO_CACHE="1")
        cold = _cli_fit_seconds(tracks, scene_path, os.path.join(tmp, "cold"), cold_env)
        warm_env = dict(os.environ, ESTIM_CACHE_DIR=os.path.join(tmp, "cache"))
        _cli_fit_seconds(tracks, scene_path, os.path.join(tmp, "fill"), warm_env)
        warm = _cli_fit_seconds(tracks, scene_path, os.path.join(tmp, "warm"), warm_env)

    import estim

    from ._job import fit_csv

    scene = estim.load_scene(scene_path)
    fit_csv(tracks, scene)  # compile
    times = []
    for _ in range(max(repeats, 1)):
        t = time.perf_counter()
        result, _ = fit_csv(tracks, scene)
        times.append(time.perf_counter() - t)
    steady = statistics.median(times)
    out = {"cli_cold_s": cold, "cli_warm_s": warm, "steady_s": steady,
           "e": {b: f.values["e"] for b, f in result.balls.items()}}
    out["targets"] = {k: {"target": f"< {v:g} s", "met": bool(out[k] < v)} for k, v in FIT_TARGETS.items()}
    return out


def format_fit_bench(r: dict) -> str:
    t = r["targets"]
    rows = [f"{'metric':<52} {'measured':>10} {'target':>9} {'status':>8}"]
    for key, name in (("cli_cold_s", "estim fit, bundled tracks, fresh process, no cache (s)"),
                      ("cli_warm_s", "estim fit, fresh process, compilation cache warm (s)"),
                      ("steady_s", "fit, compiled, in-process (s)")):
        rows.append(f"{name:<52} {r[key]:>10.2f} {t[key]['target']:>9} {'met' if t[key]['met'] else 'NOT met':>8}")
    rows.append("fitted e: " + ", ".join(f"{b} {v:.4f}" for b, v in r["e"].items()))
    return "\n".join(rows)
