"""How estim runs on XLA:CPU (``estim._config``): small loops compiled as one kernel."""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ROOT, STAIRS_XML, jax_path, seed_params

import estim
from estim import _config
from estim.forward._contact import inner
from estim.forward._simulate import flat_params
from estim.forward._solver import plan, replay

_PROBE = (
    "import os, json, sys\n"
    "{before}\n"
    "import estim\n"
    "from estim import _config\n"
    "print(json.dumps([_config.SMALL_LOOPS_AS_KERNELS, os.environ.get('XLA_FLAGS', '')]))\n"
)
_OPTION = f"xla_cpu_small_while_loop_byte_threshold={_config.SMALL_LOOP_BYTES}"


def _probe(before: str = "", xla_flags: str | None = None):
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    out = subprocess.run([sys.executable, "-c", _PROBE.format(before=before)], env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_inner_is_the_dot_product():
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(5, 86, 3)), rng.normal(size=3)
    np.testing.assert_allclose(inner(x, y), np.einsum("...i,i->...", x, y), rtol=1e-14, atol=1e-14)


def test_import_raises_the_small_loop_threshold():
    active, flags = _probe(xla_flags="--xla_cpu_enable_fast_math=false")
    assert active
    assert flags == f"--xla_cpu_enable_fast_math=false --xla_backend_extra_options={_OPTION}"


