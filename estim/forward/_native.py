"""The closed-form solver's primal on native CPU kernels, its derivatives in JAX.

``estim/forward/_kernels.cc`` ports the gravity-only solver of ``estim.forward._solver``,
``estim.forward._contact`` and ``estim.forward._trajectory``, with the seed's contact law
(``estim.forward.laws.FactorLaw``), line by line to C++, and JAX calls it through its
foreign function interface (``jax.ffi``). What the kernels
compute is the *primal*: each ball's plan (the discrete structure of its solution and its
segments) and its packed :class:`estim.Trajectory` rows. Derivatives never enter them:

- :func:`plan` gives the same :class:`estim.forward._solver.Plan` as the JAX planner, as values
  with no derivatives (the JAX planner stops gradients too); ``segments_of`` then
  differentiates by replaying the structure in JAX, as before.
- :func:`trajectory_rows` is a ``jax.custom_jvp``: its tangent replays the ball's
  structure (found by :func:`plan`) through the same differentiable JAX pipeline that
  the JAX path runs (``estim.forward._simulate.ball_parts``): samples, events, final state and
  dense solution, packed. Forward and reverse mode, ``vmap`` and ``jit`` all compose.

Why: the JAX program of the event loop is one XLA kernel of some 26,000 HLO lines, which
XLA:CPU takes 2.5 s to compile at every new process and whose buffers cost a call some
tens of microseconds; the kernels are compiled once, at install (docs/pages/speed.md).

The kernels accelerate what they support and say so: :func:`supports` is true for the
factor law in a scene without air, and :func:`runs` is the one dispatch of the closed-form
path (``estim.simulate``, the fit, the sensitivities): the kernels where they are
:func:`active` and support the scene's law, the JAX planner otherwise, with the same
results to rounding (``tests/test_native.py`` checks them ball by ball; a scene with air
goes to the ODE path, ``estim.forward._ode``). The kernels run on the CPU backend only:
where they are not built (no C++ compiler at install), were built with other shared
constants than ``estim.forward._constants`` (a stale build), where JAX's default backend
is not the CPU, or with ``ESTIM_NATIVE=0`` in the environment, estim runs the JAX planner.
"""

from __future__ import annotations

import functools
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from .._config import keep_loop
from ..model._scene import Scene
from . import _constants
from ._balls import ball_parts, flat_params, map_balls, param_rows
from ._contact import faces_for, has_edges
from ._record import Layout, layout_of, pack
from ._solver import Decision, Plan, Segment
from ._trajectory import KEEP, ClosedFormSolution, Events, State, trajectory_parts
from .laws import AbstractContactLaw, FactorCoefficients, FactorLaw, law_of

try:  # the extension built from estim/forward/_kernels.cc (setup.py)
    from . import _kernels
except ImportError:  # pragma: no cover - an install without a C++ compiler
    _kernels = None

__all__ = ["available", "active", "supports", "runs", "stale_constants", "plan", "trajectory_rows",
           "trajectory_layout", "FIELDS"]

# The fields of a Trajectory's rows the kernel writes, in the order of its `Field` enum.
FIELDS = (
    "final.t", "final.position", "final.velocity", "complete",
    "position", "velocity",
    "events.t", "events.position", "events.velocity_pre", "events.velocity_post", "events.face",
    "events.kind", "events.count", "events.truncated",
    "solution.segments.t0", "solution.segments.p0", "solution.segments.v0", "solution.segments.acc",
    "solution.segments.t1", "solution.segments.p1", "solution.segments.v1", "solution.segments.v1_post",
    "solution.segments.normal", "solution.segments.pivot",
    "solution.structure.kind", "solution.structure.support", "solution.structure.n",
    "solution.structure.reason", "solution.structure.face",
    "solution.coefficients.e", "solution.coefficients.mu_t",
)
# Numbers per segment in the plan kernel's output: t0, p0, v0, acc, t1, p1, v1, v1_post, normal, pivot.
_SEGMENT = (("t0", 1), ("p0", 3), ("v0", 3), ("acc", 3), ("t1", 1), ("p1", 3), ("v1", 3), ("v1_post", 3),
            ("normal", 3), ("pivot", 3))

