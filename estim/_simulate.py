"""The one entry point: simulate any number of balls in a scene."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from ._config import require_x64
from ._params import Params, check_runtime, check_t_end
from ._scene import Scene
from ._solver import plan, segments_of
from ._trajectory import State, Trajectory, list_events, sample

__all__ = ["simulate"]


def simulate(
    scene: Scene,
    params: Params,
    t_end: float | ArrayLike,
    *,
    ts: Float[ArrayLike, " times"] | None = None,
    max_segments: int = 48,
    max_events: int = 64,
    throw: bool = True,
) -> Trajectory:
    """Simulate balls bouncing in a scene over ``[0, t_end]``, exactly.

    With only gravity acting, every flight is a parabola and every contact time the root of
    a quadratic, so the result is exact to rounding and no contact can be missed; bounce
    series (including Zeno series with infinitely many bounces) are summed in closed form
    (see ``estim._solver``). The result is differentiable (``jax.grad``, ``jax.jacfwd``)
    with respect to every field of ``params``, ``t_end``, the sample times and the scene
    geometry; derivatives of event times are the event-time sensitivities of the hybrid
    system.

    Args:
        scene: the scene (:func:`estim.load_scene`).
        params: per-ball parameters; all balls of a batch are simulated together (vmap).
        t_end: final time (s), > 0.
        ts: sample times in ``[0, t_end]``; default ``[0, t_end]``.
        max_segments: static bound on the closed-form segments per ball (a segment is a
            flight, a whole bounce series on one face, or a slide). Bounded compute: a ball
            that would need more is reported (``throw``).
        max_events: static size of the event list per ball.
        throw: raise if a ball needs more than ``max_segments``; otherwise return with
            ``complete = False`` for that ball.

    Returns:
        A :class:`Trajectory`.

    Example:
        >>> scene = estim.load_scene("data/scenes/stairs.xml")
        >>> golf = estim.Params.for_ball(scene, "golf", e=0.7, mu_t=0.98, velocity=(1.15, 0, 0))
        >>> traj = estim.simulate(scene, golf, 2.3)
        >>> traj.final.position  # doctest: +SKIP
    """
    require_x64()
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be an estim.Scene (estim.load_scene), got {type(scene).__name__}")
    if not isinstance(params, Params):
        raise TypeError(f"params must be an estim.Params, got {type(params).__name__}")
    check_t_end(t_end)
    t_end = jnp.asarray(t_end, dtype=jnp.float64)
    if ts is None:
        ts = jnp.stack([jnp.zeros(()), t_end])
    ts = jnp.asarray(ts, dtype=jnp.float64)
    if ts.ndim != 1:
        raise ValueError(f"ts must be one-dimensional, got shape {ts.shape}")
    if not isinstance(ts, jax.core.Tracer) and not isinstance(t_end, jax.core.Tracer):
        tv = np.asarray(ts)
        if not np.all(np.isfinite(tv)) or np.any(tv < 0) or np.any(tv > float(t_end)):
            raise ValueError(f"ts must be finite and lie in [0, t_end={float(t_end)}]")
    _check_outside(scene, params)
    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((scene, params, t_end, ts)))
    # Called with concrete values, the inputs were checked above and completion is checked
    # below, in Python: the compiled program then has no host callbacks and can live in
    # JAX's persistent compilation cache. Inside a user's jit/grad the checks run in-graph.
    traj = _simulate(scene, params, t_end, ts, max_segments, max_events, throw and traced)
    if throw and not traced and not bool(np.all(np.asarray(traj.complete))):
        raise RuntimeError(_INCOMPLETE)
    return traj


_INCOMPLETE = (
    "a ball needed more closed-form segments than max_segments; increase max_segments "
    "(this happens for balls trapped between walls, not for Zeno bounce series, which are "
    "summed exactly), or pass throw=False and inspect Trajectory.complete"
)


@eqx.filter_jit
def _simulate(scene, params, t_end, ts, max_segments, max_events, checks):
    batch = params.batch_shape
    if checks:
        params = check_runtime(params, t_end)

    def flatten(x, event_shape):
        return jnp.broadcast_to(x, batch + event_shape).reshape((-1,) + event_shape)

    flat = Params(
        flatten(params.e, ()), flatten(params.mu_t, ()), flatten(params.radius, ()),
        flatten(params.position, (3,)), flatten(params.velocity, (3,)),
    )

    def one(prm):
        pl = plan(scene, prm, t_end, max_segments)
        segments = segments_of(scene, prm, t_end, pl.decisions, pl.segments)
        pos, vel = sample(segments, pl.decisions, prm.e, prm.mu_t, scene.gravity, ts)
        events = list_events(segments, pl.decisions, prm.e, prm.mu_t, scene.gravity, max_events)
        last = jnp.maximum(pl.n_segments - 1, 0)
        final = State(t_end, segments.p1[last], segments.v1_post[last])
        return pos, vel, events, final, segments, pl.decisions, pl.complete

    pos, vel, events, final, segments, decisions, complete = jax.vmap(one)(flat)
    if checks:
        pos = eqx.error_if(pos, ~jnp.all(complete), _INCOMPLETE)

    def unflat(x):
        return x.reshape(batch + x.shape[1:])

    return Trajectory(
        ts=ts,
        position=unflat(pos),
        velocity=unflat(vel),
        events=jax.tree.map(unflat, events),
        final=jax.tree.map(unflat, final),
        segments=jax.tree.map(unflat, segments),
        structure=jax.tree.map(unflat, decisions),
        e=unflat(flat.e),
        mu_t=unflat(flat.mu_t),
        gravity=scene.gravity,
        complete=unflat(complete),
    )


def _check_outside(scene: Scene, params: Params) -> None:
    """A ball must not start inside a solid (checked when the values are concrete)."""
    leaves = (params.position, params.radius, scene.box_centre)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return
    batch = params.batch_shape
    p = np.broadcast_to(np.asarray(params.position), batch + (3,)).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(params.radius), batch).reshape(-1)
    c, h = np.asarray(scene.box_centre), np.asarray(scene.box_half)
    depth = np.sum(np.maximum(np.abs(p[:, None, :] - c[None]) - h[None], 0.0), axis=-1)
    inside_box = depth < r[:, None] - 1e-9
    n, s = np.asarray(scene.plane_normal), np.asarray(scene.plane_offset)
    inside_plane = (p @ n.T) < s[None] + r[:, None] - 1e-9
    for i in range(p.shape[0]):
        hit = [scene.names[j] for j in np.flatnonzero(inside_box[i])]
        hit += [scene.names[scene.n_boxes + j] for j in np.flatnonzero(inside_plane[i])]
        if hit:
            raise ValueError(
                f"ball {i} starts inside {hit[0]!r}: its centre {p[i].tolist()} is closer "
                f"than its radius {r[i]} to the solid (release it outside every solid)"
            )
