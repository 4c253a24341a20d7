"""Event-time sensitivities two ways: autodiff through the solver, and the implicit
function theorem, so that one can be checked against the other.

An event happens at the time t* where the guard of the face touched,
``g(x, theta) = n . x - H(theta)``, reaches zero along the flow ``x(t, theta)``. Differentiating
``g(x(t*(theta), theta), theta) = 0`` gives the implicit-function formula

    dt*/dtheta = -( dg/dtheta + dg/dx . dx/dtheta ) / ( dg/dx . dx/dt ),                (1)

where ``dx/dtheta`` is the sensitivity of the state at the *fixed* time t* (the solution of
the variational equation, here the derivative of the closed-form flight that ends at the
event), and the denominator is the rate at which the guard closes just before the event.
At a grazing contact that rate vanishes and (1) blows up: such events are flagged instead of
returning inf or NaN.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._config import require_x64
from ..model._params import Params
from ..model._scene import Scene
from ._contact import NORMAL, faces_for
from ._dispatch import closed_form_plan
from ._solver import segments_of
from ._trajectory import event_flights, list_events
from .laws import law_of

__all__ = ["EventSensitivity", "event_sensitivities"]


class EventSensitivity(eqx.Module):
    """Sensitivities of the event times of one ball.

    Attributes:
        t: event times (padding ``inf``), as in :class:`estim.Events`.
        autodiff: ``d t_i / d theta`` from differentiating the solver, ``(events, params)``.
        implicit: the same from equation (1) of this module.
        closing_speed: ``dg/dt`` just before each event (negative at an impact).
        grazing: the closing speed is below ``grazing_speed`` in magnitude: (1) is
            ill-conditioned there (its value uses a floored denominator and is not to be
            trusted; autodiff stays finite).
        valid: the slot holds a contact event that crosses a face (not padding, not the
            accumulation point of a Zeno series).
    """

    t: Float[Array, " events"]
    autodiff: Float[Array, "events params"]
    implicit: Float[Array, "events params"]
    closing_speed: Float[Array, " events"]
    grazing: Bool[Array, " events"]
    valid: Bool[Array, " events"]


def event_sensitivities(
    make: Callable[[Float[Array, " params"]], Params | tuple[Scene, Params]],
    theta: Float[Array, " params"],
    t_end: float,
    *,
    scene: Scene | None = None,
    max_segments: int = 48,
    max_events: int = 64,
    grazing_speed: float = 1e-6,
) -> EventSensitivity:
    """Event-time sensitivities of one ball by autodiff and by equation (1).

    Args:
        make: maps a parameter vector theta to the ball's :class:`estim.Params` (one ball,
            no batch dimension), or to ``(scene, params)`` to differentiate with respect to
            the scene geometry as well.
        theta: the parameter vector.
        t_end: final time (s).
        scene: the scene, when ``make`` returns only ``Params``.
        grazing_speed: closing speed (m/s) below which an event is flagged as grazing.

    Example:
        >>> def make(th):
        ...     return estim.Params(th[0], th[1], 0.05, jnp.array([-0.2, 0, 1.7]),
        ...                         jnp.stack([th[2], 0.0, 0.0]))
        >>> s = estim.event_sensitivities(make, jnp.array([0.7, 0.98, 1.15]), 2.3, scene=scene)
        >>> jnp.max(jnp.abs(s.autodiff - s.implicit)[s.valid])  # doctest: +SKIP
    """
    require_x64()
    theta = jnp.asarray(theta, dtype=jnp.float64)

    if scene is None and not isinstance(jax.eval_shape(make, theta), tuple):
        raise ValueError("pass scene=... when make returns only Params")
    # make and scene go to the compiled function as they are (not wrapped in a new closure),
    # so that calling again with the same make reuses the compiled program.
    return _sensitivities(make, scene, theta, jnp.asarray(t_end, dtype=jnp.float64), max_segments, max_events, grazing_speed)


def _unpack(make, scene, th):
    out = make(th)
    return out if isinstance(out, tuple) else (scene, out)


@eqx.filter_jit
def _sensitivities(make, scene, theta, t_end, max_segments, max_events, grazing_speed):
    def unpack(th):
        return _unpack(make, scene, th)

    def solve(th):
        sc, prm = unpack(th)
        pl = closed_form_plan(sc, prm, t_end, max_segments)
        segs = segments_of(sc, prm, t_end, pl.decisions, pl.segments, pl.n_segments)
        g, law = sc.gravity, law_of(sc)
        c = law.coefficients(prm)
        events = list_events(segs, pl.decisions, law, c, g, max_events)
        flights = event_flights(segs, pl.decisions, law, c, g, max_events)
        return sc, prm, events, flights

    _, _, events, (_, _, _, _, crossing) = solve(theta)
    autodiff = jax.jacfwd(lambda th: solve(th)[2].t)(theta)
    t_fixed = jax.lax.stop_gradient(events.t)
    face = jnp.maximum(events.face, 0)

    def guard(th):
        # g(x(t*, theta), theta) with t* held fixed: the total derivative in (1)'s numerator.
        sc, prm, _, (t_s, p_s, v_s, acc, _) = solve(th)
        tau = jnp.where(crossing, t_fixed - t_s, 0.0)[:, None]
        x = p_s + v_s * tau + 0.5 * acc * tau**2
        normal, offset = faces_for(sc, prm.contact_radius).normal_offset(face)
        return jnp.sum(normal * x, axis=1) - offset

    numerator = jax.jacfwd(guard)(theta)
    sc, prm = unpack(theta)
    normal = faces_for(sc, prm.contact_radius).row[face][:, NORMAL]
    closing = jnp.sum(normal * events.velocity_pre, axis=1)
    grazing = crossing & (jnp.abs(closing) < grazing_speed)
    floored = jnp.where(jnp.abs(closing) < grazing_speed, -grazing_speed, closing)
    implicit = -numerator / floored[:, None]
    mask = crossing[:, None]
    return EventSensitivity(
        t=events.t,
        autodiff=jnp.where(mask, autodiff, 0.0),
        implicit=jnp.where(mask, implicit, 0.0),
        closing_speed=jnp.where(crossing, closing, 0.0),
        grazing=grazing,
        valid=crossing,
    )