# Whether estim uses the kernels where it can (tests switch it to compare both paths).
ENABLED = os.environ.get("ESTIM_NATIVE", "1") != "0"


@functools.cache
def stale_constants() -> dict[str, tuple[float, float]]:
    """The shared constants the kernels were built with that differ from
    ``estim.forward._constants`` (name -> (kernels, Python)), a name missing on either side
    as NaN; empty for a current build (or none)."""
    if _kernels is None:
        return {}
    built = _kernels.constants()
    ours = {name: float(value) for name, value in _constants.exported().items()}
    return {name: (built.get(name, math.nan), ours.get(name, math.nan))
            for name in sorted(set(built) | set(ours)) if built.get(name) != ours.get(name)}


def available() -> bool:
    """Whether the native kernels were built (at install), with the shared constants of this
    estim (``estim.forward._constants``; a stale build is not used: rebuild with
    ``pip install -e .``)."""
    return _kernels is not None and not stale_constants()


def active() -> bool:
    """Whether the native kernels run now where they support the scene: built (and
    current), not switched off (``ESTIM_NATIVE=0``), and JAX's default backend is the CPU."""
    return ENABLED and available() and jax.default_backend() == "cpu"


def supports(law: AbstractContactLaw, scene: Scene) -> bool:
    """Whether the kernels compute the closed-form path of ``scene`` under ``law``: the
    seed's factor law (``estim.forward.laws.FactorLaw``, the only law they implement) in a
    scene without air (a scene with air takes the ODE path), in either geometry (the
    seed's, or exact edges and corners with their rolls). Anything else runs on the JAX
    planner, with the same results."""
    return isinstance(law, FactorLaw) and scene.air is None


def runs(scene: Scene) -> bool:
    """The dispatch of the closed-form path: whether the kernels run ``scene`` now
    (:func:`active` and :func:`supports` its contact law), else the JAX planner does."""
    return active() and supports(law_of(scene), scene)


def _check_supported(scene: Scene) -> None:
    law = law_of(scene)
    if not supports(law, scene):
        raise ValueError(
            f"the native kernels do not support the contact law {type(law).__name__} in this scene "
            "(estim.forward._native.supports: the factor law without air); use the JAX planner "
            "(estim.forward._solver.plan), which estim.forward._native.runs(scene) chooses"
        )


@functools.cache
def _register() -> None:
    for name, capsule in _kernels.handlers().items():
        jax.ffi.register_ffi_target(name, capsule, platform="cpu")


def _scene_operands(scene: Scene) -> tuple[jax.Array, np.ndarray]:
    """The scene as the kernels read it: the face table (``estim.forward._contact.Faces``, for
    radius 0: the kernels grow it by each ball's radius; its ranks as numbers), the solids
    and gravity, as one array (each flattened, one after the other, in the order of the
    kernel's ``SceneBuffers``), and the counts of faces, solids, boxes and planes that say
    where each begins, and whether the geometry is exact (the kernel's ``counts``
    attribute)."""
    faces = faces_for(scene, jnp.float64(0.0))
    numbers = (faces.row, faces.growth, faces.rank, faces.box_lo, faces.box_hi, scene.box_centre, scene.box_half,
               scene.plane_normal, scene.plane_offset, scene.gravity)
    counts = np.array([faces.growth.shape[0], faces.box_lo.shape[0], scene.box_centre.shape[0],
                       scene.plane_offset.shape[0], scene.geometry == "exact"], dtype=np.int64)
    return jnp.concatenate([jnp.ravel(x).astype(jnp.float64) for x in numbers]), counts


