"""Shared fixtures and helpers for the estim test suite.

Speed: JAX compiles ``estim.simulate`` once per distinct combination of static arguments
and array shapes (several seconds each). Every simulation in the suite therefore goes
through the helpers below, which pad a batch of balls to ``B`` and the sample times to
``NT`` so that each scene compiles ``simulate`` once, and the derivative helpers are
``jax.jit``-ed functions defined once here.

Importing estim switches JAX's x64 mode on; every helper computes in float64.
"""

from __future__ import annotations

import atexit
import functools
import gc
import os
import pathlib
import shutil
import tempfile
import types
import uuid

# The suite compiles at XLA's backend (LLVM) optimisation level 0 wherever a program does
# not set its own level: most of its time is XLA compiling programs that run a few times
# (the JAX path's Jacobians it checks the native kernels against, reverse-mode helpers, fits
# of a few calls). Programs that set a level (estim._config: the closed form's 1, the ODE
# fit's 0 and 1) are meant to keep it, jit's compiler_options being applied over the
# defaults XLA_FLAGS sets (not measured here). The level is LLVM's optimisation, not
# fast-math (off by default on XLA:CPU), and the whole suite passes at either level, the
# native kernels' bit-for-bit comparisons included (session 65, one run each on the 2-core machine: 854 passed in 1692 s at level
# 0, the tests' summed time 3352 s; 1988 s and 3932 s at XLA's default the session before).
# Set before JAX starts its backend; subprocesses (the command line, the notebooks) inherit
# it. ESTIM_TESTS_XLA_DEFAULT=1 runs the suite at XLA's default instead.
if not os.environ.get("ESTIM_TESTS_XLA_DEFAULT") and "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level=0".strip()

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import estim
from estim._config import CLOSED_FORM_COMPILE, compile_options

# The suite runs the command line in-process (estim.app._cli.main), which would switch JAX's
# persistent compilation cache on for the whole test process: every later compile of the suite
# would then be serialised into the user's cache, hundreds of programs the user never asked
# for (see also _free_compiled_programs below).
# Subprocesses that measure or want the cache ask for it (estim.app._bench, the notebooks).
os.environ["ESTIM_NO_CACHE"] = "1"

ROOT = pathlib.Path(__file__).resolve().parents[1]

# The suite's own persistent compilation cache, for one run and then deleted: many modules
# compile the same programs (this file's helpers, padded to B balls and NT times, the fits of
# the bundled tracks), and _free_compiled_programs below drops each module's programs when it
# ends; from this cache a later module, or another pytest-xdist worker of the same run, loads
# them instead of compiling them again (the closed-form reverse-mode gradient alone compiles
# for 60-110 s). Programs that compile in under a second are not worth the disk.
# (The controller names the run; its workers inherit the name with its environment.)
_RUN = os.environ.setdefault("ESTIM_TESTS_RUN", uuid.uuid4().hex)
CACHE_DIR = pathlib.Path(tempfile.gettempdir()) / f"estim-tests-jax-cache-{_RUN}"
jax.config.update("jax_compilation_cache_dir", str(CACHE_DIR))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


# The modules that take longest (minutes each on the 2-core CI machine), longest first
# (their totals in one full run, session 50, 2-core Intel Xeon, less what that session
# saved in them: test_native about 700 s, test_hard_cases 300, test_exact_geometry 290, then
# 230 down to 30 s). pytest-xdist hands each worker a whole module at a time, in collection
# order (--no-loadscope-reorder in pyproject.toml): started last, one of these would leave a
# worker running it alone at the end of the run.
LONG_MODULES = ("test_native.py", "test_hard_cases.py", "test_exact_geometry.py", "test_pooled_calibration.py",
                "test_image_fit.py", "test_cli.py", "test_pooled.py", "test_bench_accuracy.py", "test_fit.py",
                "test_friction_law.py", "test_notebooks.py", "test_image_tracks.py", "test_image_clips.py", "test_ode.py",
                "test_air_contacts.py", "test_config.py", "test_notebooks_fit.py", "test_simulate.py",
                "test_fit_friction.py", "test_cli_scenes.py", "test_fit_air.py", "test_laws.py", "test_compression.py",
                "test_properties.py", "test_sensitivity.py", "test_priors.py", "test_notebooks_cameras.py",
                "test_scan.py", "test_tracks.py", "test_hits.py")


