"""What a user would otherwise write: a plain diffrax event loop, for the benchmarks.

The textbook way to simulate a ball bouncing in air with diffrax: integrate the flight with
``Tsit5`` under a PID step-size controller (``dtmax`` caps the step so that the event
function, sampled once per step, cannot step over a short dip), stop at an
:class:`diffrax.Event` on the *guard* (height of the ball's bottom over the solid under its
centre) located by Newton's method, apply the contact law, and restart, ``max_contacts``
times in a ``lax.scan``; ``vmap`` over the balls. Nothing here is estim's solver: only the
scene (tread tops under the centre, the seed's geometry), the air's acceleration
(``estim.model._air``) and the contact law (``estim.forward.laws``), so that the two
compute the same physics and ``estim bench speed`` / ``estim bench accuracy`` compare
solvers, not models.

What it cannot do, and estim's ODE path does: contacts with the side of a solid (a riser,
an edge), a sliding or resting ball (a bounce series that accumulates ends the loop's
usefulness: each bounce is a restart, and ``max_contacts`` runs out), and a guarantee that
no contact is skipped (a dip shorter than ``dtmax`` can be).
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import optimistix as optx

from ..forward.laws import law_of
from ..model._air import acceleration

__all__ = ["event_loop"]


def _top(scene, x, y, radius):
    """Height of the support under a ball centred at (x, y): the highest box top whose
    footprint holds the centre, else the highest upward plane (the seed's tread-top
    semantics), plus the radius."""
    c, h = scene.box_centre, scene.box_half
    over = (jnp.abs(x - c[:, 0]) <= h[:, 0]) & (jnp.abs(y - c[:, 1]) <= h[:, 1])
    box_top = jnp.max(jnp.where(over, c[:, 2] + h[:, 2], -jnp.inf), initial=-jnp.inf)
    n, s = scene.plane_normal, scene.plane_offset
    plane_top = jnp.max(jnp.where(n[:, 2] > 0.5, s, -jnp.inf), initial=-jnp.inf)
    return jnp.maximum(box_top, plane_top) + radius


def event_loop(scene, params, t_end, *, max_contacts: int = 16, rtol: float = 1e-8, atol: float = 1e-9,
               dtmax: float = 0.004, max_steps: int = 4096):
    """Final position and velocity of each ball of ``params`` (a batch along axis 0) at
    ``t_end``, and the contact times (``inf`` past the last), by the plain diffrax loop."""
    law = law_of(scene)
    g = scene.gravity
    g_vec = jnp.array([0.0, 0.0, -1.0]) * g
    up = jnp.array([0.0, 0.0, 1.0])

    def one(prm):
        c = law.coefficients(prm)

        def field(t, y, args):
            v = y[3:]
            return jnp.concatenate([v, acceleration(scene.air, g, prm.radius, prm.mass, prm.drag_coefficient,
                                                    prm.spin, v, prm.lift_factor)])

        def guard(t, y, args, **kwargs):
            return y[2] - _top(scene, y[0], y[1], prm.radius)

        term = diffrax.ODETerm(field)
        solver = diffrax.Tsit5()
        controller = diffrax.PIDController(rtol=rtol, atol=atol, dtmax=dtmax)
        event = diffrax.Event(guard, root_finder=optx.Newton(rtol=1e-12, atol=1e-12), direction=False)

        def segment(carry, _):
            t, y, done = carry
            sol = diffrax.diffeqsolve(term, solver, t, t_end, 1e-3, y, stepsize_controller=controller,
                                      event=event, max_steps=max_steps, throw=False,
                                      adjoint=diffrax.RecursiveCheckpointAdjoint(checkpoints=max_steps))
            t1, y1 = sol.ts[-1], sol.ys[-1]
            hit = sol.event_mask & ~done
            v_post = law.contact_velocity(y1[3:], up, g_vec, c)
            y_next = jnp.where(hit, jnp.concatenate([y1[:3], v_post]), jnp.where(done, y, y1))
            t_next = jnp.where(done, t, t1)
            return (t_next, y_next, done | ~hit), jnp.where(hit, t1, jnp.inf)

        y0 = jnp.concatenate([prm.position, prm.velocity])
        (_, y, _), times = jax.lax.scan(segment, (jnp.asarray(0.0), y0, jnp.bool_(False)), None, length=max_contacts)
        return y[:3], y[3:], times

    return jax.vmap(one)(params)