def plan(scene: Scene, params, t_end, max_segments: int) -> Plan:
    """``estim.forward._solver.plan`` on the native kernel, for balls of any batch shape: the
    discrete structure of each ball's solution and its segments, as values (no
    derivatives flow through a plan). ``ValueError`` where the kernels do not
    :func:`supports` the scene's contact law."""

    _check_supported(scene)
    _register()
    scene, params, t_end = jax.lax.stop_gradient((scene, params, jnp.asarray(t_end, jnp.float64)))
    batch = params.batch_shape
    # One row of parameters per ball, packed as the JAX loop over balls packs them
    # (estim.forward._simulate.map_balls): where both run, as in a derivative, XLA gathers them once.
    flat = flat_params(params)
    n = flat.e.shape[0]
    (rows, *_), (layout, *_), _ = param_rows(flat)  # (the first row: the fields the kernels read)
    # e, mu_t, radius, position, velocity, compression
    param_columns = np.array([leaf.start for leaf in layout.parts[0][2][:6]], dtype=np.int64)
    S = max_segments

    def out(shape, dtype):
        return jax.ShapeDtypeStruct(shape, dtype)

    shapes = (out((n, S), jnp.int32), out((n, S), jnp.int32), out((n, S), jnp.float64), out((n, S), jnp.int32),
              out((n, S), jnp.int32), out((n, S, 26), jnp.float64), out((n,), jnp.int32), out((n,), jnp.bool_))
    call = jax.ffi.ffi_call("estim_plan", shapes, vmap_method="expand_dims")
    scene_numbers, counts = _scene_operands(scene)
    kind, support, count, reason, face, numbers, n_segments, complete = call(
        scene_numbers, rows, t_end, counts=counts, columns=param_columns)
    columns, start = {}, 0
    for name, size in _SEGMENT:
        columns[name] = numbers[..., start] if size == 1 else numbers[..., start:start + size]
        start += size

    def unflat(x):
        return x.reshape(batch + x.shape[1:])

    decisions = Decision(kind, support, count, reason, face)
    return Plan(decisions=jax.tree.map(unflat, decisions), segments=jax.tree.map(unflat, Segment(**columns)),
                n_segments=unflat(n_segments), complete=unflat(complete))


@functools.lru_cache(maxsize=64)
def trajectory_layout(n_times: int, max_segments: int, max_events: int, keep: frozenset[str],
                      rolls: bool) -> Layout:
    """The layout of one ball's Trajectory rows (``estim.forward._record``), as the JAX path packs
    them: built from placeholder parts of the right shapes and dtypes. ``rolls``: whether the
    scene has edges and corners (``estim.forward._contact.has_edges``)."""
    S, E = max_segments, max_events

    def f64(*shape):
        return np.zeros(shape)

    def i32(*shape):
        return np.zeros(shape, np.int32)

    flag = np.zeros((), bool)
    events = Events(f64(E), f64(E, 3), f64(E, 3), f64(E, 3), i32(E), i32(E), i32(), flag)
    final = State(f64(), f64(3), f64(3))
    segments = Segment(f64(S), f64(S, 3), f64(S, 3), f64(S, 3), f64(S), f64(S, 3), f64(S, 3), f64(S, 3), f64(S, 3),
                       f64(S, 3))
    structure = Decision(i32(S), i32(S), f64(S), i32(S), i32(S))
    # (The kernels' law: the JAX path's layout for a scene they support.)
    solution = ClosedFormSolution(segments=segments, structure=structure, law=FactorLaw(),
                                  coefficients=FactorCoefficients(f64(), f64()), gravity=f64(), rolls=rolls)
    parts = trajectory_parts(f64(n_times, 3), f64(n_times, 3), events, final, flag, solution, keep)
    return layout_of(parts, 0)