def pytest_collection_modifyitems(config, items):
    """The long modules first (``LONG_MODULES``), the rest in their usual order; each
    module's tests keep theirs."""
    rank = {name: k for k, name in enumerate(LONG_MODULES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_MODULES)))


if "PYTEST_XDIST_WORKER" not in os.environ:  # the controller (or the only process)
    # At its exit, after every worker ended.
    atexit.register(shutil.rmtree, CACHE_DIR, ignore_errors=True)


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Each test module's compiled programs are freed when it ends (``jax.clear_caches``):
    kept for the whole session, the suite's hundreds of programs grew the test process past
    13 GB by two thirds of the suite, and CI's runs crashed there twice in XLA (a segfault
    in a compile, or in the persistent cache's writer). A module recompiles what it shares
    with an earlier one."""
    yield
    jax.clear_caches()
    gc.collect()
STAIRS_XML = ROOT / "data" / "scenes" / "stairs.xml"
STAIRS_EXACT_XML = ROOT / "data" / "scenes" / "stairs_exact.xml"

B = 64  # every batched simulation has exactly this many balls (padded)
NT = 64  # every ``ts`` has exactly this many sample times (padded)

# A ball alone and the same ball in a batch run different compiled code: for one ball XLA
# drops the loop over balls (estim.forward._simulate) and compiles its body kernel by kernel, for
# several it compiles the loop as one kernel; XLA:CPU contracts multiply-adds into fused
# ones differently in the two, so the closed forms of a bounce series (the times and
# positions of its events, states sampled in it) may differ in their last bits (1 ulp
# measured). Faces, kinds and counts are the same. Relative and absolute tolerance.
BATCH_ROUNDING = 1e-14

# The seed experiment.
SEED_BALLS = ("bocce", "golf", "pingpong")
SEED_E = (0.55, 0.70, 0.85)
SEED_MU = 0.98
SEED_VX = 1.15
SEED_X0 = -0.20
SEED_T_END = 2.3
G = 9.81


def jax_path():
    """Run estim's closed-form path on the JAX solver (the path of backends without its
    native kernels, estim.forward._native) instead of the kernels, within the block. Programs
    traced (jitted) before keep the path they were traced with."""
    from estim.forward._dispatch import jax_planner

    return jax_planner()


def seed_release(scene: estim.Scene, ball: str) -> np.ndarray:
    """Seed release point of ``ball``: x0 = -0.20, its y in the scene, 0.25 m above step1."""
    spec = scene.ball(ball)
    return np.array([SEED_X0, spec.position[1], 1.40 + spec.radius + 0.25])


def seed_arrays(scene: estim.Scene):
    """(e, mu_t, radius, position, velocity) of the three seed balls, as numpy arrays."""
    e = np.array(SEED_E)
    mu = np.full(3, SEED_MU)
    r = np.array([scene.ball(b).radius for b in SEED_BALLS])
    pos = np.stack([seed_release(scene, b) for b in SEED_BALLS])
    vel = np.tile([SEED_VX, 0.0, 0.0], (3, 1))
    return e, mu, r, pos, vel


def seed_params(scene: estim.Scene) -> estim.Params:
    """The seed Params (batch of 3: bocce e=.55, golf e=.70, pingpong e=.85)."""
    return estim.Params(*seed_arrays(scene))


def _pad_rows(x, n: int, event_shape: tuple[int, ...]) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    k = x.shape[0]
    if k > n:
        raise ValueError(f"batch of {k} balls exceeds the fixed batch size {n}")
    if k == n:
        return x
    return np.concatenate([x, np.broadcast_to(x[-1:], (n - k,) + event_shape)], axis=0)


def padded_params(e, mu_t, radius, position, velocity, n: int = B) -> tuple[estim.Params, int]:
    """Params padded to the fixed batch size ``n`` (by repeating the last ball).

    Scalars broadcast to the batch. Returns ``(params, k)`` with ``k`` the real balls.
    """
    position = np.atleast_2d(np.asarray(position, dtype=np.float64))
    velocity = np.atleast_2d(np.asarray(velocity, dtype=np.float64))
    k = max(position.shape[0], velocity.shape[0], np.size(e), np.size(mu_t), np.size(radius))
    arrays = [
        np.broadcast_to(np.asarray(e, dtype=np.float64), (k,)),
        np.broadcast_to(np.asarray(mu_t, dtype=np.float64), (k,)),
        np.broadcast_to(np.asarray(radius, dtype=np.float64), (k,)),
        np.broadcast_to(position, (k, 3)),
        np.broadcast_to(velocity, (k, 3)),
    ]
    shapes = [(), (), (), (3,), (3,)]
    padded = [_pad_rows(a, n, s) for a, s in zip(arrays, shapes, strict=True)]
    return estim.Params(*padded), k


def padded_ts(ts) -> jnp.ndarray:
    ts = np.asarray(ts, dtype=np.float64).reshape(-1)
    if ts.size > NT:
        raise ValueError(f"{ts.size} sample times exceed the fixed NT = {NT}")
    return jnp.asarray(_pad_rows(ts, NT, ()))


def run(scene, e, mu_t, radius, position, velocity, t_end, ts=None) -> estim.Trajectory:
    """``estim.simulate`` on a batch padded to B balls and NT sample times.

    Slice the result to the first k balls yourself (k = number of balls given); ``ts``
    defaults to NT equally spaced times on [0, t_end]. Runs with ``throw=False`` so that
    one ball exhausting ``max_segments`` does not hide the others: unless ``complete``
    is False is what a test expects, assert ``traj.complete`` (``assert_complete``).
    """
    params, _ = padded_params(e, mu_t, radius, position, velocity)
    if ts is None:
        ts = np.linspace(0.0, t_end, NT)
    return estim.simulate(scene, params, t_end, ts=padded_ts(ts), throw=False)


def assert_complete(traj, k: int = B) -> None:
    """Every one of the first k balls reached t_end within max_segments."""
    done = np.asarray(traj.complete[:k])
    assert done.all(), f"balls {np.flatnonzero(~done).tolist()} did not reach t_end"


def _outputs(scene, theta, radius, position, velocity, t_end, ts):
    """(final position, event times, sampled positions, complete as 0/1) with
    theta[:, :] = (e, mu_t, vx0); ``throw=False``: check ``complete`` yourself."""
    vel = velocity.at[:, 0].set(theta[:, 2])
    params = estim.Params(theta[:, 0], theta[:, 1], radius, position, vel)
    traj = estim.simulate(scene, params, t_end, ts=ts, throw=False)
    return traj.final.position, traj.events.t, traj.position, traj.complete.astype(jnp.float64)


# The derivative programs compile with estim's own options for the closed-form path (a jit
# around estim.simulate compiles with the caller's options, not estim's): with XLA:CPU's
# fusion emitters, the reverse-mode gradient of 64 balls bouncing 1000 times ran for 40 s
# instead of 0.1 s.
derivative_jit = functools.partial(jax.jit, compiler_options=compile_options(CLOSED_FORM_COMPILE))


@derivative_jit
def jac_outputs(scene, theta, radius, position, velocity, t_end, ts):
    """Per-ball Jacobians (jax.jacfwd) of ``_outputs`` w.r.t. (e, mu_t, vx0).

    Balls are independent, so shifting every ball's theta by the same ``delta`` (3,) and
    differentiating w.r.t. ``delta`` gives each ball's own derivatives. Returns
    ``(outputs, jacobians)``; each Jacobian leaf has a trailing axis of 3.
    """

    def f(delta):
        return _outputs(scene, theta + delta, radius, position, velocity, t_end, ts)

    zero = jnp.zeros(3)
    return f(zero), jax.jacfwd(f)(zero)


@derivative_jit
def grad_final_x(scene, theta, radius, position, velocity, t_end, ts):
    """jax.grad of ball 0's final x w.r.t. its (e, mu_t, vx0), by reverse mode. The
    simulation keeps the final state alone (``keep=()``), as a user's gradient of it
    would: the reverse-mode program of the whole trajectory took twice as long to compile
    (16 balls on exact geometry, tests/test_native.py: 170-179 s instead of 98 s, 2-core
    Intel machine; docs/pages/speed.md)."""

    def f(th0):
        th = theta.at[0].set(th0)
        params = estim.Params(th[:, 0], th[:, 1], radius, position, velocity.at[:, 0].set(th[:, 2]))
        return estim.simulate(scene, params, t_end, ts=ts, throw=False, keep=()).final.position[0, 0]

    return jax.grad(f)(theta[0])


@jax.jit
def evaluate(traj: estim.Trajectory, t):
    """Jitted ``Trajectory.evaluate`` (call it with t of shape (3, NT) only)."""
    return traj.evaluate(t)


def jac_args(e, mu_t, radius, position, velocity, t_end, ts=None):
    """Padded arguments for ``jac_outputs`` / ``grad_final_x`` (theta = (e, mu_t, vx0))."""
    params, k = padded_params(e, mu_t, radius, position, velocity)
    theta = jnp.stack([params.e, params.mu_t, params.velocity[:, 0]], axis=1)
    if ts is None:
        ts = np.linspace(0.0, t_end, NT)
    return (
        theta,
        params.radius,
        params.position,
        params.velocity,
        jnp.asarray(float(t_end)),
        padded_ts(ts),
    ), k


def box_distance(position, centre, half):
    """Euclidean distance of points (..., 3) from boxes (nb, 3): shape (..., nb). A ball of
    radius r is outside a box (exact geometry) where this is at least r."""
    d = np.abs(np.asarray(position)[..., None, :] - np.asarray(centre)) - np.asarray(half)
    return np.sqrt(np.sum(np.maximum(d, 0.0) ** 2, axis=-1))


@pytest.fixture(scope="session")
def stairs() -> estim.Scene:
    """The seed scene, with the seed's geometry (a tread is its faces)."""
    return estim.load_scene(STAIRS_XML)