def test_import_starts_no_backend():
    """Importing estim (every module of it, the CLI's included) and building the CLI's
    parser and help leave JAX's backend unstarted: ``jax.distributed.initialize`` (``estim fit --distributed``) and ``estim
    bench --cpus`` must come before it starts. (A registry message that traced a contact
    law at import once started it.)"""
    code = ("import estim, estim.app._cli\n"
            "estim.app._cli.build_parser().format_help()\n"
            "from jax._src import xla_bridge\n"
            "print(xla_bridge.backends_are_initialized())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "False", out.stderr


def test_a_users_extra_options_are_left_alone():
    mine = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1024"
    assert _probe(xla_flags=mine) == [False, mine]


def test_a_started_backend_is_left_alone():
    # XLA reads XLA_FLAGS once, when JAX starts its backend: after that, setting it would
    # change nothing, so estim does not pretend to.
    active, flags = _probe(before="import jax.numpy as jnp; jnp.zeros(1)")
    assert not active and flags == ""


def _loop_owners(hlo: str) -> list[str]:
    """Names of the computations that hold a while loop, in optimised HLO text."""
    owners, current = [], None
    for line in hlo.splitlines():
        head = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{$", line)
        if head:
            current = head.group(1)
        elif re.search(r"\bwhile\(", line):
            owners.append(current)
    return owners


@pytest.mark.skipif(not _config.SMALL_LOOPS_AS_KERNELS, reason="XLA's backend started before estim")
def test_event_loops_compile_to_one_kernel():
    """The planning loop and the derivative replay call no library routine (a dot, a
    scatter), so XLA:CPU compiles each into a single kernel: every while loop of the
    compiled program lies inside an outlined ``*_computation`` (SmallWhileLoopHoistingPass)."""
    scene = estim.load_scene(STAIRS_XML)
    golf = estim.Params.for_ball(scene, "golf", e=0.7, mu_t=0.98, velocity=(1.15, 0.0, 0.0))
    three = flat_params(seed_params(scene))  # the seed's three balls

    plan_hlo = jax.jit(lambda p: jax.lax.map(lambda q: plan(scene, q, 2.3, 48), p)).lower(three).compile().as_text()
    planned = plan(scene, golf, 2.3, 48)
    decisions, durations = planned.decisions, planned.segments.t1 - planned.segments.t0

    def final_x(e):
        return replay(scene, eqx.tree_at(lambda p: p.e, golf, e), 2.3, decisions, durations).p1[-1, 0]

    grad_hlo = jax.jit(jax.jacfwd(final_x)).lower(jnp.float64(0.7)).compile().as_text()

    # simulate itself on the JAX path (estim's path without its native kernels): the three
    # seed balls, one at a time in a loop (estim.forward._simulate), and the jacfwd of the golf
    # ball's final x through it.
    with jax_path():
        sim_hlo = _simulate_hlo(scene, seed_params(scene))
        sim_grad_hlo = _gradient_hlo(scene, golf)
    for hlo in (plan_hlo, grad_hlo, sim_hlo, sim_grad_hlo):
        owners = _loop_owners(hlo)
        assert owners, "no while loop found"
        assert all(name.endswith("_computation") for name in owners), owners
    # The forward call is one such kernel: the loop over balls, with everything inside.
    entry = _entry(sim_hlo)
    assert len(re.findall(r"= .* call\(", entry)) == 1, "simulate is not one loop kernel"


@pytest.mark.skipif(not _config.SMALL_LOOPS_AS_KERNELS, reason="XLA's backend started before estim")
def test_the_air_paths_step_loop_with_round_edges_is_one_kernel():
    """On the ODE path in a scene with exact geometry (a table whose edges and corners are
    round, searched with quartic contact times) the step loop and its derivative replay are
    each one kernel: no ``sort`` (a call into XLA's runtime library) inside them."""
    scene = estim.load_scene(ROOT / "data" / "scenes" / "drop_air.xml")
    shot = estim.Params.for_ball(scene, "pingpong", e=0.88, mu_t=0.75, position=(-0.9, 0.0, 0.25),
                                 velocity=(4.5, 0.0, 0.6), spin=(0.0, 120.0, 0.0))

    def final_x(vx):
        return estim.simulate(scene, eqx.tree_at(lambda p: p.velocity, shot, shot.velocity.at[0].set(vx)),
                              0.42, keep=()).final.position[0]

    for hlo in (jax.jit(final_x).lower(4.5).compile().as_text(),
                jax.jit(jax.jacfwd(final_x)).lower(4.5).compile().as_text()):
        owners = _loop_owners(hlo)
        assert owners and all(name.endswith("_computation") for name in owners), owners
        assert not re.search(r"\bsort\(", hlo)


def _simulate_hlo(scene, params):
    return jax.jit(lambda p: estim.simulate(scene, p, 2.3)).lower(params).compile().as_text()


def _gradient_hlo(scene, golf):
    def final_x(e):
        return estim.simulate(scene, eqx.tree_at(lambda p: p.e, golf, e), 2.3).final.position[0]

    return jax.jit(jax.jacfwd(final_x)).lower(jnp.float64(0.7)).compile().as_text()


def _entry(hlo: str) -> str:
    entry = hlo[hlo.index("\nENTRY"):]
    return entry[: entry.index("\n}\n")]


@pytest.mark.skipif(not _config.SMALL_LOOPS_AS_KERNELS, reason="XLA's backend started before estim")
def test_native_forward_is_one_call_and_its_derivative_one_loop_kernel():
    """On the native kernels the forward program is the kernel's call and nothing else
    that computes (no loop, no check kernel); its derivative replays the structure in one
    loop kernel (estim.forward._native)."""
    scene = estim.load_scene(STAIRS_XML)
    golf = estim.Params.for_ball(scene, "golf", e=0.7, mu_t=0.98, velocity=(1.15, 0.0, 0.0))
    entry = _entry(_simulate_hlo(scene, seed_params(scene)))
    assert re.findall(r"custom_call_target=\"(\w+)\"", entry) == ["estim_trajectory"]
    assert not _loop_owners(entry) and [k for k in _entry_kernels(entry + "\n}\n") if k != "copy"] == ["custom-call"]
    grad_hlo = _gradient_hlo(scene, golf)
    owners = _loop_owners(grad_hlo)
    assert owners and all(name.endswith("_computation") for name in owners), owners
    assert "estim_plan" in grad_hlo


_DISPATCH_PROBE = (
    "import json, jax\n"
    "{before}\n"
    "import estim\n"
    "from estim import _config\n"
    "jax.numpy.zeros(1).block_until_ready()\n"
    "from jax._src import xla_bridge\n"
    "print(json.dumps([_config.SYNC_DISPATCH, _config.dispatch_is_sync(),\n"
    "                  bool(xla_bridge._CPU_ENABLE_ASYNC_DISPATCH.value)]))\n"
)


def _dispatch_probe(before: str = "", env_extra: dict | None = None):
    env = {k: v for k, v in os.environ.items() if k != "ESTIM_ASYNC_DISPATCH"} | (env_extra or {})
    out = subprocess.run([sys.executable, "-c", _DISPATCH_PROBE.format(before=before)], env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_import_runs_programs_on_the_calling_thread():
    # [estim set it, estim reports it, JAX's option as the backend read it (async?)]
    assert _dispatch_probe() == [True, True, False]


def test_async_dispatch_can_be_kept():
    assert _dispatch_probe(env_extra={"ESTIM_ASYNC_DISPATCH": "1"}) == [False, False, True]
    # a user's setting after importing estim, before the first computation, wins
    after = _DISPATCH_PROBE.replace("jax.numpy.zeros", "jax.config.update('jax_cpu_enable_async_dispatch', True)\njax.numpy.zeros")
    out = subprocess.run([sys.executable, "-c", after.format(before="")], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == [True, False, True]
    # a started backend is left alone
    assert _dispatch_probe(before="jax.numpy.zeros(1)") == [False, False, True]


def _entry_kernels(hlo: str) -> list[str]:
    """The operations of the entry computation that XLA:CPU runs as kernels (thunks)."""
    entry = hlo[hlo.index("\nENTRY"):]
    entry = entry[: entry.index("\n}\n")]
    free = ("parameter", "constant", "get-tuple-element", "tuple", "bitcast")
    kinds = [re.search(r" ([a-z][a-z\-]*)\(", line.split("=", 1)[1]) for line in entry.splitlines()[1:] if "=" in line]
    return [k.group(1) for k in kinds if k and k.group(1) not in free]


@pytest.mark.skipif(not _config.SMALL_LOOPS_AS_KERNELS, reason="XLA's backend started before estim")
@pytest.mark.parametrize("native", [True, False])
def test_one_ball_with_keep_stays_one_loop_kernel(native):
    """For one ball XLA would inline the loop over balls and run its body kernel by kernel
    (dozens, which XLA:CPU spreads over its threads); with ``keep`` given the loop stays
    one kernel, and the program at most the 8 kernels XLA:CPU runs on the calling thread.
    The gradient is the issue's seed value either way."""
    scene = estim.load_scene(STAIRS_XML)
    golf = scene.ball("golf")

    def final_x(theta, keep):
        e, mu_t, vx0 = theta
        p = estim.Params(e, mu_t, golf.radius, jnp.asarray(golf.position), jnp.stack([vx0, 0.0, 0.0]))
        return estim.simulate(scene, p, 2.3, keep=keep).final.position[0]

    theta = jnp.array([0.7, 0.98, 1.15])
    kernels = {}
    with contextlib.nullcontext() if native else jax_path():
        kernels = _gradient_kernels(final_x, theta)
    assert kernels[()].count("call") == 1 and len(kernels[()]) <= 8, kernels[()]
    assert len(kernels[None]) > 8  # inlined: the body's kernels


def _gradient_kernels(final_x, theta):
    kernels = {}
    for keep in ((), None):
        grad = jax.jit(jax.jacfwd(lambda th, keep=keep: final_x(th, keep)))
        np.testing.assert_allclose(grad(theta), [0.19213914, 6.81524982, 2.17816532], atol=5e-9)
        kernels[keep] = _entry_kernels(grad.lower(theta).compile().as_text())
    return kernels


def _timed_program(monkeypatch, seconds: float):
    """``x * n`` under ``_config.jit``'s ski-rental rule on a fake clock (the first call 1 s,
    each later one ``seconds``), its jit recording the compile options of each call.
    Returns the program, that record, and the quick and optimised options."""
    compiled = []

    def fake_filter_jit(fun, compiler_options=None):
        def run(*args, **kwargs):
            compiled.append(compiler_options)
            return fun(*args, **kwargs)
        return run

    clock = iter([0.0, 1.0] + [t for k in range(1, 10) for t in (10.0 * k, 10.0 * k + seconds)])
    monkeypatch.setattr(eqx, "filter_jit", fake_filter_jit)
    monkeypatch.setattr(_config.time, "perf_counter", lambda: next(clock))
    quick, optimised = (("xla_backend_optimization_level", 0),), (("xla_backend_optimization_level", 1),)
    program = _config.jit(lambda x, n: x * n, options=quick, optimised=optimised)
    return program, compiled, _config.compile_options(quick), _config.compile_options(optimised)


def test_a_quick_program_tiers_up_once_it_has_run_as_long_as_its_first_call(monkeypatch):
    """``jit(..., optimised=...)`` at top level: the quick options until the calls after
    the first have taken as long as the first (the ski-rental rule), then the optimised
    ones, per signature (shapes and static values); inside a transformation, neither."""
    program, compiled, q, o = _timed_program(monkeypatch, 0.3)
    for _ in range(6):  # the first call 1 s, then 0.3 s each: 0.3 + 0.3 + 0.3 + 0.3 >= 1 after the fifth
        program(np.ones(2), 3)
    program(np.ones(3), 3)  # another shape: another program, quick again
    program(np.ones(2), 4)  # another static value: the same
    assert compiled == [q] * 5 + [o] + [q] * 2
    compiled.clear()
    jax.make_jaxpr(lambda x: program(x, 3))(np.ones(2))  # inside a trace: no options of its own
    assert compiled == [None]


def test_calls_in_same_programs_keep_their_program_and_the_move_waits(monkeypatch):
    """``same_programs``: the ski-rental rule's move (timed: where the load puts it) waits
    until the block ends, the calls inside neither counted nor timed, so that runs compared
    with each other round alike; an optimised program stays optimised."""
    program, compiled, q, o = _timed_program(monkeypatch, 0.6)
    program(np.ones(2), 3)  # 1 s: the quick program's first call
    with _config.same_programs():
        for _ in range(4):  # untimed: would have moved after the second
            program(np.ones(2), 3)
    program(np.ones(2), 3)
    program(np.ones(2), 3)  # 0.6 + 0.6 >= 1 s: moves after this one
    with _config.same_programs():
        program(np.ones(2), 3)
    assert compiled == [q] * 7 + [o]


def test_a_program_compiled_ahead_is_the_one_its_first_call_runs_and_its_compile_counts(monkeypatch):
    """``jit(...).ahead``: the quick program of a signature not seen yet, lowered from shapes
    alone, compiled on another thread; the call then neither traces nor compiles it again,
    and the time spent ahead is its first call's for the ski-rental rule (here 2 s ahead,
    then 0.5 s per call: the optimised program, compiled anew, from the fifth call on)."""
    import threading

    traces, compiles = [], []

    def fun(x, n):
        traces.append(x.shape)
        return x * n

    def count(name, _, **__):
        if name == "/jax/core/compile/backend_compile_duration":
            compiles.append(name)

    quick, optimised = (("xla_backend_optimization_level", 0),), (("xla_backend_optimization_level", 1),)
    program = _config.jit(fun, options=quick, optimised=optimised, static_argnames=("n",))
    clock = iter([0.0, 1.0, 1.0, 2.0] + [t for k in range(1, 10) for t in (10.0 * k, 10.0 * k + 0.5)])
    _config.compile_options(quick), _config.compile_options(optimised)  # (their probes compile too)
    monkeypatch.setattr(_config.time, "perf_counter", lambda: next(clock))
    jax.monitoring.register_event_duration_secs_listener(count)
    try:
        shapes, compile_ = program.ahead(jax.ShapeDtypeStruct((2,), jnp.float64), n=3)
        assert shapes.shape == (2,) and shapes.dtype == jnp.float64
        thread = threading.Thread(target=compile_)
        thread.start()
        thread.join()
        assert len(compiles) == 1
        assert program.ahead(np.ones(2), n=3) is None  # (seen: nothing to compile ahead)
        for _ in range(4):
            np.testing.assert_array_equal(program(np.ones(2), n=3), [3.0, 3.0])
        assert traces == [(2,)] and len(compiles) == 1  # four calls of the program compiled ahead
        np.testing.assert_array_equal(program(np.ones(2), n=3), [3.0, 3.0])
        assert len(compiles) == 2  # 4 x 0.5 s >= 2 s: the optimised program
    finally:
        jax.monitoring.unregister_event_duration_listener(count)
    with pytest.raises(TypeError, match="ahead needs static_argnames"):
        _config.jit(fun, options=quick).ahead(np.ones(2), 3)