@functools.lru_cache(maxsize=64)
def _field_columns(layout: Layout) -> np.ndarray:
    """Where each field of ``FIELDS`` starts in the rows of ``layout`` (-1: not kept)."""
    start = dict.fromkeys(FIELDS, -1)
    for name, treedef, leaves in layout.parts:
        placeholder = jax.tree.unflatten(treedef, [np.zeros(leaf.shape) for leaf in leaves])
        paths = [name + jax.tree_util.keystr(path) for path, _ in jax.tree_util.tree_flatten_with_path(placeholder)[0]]
        for path, leaf in zip(paths, leaves, strict=True):
            if path not in start:
                raise AssertionError(f"estim.forward._native: the kernel does not write the trajectory field {path!r}")
            start[path] = leaf.start
    return np.array([start[f] for f in FIELDS], dtype=np.int64)


@functools.partial(jax.custom_jvp, nondiff_argnums=(4, 5, 6, 7, 8))
def trajectory_rows(scene: Scene, params, t_end, ts, max_segments: int, max_events: int, keep: frozenset[str],
                    checks: bool, messages: tuple[str, ...]):
    """Every ball's packed Trajectory rows ``(numbers, integers)``, flat (one axis of balls
    in the order of ``params.batch_shape``), laid out by ``trajectory_layout``. With
    ``checks`` the kernel also checks the inputs and the completion of every ball, and
    fails with the first message of ``messages`` that applies (in the order of
    ``estim.forward._simulate``). ``ValueError`` where the kernels do not :func:`supports`
    the scene's contact law."""

    _check_supported(scene)
    _register()
    batch = params.batch_shape
    n = math.prod(batch)
    layout = trajectory_layout(ts.shape[0], max_segments, max_events, keep, has_edges(scene))
    shapes = (jax.ShapeDtypeStruct((n, layout.n_numbers), jnp.float64),
              jax.ShapeDtypeStruct((n, layout.n_integers), jnp.int32))
    call = jax.ffi.ffi_call("estim_trajectory", shapes, vmap_method="expand_dims")

    each = flat_params(params)

    def one_or_each(x, flat, event):  # (no copy per ball of a value shared by all balls)
        return x.reshape((1,) + event) if x.shape == event else flat

    mass = jnp.zeros((0,)) if params.mass is None else one_or_each(params.mass, each.mass, ())
    scene_numbers, counts = _scene_operands(scene)
    return call(scene_numbers, one_or_each(params.e, each.e, ()), one_or_each(params.mu_t, each.mu_t, ()),
                one_or_each(params.radius, each.radius, ()), one_or_each(params.position, each.position, (3,)),
                one_or_each(params.velocity, each.velocity, (3,)),
                one_or_each(params.compression, each.compression, ()), mass,
                one_or_each(params.drag_coefficient, each.drag_coefficient, ()), one_or_each(params.spin, each.spin, (3,)),
                t_end, ts,
                max_segments=np.int64(max_segments), max_events=np.int64(max_events), checks=bool(checks),
                fields=_field_columns(layout), messages="\n".join(messages), counts=counts)


@trajectory_rows.defjvp
def _trajectory_rows_jvp(max_segments, max_events, keep, checks, messages, primals, tangents):

    scene, params, t_end, ts = primals
    numbers, integers = trajectory_rows(scene, params, t_end, ts, max_segments, max_events, keep, checks, messages)
    plans = plan(scene, params, t_end, max_segments)
    plans = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[len(params.batch_shape):]), plans)
    layout = trajectory_layout(ts.shape[0], max_segments, max_events, keep, has_edges(scene))

    def rows(scene, params, t_end, ts):
        def ball(prm, pl):
            return pack(ball_parts(scene, prm, t_end, ts, pl, max_events, keep), layout)[0]

        rows = map_balls(ball, flat_params(params), plans)
        # As on the JAX path (estim.forward._simulate): where the caller said what to keep, the
        # loop stays one kernel, also for one ball; else XLA may inline it and drop what
        # the caller leaves unused.
        return rows if keep == frozenset(KEEP) else keep_loop(rows)

    _, d_numbers = jax.jvp(rows, primals, tangents)
    return (numbers, integers), (d_numbers, np.zeros(integers.shape, jax.dtypes.float0))