@pytest.fixture(scope="session")
def stairs_exact() -> estim.Scene:
    """The seed's staircase with exact edges and corners."""
    return estim.load_scene(STAIRS_EXACT_XML)


@pytest.fixture(scope="session")
def yard() -> estim.Scene:
    """A flat ground plane z = 0 and a wall box x in [3.0, 3.2], |y| <= 2, z in [0, 1]."""
    return estim.Scene.from_arrays(
        boxes={"wall": ((3.1, 0.0, 0.5), (0.1, 2.0, 0.5))},
        planes={"ground": ((0.0, 0.0, 1.0), 0.0)},
        gravity=G,
    )


@pytest.fixture(scope="session")
def kit():
    """The helpers of this module, for tests that prefer a fixture to an import."""
    return types.SimpleNamespace(
        B=B,
        NT=NT,
        G=G,
        run=run,
        padded_params=padded_params,
        padded_ts=padded_ts,
        jac_outputs=jac_outputs,
        grad_final_x=grad_final_x,
        jac_args=jac_args,
        evaluate=evaluate,
        seed_arrays=seed_arrays,
        seed_params=seed_params,
        seed_release=seed_release,
        box_distance=box_distance,
        SEED_T_END=SEED_T_END,
        SEED_MU=SEED_MU,
        SEED_VX=SEED_VX,
        SEED_E=SEED_E,
    )
