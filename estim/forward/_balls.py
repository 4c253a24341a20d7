"""One ball at a time: the parameters of a batch as a flat row of balls, the loop over
them, one ball's trajectory parts from its plan, and whether a ball stays outside every
solid. Shared by the JAX path (``estim.forward._simulate``) and the native one
(``estim.forward._native``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..model._params import Params
from ..model._scene import Scene
from ._constants import INSIDE_DEPTH, ROLL, TRAIN
from ._contact import has_edges
from ._record import layout_of, pack, unpack
from ._solver import Plan, segments_of
from ._trajectory import (
    ClosedFormSolution,
    State,
    list_events_used,
    roll_states,
    sample,
    trajectory_parts,
)
from .laws import law_of


def flat_params(params: Params) -> Params:
    """The parameters with every field broadcast to the batch and flattened to one axis of balls."""
    batch = params.batch_shape

    def flatten(x, event_shape):
        return jnp.broadcast_to(x, batch + event_shape).reshape((-1,) + event_shape)

    mass = None if params.mass is None else flatten(params.mass, ())
    return Params(
        flatten(params.e, ()), flatten(params.mu_t, ()), flatten(params.radius, ()),
        flatten(params.position, (3,)), flatten(params.velocity, (3,)), mass=mass,
        drag_coefficient=flatten(params.drag_coefficient, ()), spin=flatten(params.spin, (3,)),
        mu=flatten(params.mu, ()), inertia=flatten(params.inertia, ()), lift_factor=flatten(params.lift_factor, ()),
        e_slope=flatten(params.e_slope, ()), compression=flatten(params.compression, ()),
    )


# The most parameter fields packed into one row: XLA:CPU fuses a concatenation of at most 8
# pieces (and its producers) into one kernel, and splits a longer one into a kernel per piece.
# Params' 11 fields in one row made jacfwd of the golf ball's final x 17 kernels instead of 7,
# 63 us instead of 26 (2-core reference machine, jax 0.10.2); in rows of 7, one kernel each.
ROW_LEAVES = 7


def param_rows(flat: Params):
    """Flat parameters as rows per ball, ``ROW_LEAVES`` fields each: ``(rows, layouts,
    treedef)``, the rows' layouts (``estim.forward._record``, a part ``"leaves"`` each) and
    the tree of the fields. The first row holds e, mu_t, radius, position, velocity and compression."""
    leaves, treedef = jax.tree.flatten(flat)
    groups = [{"leaves": tuple(leaves[i:i + ROW_LEAVES])} for i in range(0, len(leaves), ROW_LEAVES)]
    layouts = tuple(layout_of(group, 1) for group in groups)
    rows = tuple(pack(group, layout, (flat.e.shape[0],))[0] for group, layout in zip(groups, layouts, strict=True))
    return rows, layouts, treedef


def map_balls(fn, flat: Params, *per_ball):
    """``jax.lax.map`` of ``fn(params, *items)`` over the balls of flat parameters (and
    of the arrays ``per_ball``, one item per ball). The parameters enter the loop as rows
    per ball (``ROW_LEAVES`` fields each), each gathered by one kernel: where the caller
    computes them (slices and stacks of a theta under jacfwd), that is a kernel or two
    instead of one per field."""
    rows, layouts, treedef = param_rows(flat)

    def body(items):
        parts = [unpack(row, None, layout, "leaves") for row, layout in zip(items[:len(rows)], layouts, strict=True)]
        return fn(jax.tree.unflatten(treedef, [x for part in parts for x in part]), *items[len(rows):])

    return jax.lax.map(body, rows + per_ball)


def ball_parts(scene: Scene, prm: Params, t_end, ts, pl: Plan, max_events: int, keep: frozenset[str]) -> dict:
    """One ball's Trajectory parts from its plan (``estim.forward._trajectory.trajectory_parts``),
    differentiably: the segments of ``pl`` with the derivatives of their replay, then the
    samples, events, final state and dense solution that ``keep`` keeps. The JAX path runs
    this for its primal; the native path for its tangent (``estim.forward._native``)."""
    g = scene.gravity
    law = law_of(scene)
    c = law.coefficients(prm)
    segments = segments_of(scene, prm, t_end, pl.decisions, pl.segments, pl.n_segments)
    pos = vel = events = None  # only what keep keeps is computed
    if "samples" in keep:
        pos, vel = sample(segments, pl.decisions, law, c, g, ts, has_edges(scene))
    if "events" in keep:
        events = list_events_used(segments, pl.decisions, law, c, g, max_events, pl.n_segments)
    last = jnp.maximum(pl.n_segments - 1, 0)
    final = State(t_end, segments.p1[last], segments.v1_post[last])
    solution = ClosedFormSolution(segments=segments, structure=pl.decisions, law=law, coefficients=c, gravity=g,
                                  rolls=has_edges(scene))
    complete = pl.complete & stays_outside(scene, prm.contact_radius, pl.decisions, pl.segments, pl.n_segments)
    return trajectory_parts(pos, vel, events, final, complete, solution, keep)


def inside(xp, scene: Scene, p, r, path: bool = False):
    """Which solids balls of centres ``p (n, 3)`` and radii ``r (n,)`` are inside (deeper
    than ``INSIDE_DEPTH``, 1 nm): ``(n, boxes)`` and ``(n, planes)`` booleans. A box is
    entered where the centre is closer than r to it, in the scene's geometry
    (``estim.model._scene``): the Euclidean distance from the box for exact geometry; for
    the seed's, the distance beyond one face only (a centre beyond two or three faces at
    once is off the box's edges and corners, which that geometry does not have). Along a
    path (``path``) the seed's geometry lets a ball pass a box's corner and overlap the face
    beyond it, as the seed does; there only a centre inside the box itself is inside."""
    c, h = xp.asarray(scene.box_centre), xp.asarray(scene.box_half)
    gap = xp.abs(p[:, None, :] - c[None]) - h[None]
    excess = xp.maximum(gap, 0.0)
    if scene.geometry == "exact":
        box = xp.sqrt(xp.sum(excess * excess, axis=-1)) < r[:, None] - INSIDE_DEPTH
    elif path:
        box = xp.max(gap, axis=-1) < -INSIDE_DEPTH
    else:
        beyond = xp.sum((excess > 0).astype(excess.dtype), axis=-1)
        box = (beyond <= 1) & (xp.sum(excess, axis=-1) < r[:, None] - INSIDE_DEPTH)
    n, s = xp.asarray(scene.plane_normal), xp.asarray(scene.plane_offset)
    height = sum(p[:, None, k] * n[None, :, k] for k in range(3))  # p @ n.T, written out (estim._fold.inner)
    return box, height < s[None] + r[:, None] - INSIDE_DEPTH


def stays_outside(scene: Scene, radius, decisions, segments, n_segments):
    """Whether the planned path keeps the ball outside every solid at the start, middle and
    end of each segment it uses (the middle of a bounce series is not on one parabola, and
    is not tested). A guard, not a solver: the closed forms find every contact of a
    generic path, and this catches a degenerate one they miss (found: a flight whose apex
    grazes a tread top 1e-12 m inside its edge, a ball sliding off an edge from 1e-12 m
    inside it; docs/pages/hard-cases.md) so that the ball is reported incomplete instead
    of passing through the solid."""
    s = jax.lax.stop_gradient(segments)
    tau = 0.5 * (s.t1 - s.t0)[:, None]
    middle = s.p0 + s.v0 * tau + 0.5 * s.acc * tau * tau
    middle = jnp.where((decisions.kind == TRAIN)[:, None], s.p0, middle)
    if has_edges(scene):  # (a roll's middle is on its circle)
        is_roll = decisions.kind == ROLL
        middle = jax.lax.cond(jnp.any(is_roll),
                              lambda: jnp.where(is_roll[:, None], roll_states(s, is_roll, tau[:, 0], scene.gravity)[0],
                                                middle),
                              lambda: middle)
    points = jnp.stack([s.p0, middle, s.p1], axis=1).reshape(-1, 3)
    used = jnp.repeat(jnp.arange(s.t0.shape[0]) < n_segments, 3)
    r = jax.lax.stop_gradient(radius)
    inside_box, inside_plane = inside(jnp, scene, points, jnp.broadcast_to(r, used.shape), path=True)
    into = jnp.any(inside_box, axis=1) | jnp.any(inside_plane, axis=1)
    return ~jnp.any(used & into)


def solids_at_release(scene: Scene, params: Params) -> list[tuple[str, ...]]:
    """The names of the solids each ball of ``params`` (concrete values) starts in: closer
    to them than its contact radius (radius - compression); one tuple per ball, flattened
    over the batch."""
    batch = params.batch_shape
    p = np.broadcast_to(np.asarray(params.position), batch + (3,)).reshape(-1, 3)
    # (In NumPy: inside a user's jit even concrete fields' JAX arithmetic is traced.)
    r = np.broadcast_to(np.asarray(params.radius) - np.asarray(params.compression), batch).reshape(-1)
    inside_box, inside_plane = inside(np, scene, p, r)
    return [tuple(scene.names[j] for j in np.flatnonzero(inside_box[i]))
            + tuple(scene.names[scene.n_boxes + j] for j in np.flatnonzero(inside_plane[i])) for i in range(len(p))]


def resting_on(scene: Scene, p, r, tol: float) -> tuple[str, float] | None:
    """The solid whose upward face a ball of centre ``p (3,)`` and contact radius ``r``
    rests on, and the centre's height there, or None: a box top whose outline holds the
    centre (its x and y within the box's) or an upward plane, the centre within ``tol`` of
    ``r`` above it (gravity points along -z). The highest such face where several are."""
    p = np.asarray(p, dtype=np.float64)
    found = []
    for name, c, h in zip(scene.names, np.asarray(scene.box_centre), np.asarray(scene.box_half), strict=False):
        if np.all(np.abs(p[:2] - c[:2]) <= h[:2]):
            found.append((name, float(c[2] + h[2] + r)))
    for name, n, o in zip(scene.names[scene.n_boxes:], np.asarray(scene.plane_normal),
                          np.asarray(scene.plane_offset), strict=True):
        if n[2] == 1.0:
            found.append((name, float(o + r)))
    found = [(name, z) for name, z in found if abs(p[2] - z) <= tol]
    return max(found, key=lambda f: f[1]) if found else None


def check_outside(scene: Scene, params: Params, names=None) -> None:
    """A ball must not start inside a solid (checked here when the values are concrete;
    inside a user's jit by ``_input_code``). ``names``: the balls' names, for the message."""
    leaves = (params.position, params.radius, params.compression, scene.box_centre)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return
    for i, hit in enumerate(solids_at_release(scene, params)):
        if hit:
            p = np.broadcast_to(np.asarray(params.position), params.batch_shape + (3,)).reshape(-1, 3)
            r = np.broadcast_to(np.asarray(params.radius) - np.asarray(params.compression),
                                params.batch_shape).reshape(-1)
            who = f"ball {i}" if names is None else f"ball {names[i]!r}"
            raise ValueError(
                f"{who} starts inside {hit[0]!r}: its centre {p[i].tolist()} is closer "
                f"than its contact radius {r[i]} (radius - compression) to the solid (release it outside "
                "every solid)"
            )
