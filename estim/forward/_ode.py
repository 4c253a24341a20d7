"""The event-driven ODE solver, for scenes where the air acts (``estim.model._air``).

With drag or Magnus forces a flight has no closed form; it is integrated with a diffrax
Runge-Kutta solver (``Tsit5`` by default) under an error-controlled step size. Contacts are
found without ever stepping over one:

1. *Prediction.* At the start of a step, the ball's path is approximated by the parabola of
   its current acceleration a0, ``q(tau) = p + v tau + a0 tau^2 / 2``, and the exact
   closed-form contact search of the gravity-only solver (``estim.forward._contact.first_contact``,
   ``slide_exit_time``) gives the first face it enters, and when.
2. *A step bound.* Away from every solid a step is as long as the tolerance allows: over a
   step of length h the true path stays within ``D(h) = L A h^3 / 6`` of that parabola, a
   rigorous bound (``estim.model._air.step_bounds``: A bounds the acceleration and L the
   Lipschitz constant of the air's over every velocity the ball can reach in h), so if the
   parabola's bounding box over the step, grown by ``D(h) + SLACK``, meets no solid's box
   grown by r (``estim.forward._contact.sweep_clear``), the true path touches no solid in
   the step, whatever its length, and no contact is searched for. Only a step that this
   test cannot clear (the ball near a solid, or sliding on one) is bounded as follows: it
   is accepted only if the integrated end point lies within ``SLACK`` (1 micrometre) of
   the parabola. Since the distance between the true path and the parabola grows like
   tau^3 along a step, the path stays within ``SLACK`` of the parabola over the whole
   step, so the only contacts the prediction can miss are grazes that dip less than
   ``SLACK`` into a face. No contact deeper than that is skipped, whatever the
   tolerances, and no ball tunnels through a solid. (The integrated path differs from
   the true one by the local error that the tolerances control, about atol, far below
   the ``SLACK`` that both bounds add.) ``tests/test_air_contacts.py`` checks the bound
   against an independent integration and the first contacts of fast spinning throws
   against a loop of capped steps.
3. *Root finding.* When a contact (or a slide's exit over an edge) is predicted within the
   step, the step is shortened to the event: a Newton iteration solves
   ``G(tau) = n . q_RK(tau) - H = 0`` where ``q_RK(tau)`` is the solver's own step of length
   tau from the step start and (n, H) the face plane (or the edge bound). The scene's
   contact law (``estim.forward.laws``) then gives the velocity after the contact.

Zeno series carry over (for a contact law whose series have a closed form,
``estim.forward.laws.AbstractSeriesLaw``, where the law ``sums`` them, and in air only a
summable law's, ``_sums_series``; any other goes bounce by bounce): after a bounce on a
face that supports the ball, if the rest of the bounce series (gravity only) lasts less
than ``sqrt(2 SLACK / |a_air|)`` (so neglecting the air over it moves the ball by less
than ``SLACK``), lands on the same face and meets no other solid (the slab test
``train_reach`` along the landings' line for a summable law, ``slab_clear`` over the
triangle that holds them for the friction law, whose landings turn with the slip), it is
summed in closed form (the law's, spin included) and the ball rests or slides on the face
(with the air acting along it); it flies again when it slides off an edge. A series still bouncing at ``t_end`` (always so for e = 1) is summed
up to ``t_end`` under the same conditions. In a vacuum (the ODE path forced on a
gravity-only scene) every such series is summed, as in the closed-form solver, and its
bounces are listed as events as there (those whose flight lasts at least 1 us, then a
settle event). Events and compute stay bounded by ``max_steps``.

Rolls: a ball that meets an edge or a corner without normal speed (or with a hop lower than
the slack, whose dying bounces the law's ``settle`` stands for), pressed onto it, rolls over
it (mode ROLL): the vector field keeps the acceleration along the surface and adds the
centripetal one that holds the centre at distance r from the edge line or the vertex
(``_vector_field``; the step's end is put back on the surface, ``_onto_piece``), with no
contact search. The roll ends, found by bisection on the step (``_roll_end``), where the
surface's push falls to zero (STEP_DETACH: the ball flies on) or the ball leaves the piece's
region: past an edge's end onto the corner there, from a corner onto an edge, or back onto
the face above the edge (STEP_EXIT). Over a corner this is the spherical pendulum in full,
drag included.

Spin: the state is (position, velocity, spin). The spin is constant in flight (it enters the
Magnus force) and changes only at impacts, by the contact law (``impact``, ``settle_spin``
and, over a summed series, ``flight_start``): the friction law's bounce depends on it and
changes it. A ball that comes to
slide on a face slides as before (the air along the face, no friction): the friction law's
``settle_spin`` has left it rolling without slip.

Gradients: as in ``estim.forward._solver``, a ``plan`` pass (``lax.while_loop``, no gradients)
finds the discrete structure and the accepted step sizes, and records each step's node
(its end states) in values; a primal call uses those (``nodes_of``, a ``custom_jvp``), so
its program is the step loop alone. Only derivatives run a ``replay`` pass (``lax.scan``),
which recomputes every step differentiably with the same step sizes (discretise-then-
differentiate: exact derivatives of the computed solution). A step that ends at an event
is taken to plan's root tau*, then moved by one Newton step on the guard,
``delta = -G(tau*) / G'(tau*)``, along its own rate in tau: ``y(tau*) + y'(tau*) delta``, with
the slope ``G'`` and the rate ``y'`` (the Runge-Kutta step's derivative in its length) held
as values. delta's value is plan's residual (about 0) and its derivative the
implicit-function event-time sensitivity ``d tau = -(dG/dtheta) / (dG/dtau)``; the end
state's derivative is the chain rule's ``dy/dtheta + y' d tau``. (What the values leave
out is multiplied by ``G(tau*)``, zero at plan's root to its tolerance; the program then
carries no derivative of a derivative, and one step with derivatives per event, not two.)
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PyTree

from .._fold import first_least, least, some
from ..model._air import acceleration, step_bounds
from ._constants import (
    AXIS_TOL,
    FLIGHT,
    IMPACT,
    LISTED_FLIGHT,
    MAX_COUNT,
    ON_FACE_TOL,
    REST,
    REST_SPEED,
    ROLL,
    SLIDE,
    SPEED_TOL,
    STEP_CONTACT,
    STEP_DETACH,
    STEP_EXIT,
    STEP_LAST,
    STEP_PLAIN,
    STEP_UNUSED,
    STEP_ZENO,
)
from ._contact import (
    CENTRE,
    DIRECTION,
    HALF,
    NORMAL,
    Faces,
    across_speed2,
    clear_time,
    contact_normal,
    face_normal,
    faces_for,
    first_contact,
    inner,
    is_curved,
    next_piece,
    on_face,
    piece_at,
    slab_clear,
    slide_exit_time,
    sweep_clear,
    train_reach,
)
from ._scan import scan_used
from ._trajectory import AbstractSolution, Events, State, trajectory_parts
from .laws import AbstractContactLaw, law_of, series

# What a step is (Step.kind: STEP_PLAIN, STEP_LAST, STEP_CONTACT, STEP_EXIT, STEP_ZENO,
# STEP_UNUSED) and how the ball moves in it (Step.mode: FLIGHT or SLIDE, the closed-form
# planner's segment kinds) are numbered in estim.forward._constants, which says why a step's
# kind is not a segment's.
# The default largest distance (m) the integrated path may stray from a step's contact
# parabola (``simulate(..., contact_slack=...)``).
SLACK = 1e-6
# The default tolerances of the step-size control and step budget per ball: the fastest
# setting of ``estim bench accuracy`` within 1e-9 m of the reference on the drag scene
# (docs/pages/accuracy.md).
RTOL = 1e-9
ATOL = 1e-10
MAX_STEPS = 2048
# Steps per chunk of the replay (``estim.forward._scan``): a chunk past the last step used
# is skipped, one branch in the loop kernel, and the last chunk in use runs whole. With
# chunks of sqrt(MAX_STEPS) = 45 steps a table-tennis shot (19 steps) replayed 45 and its
# forward took 125 us; with chunks of 16, 118 us (one process, 2-core machine). Chunks of 8
# were as fast, but XLA unrolls a loop of 8 trips: the shot's fit program then took 1.2 s
# longer to compile.
REPLAY_CHUNK = 16
NEWTON_ITERATIONS = 6
# Bisections of a roll step for the end of the roll (a step is at most 1 s: 2^-60 s).
ROLL_BISECTIONS = 60

# Incremented each time a step loop (``plan``) is traced: tests use it to check that a scene
# without air never reaches the ODE solver.
TRACE_COUNT = 0


class Step(eqx.Module):
    """One accepted step, as ``plan`` found it (no gradients)."""

    kind: Int[Array, ""]
    mode: Int[Array, ""]
    support: Int[Array, ""]  # face slid on (SLIDE) or just slid off (FLIGHT), else -1
    wall: Int[Array, ""]  # a face the sliding ball also slides along (a wall it is pushed into), else -1
    face: Int[Array, ""]  # face hit (STEP_CONTACT), left (STEP_EXIT) or bounced on (STEP_ZENO), else -1
    bound: Int[Array, ""]  # STEP_EXIT: which edge bound, 2 * axis + (0 low, 1 high)
    h: Float[Array, ""]  # step length (a Newton start for STEP_CONTACT and STEP_EXIT)


class Node(eqx.Module):
    """One step in values: start and end state (end velocity before and after a reset) and
    the accelerations at both ends, for quintic Hermite dense output; the spin at the start
    (constant over the step) and after the end's reset."""

    t0: Float[Array, ""]
    p0: Float[Array, "3"]
    v0: Float[Array, "3"]
    a0: Float[Array, "3"]
    t1: Float[Array, ""]
    p1: Float[Array, "3"]
    v1: Float[Array, "3"]
    a1: Float[Array, "3"]
    v1_post: Float[Array, "3"]
    w0: Float[Array, "3"]
    w1_post: Float[Array, "3"]


class OdeSettings(eqx.Module):
    """Solver, tolerances and step budget of the ODE path. The tolerances are traced
    values: changing them does not recompile."""

    solver: diffrax.AbstractSolver = eqx.field(static=True)
    rtol: Float[Array, ""]
    atol: Float[Array, ""]
    slack: Float[Array, ""]  # see SLACK
    max_steps: int = eqx.field(static=True)


def _vector_field(air, gravity, params):
    """``f(y, args)`` for y = (position, velocity, spin); args = (support normal, sliding, wall
    normal or 0, roll): a sliding ball feels only the part of the acceleration along its
    face, and, against a wall (a face across its support that it touches), only the part
    that does not push it into the wall: it slides along both faces while pushed into the
    wall, and leaves the wall when the rest of the acceleration draws it away. (The field
    is continuous where the push changes sign.) A ball rolling over an edge or a corner
    (``roll = (rolling, anchor, mask)``, ``estim.forward._curved``'s piece) keeps on it: the
    acceleration along the surface, plus the centripetal ``-|u|^2 / rho n`` that holds the
    centre at its distance rho from the edge line or the vertex (u: the velocity across
    the curve; the surface pushes while ``_roll_push`` is positive)."""

    def f(y, args):
        n_sup, sliding, n_wall, (rolling, anchor, mask) = args
        v, w = y[3:6], y[6:]
        a = acceleration(air, gravity, params.radius, params.mass, params.drag_coefficient, w, v, params.lift_factor)
        a = jnp.where(sliding, a - inner(a, n_sup) * n_sup, a)
        push = inner(a, n_wall)  # (written out: a dot would be a library call, estim._fold.inner)
        a = jnp.where(push < 0, a - push * n_wall, a)
        n, rho, across2 = _on_piece(anchor, mask, y)
        a = jnp.where(rolling, a - inner(a, n) * n - across2 / rho * n, a)
        return jnp.concatenate([v, a, jnp.zeros_like(w)])  # the spin is constant in flight

    return f


def _on_piece(anchor, mask, y):
    """Unit normal n, distance rho from the edge line or vertex, and squared speed across
    the curve, of a ball at state y on an edge or a corner (harmless off one)."""
    d = mask * (y[:3] - anchor)
    dd = inner(d, d)
    rho_s = jnp.sqrt(jnp.where(dd > 0, dd, 1.0))  # (double where: no NaN derivative at d = 0)
    n = d / rho_s
    w = mask * y[3:6]
    return n, rho_s, inner(w, w) - inner(y[3:6], n) ** 2


def _roll_push(f, roll, y):
    """The surface's push per unit mass on a ball rolling over an edge or a corner (it
    leaves the surface where this falls to 0): ``-(a . n) - |u|^2 / rho``, a the free
    acceleration (gravity and the air)."""
    _, anchor, mask = roll
    n, rho, across2 = _on_piece(anchor, mask, y)
    a = f(y, _free_args(roll))[3:6]
    return -inner(a, n) - across2 / rho


def _free_args(roll=None):
    """Vector-field args of a ball in flight."""
    anchor = jnp.zeros(3) if roll is None else roll[1]
    return (jnp.zeros(3), jnp.bool_(False), jnp.zeros(3), (jnp.bool_(False), anchor, jnp.zeros(3)))


def _roll_args(faces: Faces, mode, support):
    """The ``roll`` part of the vector-field args: rolling on piece ``support`` in mode ROLL."""
    anchor, mask = piece_at(faces, jnp.maximum(support, 0))
    return (mode == ROLL, anchor, jnp.where(mode == ROLL, mask, 0.0))


def _onto_piece(roll, r, y):
    """A rolling ball's state put back on its surface (distance r from the edge line or
    the vertex, no normal velocity): the integrator keeps the constraint only to its
    tolerance."""
    rolling, anchor, mask = roll
    n, rho, _ = _on_piece(anchor, mask, y)
    p, v = y[:3], y[3:6]
    return jnp.where(rolling, jnp.concatenate([p + (r - rho) * n, v - inner(v, n) * n, y[6:]]), y)


def _contact(law: AbstractContactLaw, touches, v, w, n, g_vec, c):
    """Velocity and spin after a step's end at v, w: the law's contact state on a face of
    normal n where the step ends at a contact (``touches``), else as they are."""
    v_c, w_c = law.contact_state(v, w, n, g_vec, c)
    return jnp.where(touches, v_c, v), jnp.where(touches, w_c, w)


def _settled(law: AbstractContactLaw, hops, v, w, n, c):
    """Where ``hops``, a hop on an edge lower than the slack: the law's limit of the dying
    bounces it stands for (``settle_spin``)."""
    v_s, w_s = law.settle_spin(v - inner(v, n) * n, w, n, c)
    return jnp.where(hops, v_s, v), jnp.where(hops, w_s, w)


def _rk_step(settings, f, t, h, y, args):
    """One explicit Runge-Kutta step of length h with the solver's Butcher tableau (diffrax's
    coefficients). The stages run in a loop with one evaluation of the vector field: the
    step is called from several places of the event loop (the step, the Newton iteration
    of an event, the bisection of a roll's end), and an unrolled step puts every stage's
    vector field into the program at each of them. Returns the new state and the embedded
    error estimate."""
    tab = settings.solver.tableau
    n_stages = len(tab.b_sol)
    a = np.zeros((n_stages, n_stages))
    for i, row in enumerate(tab.a_lower):
        a[i + 1, : len(row)] = row
    a, b_sol, b_err = jnp.asarray(a), jnp.asarray(tab.b_sol), jnp.asarray(tab.b_error)

    def stage(i, ks):
        # (a weighted sum written out: a dot would be a library call, estim._fold.inner)
        incr = jnp.sum(a[i][:, None] * ks, axis=0)
        return ks.at[i].set(f(y + h * incr, args))

    ks = jax.lax.fori_loop(0, n_stages, stage, jnp.zeros((n_stages,) + y.shape, y.dtype))
    y1 = y + h * jnp.sum(b_sol[:, None] * ks, axis=0)
    err = h * jnp.sum(b_err[:, None] * ks, axis=0)
    return y1, err


def _edge_bounds(row):
    """The edge bounds of a box face as guards ``sigma_i (q_i - c_i) + beta_i >= 0``, two
    per axis (index ``2 * axis + side``), as in ``estim.forward._contact.slide_exit_time``: along
    an axis where the face direction m is 0, ``-h <= q_i - c_i <= h``; where m_i != 0,
    ``m_i (q_i - c_i) >= h_i`` (the second slot unused, beta = inf)."""
    m, h = row[DIRECTION], row[HALF]
    finite = jnp.isfinite(h)
    sigma = jnp.stack([jnp.where(m < 0, -1.0, 1.0), -jnp.ones(3)], axis=1)
    beta = jnp.stack([jnp.where(m == 0, h, -h), jnp.where(m == 0, h, jnp.inf)], axis=1)
    beta = jnp.where(finite[:, None], beta, jnp.inf)
    return sigma.reshape(-1), beta.reshape(-1)


def _guard(faces: Faces, kind, face, bound):
    """The event guard, which decreases through 0 at the event: the face's distance
    ``n . q - H`` (flat) or ``|M (q - anchor)| - r`` (an edge or a corner,
    ``estim.forward._curved``) for a STEP_CONTACT, edge bound ``bound`` of the face for a
    STEP_EXIT. Returns ``(n, H, anchor, mask, curved)`` for ``_guard_at``."""
    f = jnp.maximum(face, 0)
    row = faces.row[f]
    sigma, beta = _edge_bounds(row)
    axis = bound // 2
    e_i = jnp.zeros(3).at[axis].set(1.0)
    sg, bt = sigma[bound], beta[bound]
    n_exit = sg * e_i
    h_exit = sg * row[CENTRE][axis] - jnp.where(jnp.isfinite(bt), bt, 0.0)
    is_exit = kind == STEP_EXIT
    n_face, h_face = faces.normal_offset(f)
    anchor, mask = piece_at(faces, f)
    curved = ~is_exit & is_curved(faces, f)
    return (jnp.where(is_exit, n_exit, n_face), jnp.where(is_exit, h_exit, h_face), anchor, mask, curved,
            faces.radius)


def _guard_at(guard, q, v):
    """The guard's value and rate at centre q moving at v."""
    n, big_h, anchor, mask, curved, r = guard
    d = mask * (q - anchor)
    rho = jnp.sqrt(inner(d, d))
    rho_s = jnp.where(rho > 0, rho, 1.0)
    return (jnp.where(curved, rho - r, inner(n, q) - big_h),
            jnp.where(curved, inner(d, v) / rho_s, inner(n, v)))


def _roll_guards(f, faces: Faces, roll, piece, y):
    """The guards of a roll over piece ``piece`` at state y: the surface's push
    (``_roll_push``: the ball leaves the surface where it falls below 0, STEP_DETACH) and
    the bounds of the piece's region (``_edge_bounds``, passed by ``ON_FACE_TOL``: a ball
    that starts to roll right on a bound does not leave at once; STEP_EXIT)."""
    row = faces.row[piece]
    sigma, beta = _edge_bounds(row)
    rel = jnp.repeat(y[:3] - row[CENTRE], 2)
    return _roll_push(f, roll, y), sigma * rel + beta + ON_FACE_TOL


def _roll_end(settings, f, faces: Faces, t, y, args, support, h, y1):
    """Where a roll step of length h from (t, y) to y1 ends: ``(event, kind, face, bound,
    h, y1)``, the step cut at the first guard of ``_roll_guards`` that it crosses (found by
    bisection on the step, values only), else as it is. y1 is put back on the surface."""
    roll = args[3]
    piece = jnp.maximum(support, 0)

    def at(tau):
        y_tau, _ = _rk_step(settings, f, t, tau, y, args)
        return _onto_piece(roll, faces.radius, y_tau)

    def guards(y_tau):
        """The push and the nearest region bound, as two values."""
        push, bounds = _roll_guards(f, faces, roll, piece, y_tau)
        return jnp.stack([push, least(bounds)])

    def cut(crossed):
        # Each guard by a bisection of its own, and the earlier wins: deciding which one a
        # single bisection stopped on, from signs at its end, is a guess where both are at
        # rounding's distance from 0. The two bisections run side by side, guard k at
        # midpoint k. A guard crossed by the step's end is found at the first time it is
        # negative; 0 if already at the start (past an edge's end the corner asks for the
        # centripetal push of the speed along the edge too, and a ball whose push that
        # makes negative leaves at once); one not crossed, never (inf).
        def halve(_, lo_hi):
            lo, hi = lo_hi
            mid = 0.5 * (lo + hi)
            out = jnp.diagonal(jax.vmap(lambda tau: guards(at(tau)))(mid)) < 0
            return jnp.where(out, lo, mid), jnp.where(out, mid, hi)

        span = jnp.broadcast_to(h, (2,))
        tau_k = jnp.where(guards(y) < 0, 0.0, jax.lax.fori_loop(0, ROLL_BISECTIONS, halve, (0.0 * span, span))[1])
        tau_push, tau_bound = jnp.where(crossed, tau_k, jnp.inf)
        tau = jnp.minimum(tau_push, tau_bound)
        y_e = at(tau)
        kind = jnp.where(tau_push <= tau_bound, STEP_DETACH, STEP_EXIT).astype(jnp.int32)
        which = first_least(_roll_guards(f, faces, roll, piece, y_e)[1])
        return jnp.bool_(True), kind, piece.astype(jnp.int32), which, tau, y_e

    y1 = _onto_piece(roll, faces.radius, y1)
    crossed = guards(y1) < 0
    return jax.lax.cond(some(crossed), cut,
                        lambda _: (jnp.bool_(False), jnp.int32(STEP_CONTACT), jnp.int32(-1), jnp.int32(0), h, y1),
                        crossed)


def _exit_bound(faces: Faces, face, q):
    """Which edge bound a ball sliding on ``face`` crosses when it leaves at ``q``."""
    row = faces.row[jnp.maximum(face, 0)]
    sigma, beta = _edge_bounds(row)
    rel = jnp.repeat(q - row[CENTRE], 2)
    return first_least(sigma * rel + beta)


def _event_time(settings, f, t, y, args, guard, tau0):
    """Newton iteration for ``G(q_RK(tau)) = 0`` from ``tau0`` (no gradients)."""

    def g(tau):
        y1, _ = _rk_step(settings, f, t, tau, y, args)
        return _guard_at(guard, y1[:3], y1[3:6])

    def body(i, carry):
        # One more trip than iterations, which only evaluates: the guard at the last
        # iterate without a second copy of the step in the program.
        tau, _ = carry
        val, slope = g(tau)
        safe = (jnp.abs(slope) > SPEED_TOL) & (i < NEWTON_ITERATIONS)
        return jnp.maximum(tau - jnp.where(safe, val / jnp.where(safe, slope, 1.0), 0.0), 0.0), val

    tau, val = jax.lax.fori_loop(0, NEWTON_ITERATIONS + 1, body, (tau0, 0.0 * tau0))
    return tau, jnp.abs(val)


def _sums_series(law: AbstractContactLaw, air) -> bool:
    """Whether the ODE path sums the law's bounce series (static): every law with
    closed-form series (``closes_series``) in a vacuum, in air only a summable one
    (``summable``, the factor law). In air a series is summed only over the part that lasts
    less than ``_zeno_time`` (a few milliseconds for a ping-pong ball), where neglecting the
    air is within the slack; the rest goes bounce by bounce anyway. The friction law's
    closed form there, in every program that fits a shot in air, made the table-tennis
    shot's fit program 47% larger (47,917 -> 70,354 HLO lines after XLA's optimisation)
    for the steps saved at the end of a series that dies out within a track."""
    return law.closes_series and (air is None or law.summable)


def _zeno(faces: Faces, gravity, air, law: AbstractContactLaw, params, face, p, v, w, slack, t_left, cut=None):
    """Whether the bounce series that starts at (p, v, spin w) on ``face`` is summed in
    closed form (see the module docstring), whether it is cut at ``t_end`` (``t_left``
    after p), and its duration, displacement, final velocity and spin. ``cut`` given
    (replay): as plan decided.

    A series that does not accumulate before ``t_end`` (e = 1 never does) is summed up to
    ``t_end``: bounce j starts at ``T0 (1 - e^j) / (1 - e)`` (``estim.forward.laws.FactorLaw``),
    so the state at ``t_left`` is that of the flight in progress then, in closed form, as on
    the closed-form path. Stepping it bounce by bounce instead costs a step per bounce (an
    e = 1 ball with a 0.2 us period would need 10^7) and lets rounding accumulate in the
    bounce points (1.8e-12 m after 1,000 bounces of an e = 1 ball). A law without closed-form
    series (``closes_series``) never sums one, nor a law's series that it does not
    (``sums``)."""
    if not _sums_series(law, air):
        no = jnp.bool_(False)
        return no, no if cut is None else cut, jnp.float64(0.0), jnp.zeros(3), v, w
    c = law.coefficients(params)
    g_vec = jnp.array([0.0, 0.0, -1.0]) * gravity
    f = jnp.maximum(face, 0)
    n = face_normal(faces, f)
    w_n = jnp.dot(v, n)
    supports = (jnp.dot(n, g_vec) < 0) & (face >= 0) & (w_n > 0)
    n_s = jnp.where(supports, n, jnp.array([0.0, 0.0, 1.0]))
    s = series(jnp.where(supports, v, n_s), n_s, g_vec, w)
    if cut is None:  # e = 1: duration inf, always cut
        full = jax.lax.stop_gradient(law.series_end(s, jnp.inf, c)[0])
        cut = ~(full < jax.lax.stop_gradient(t_left))
    # One closed form: the flight in progress at t_end (a cut series) or the Zeno limit.
    # (Only where it is not cut is j inf: at e = 1 the whole series lasts T0 * inf, whose
    # derivative (inf) turns the zero cotangent of a discarded branch into NaN in reverse
    # mode.)
    t_safe = jnp.where(cut, t_left, 0.0)
    j = jnp.where(cut, jnp.minimum(law.bounces_within(t_safe / s.period, c), MAX_COUNT), jnp.inf)
    duration, travel, v_end, w_end = law.flight_state(s, j, t_safe, c)
    duration = jnp.where(cut, t_left, jnp.where(jnp.isfinite(duration), duration, 0.0))
    ok = supports & law.sums(s, c) & _zeno_allowed(
        law, *jax.lax.stop_gradient((faces, gravity, air, params, c, f, n, p, v, w_n, s, duration, travel, v_end,
                                     slack))
    )
    return (ok, cut, jnp.where(ok, duration, 0.0), jnp.where(ok, travel, 0.0),
            jnp.where(ok, v_end, v), jnp.where(ok, w_end, w))


def _zeno_allowed(law, faces, gravity, air, params, c, f, n, p, v, w, s, duration, travel, v_end, slack):
    """The decision of ``_zeno`` (no gradients): the series lands on its face, meets no
    other solid, and is short enough to neglect the air over it."""
    row = faces.row[f]
    along = travel - jnp.dot(travel, s.normal) * s.normal
    apex = w * w / (2.0 * gravity)
    if law.summable:
        # Where the series lands: its first bounce, the end of its first flight (a
        # parabola, whatever the law), and the ball's place over the face at the end (the
        # accumulation point, or where a series cut at t_end is in flight). A face that
        # supports the ball points up (every flat face is axis-aligned), so a_t = 0 and
        # the tangential displacement moves monotonically along u: every landing lies
        # between these two points, on the face if both are (a face is convex).
        x_one = s.period * s.u + 0.5 * s.a_t * s.period**2
        lands = (on_face(p + along, row[CENTRE], row[HALF], faces.radius)
                 & on_face(p + x_one, row[CENTRE], row[HALF], faces.radius))
        # Nothing in the way: the slab test of the closed form (a flat face that supports
        # the ball points up: every flat face is axis-aligned, and edges and corners have
        # no series).
        u = v.at[2].set(0.0)
        reach = train_reach(faces, f, p, u, apex)
        clear = jnp.sqrt(along[0] ** 2 + along[1] ** 2) <= reach
    else:
        # Up to the end every flight's tangential velocity lies on the segment from the
        # first flight's, u, to the last one's, u_end (``AbstractSeriesLaw``), so after the
        # series' duration T the ball is over the triangle (p, p + T u, p + T u_end): it
        # lands on the face if the triangle does (the face is convex), and meets nothing if
        # the box of the triangle, in the slab of the first apex, meets no other solid.
        u_end = v_end - jnp.dot(v_end, s.normal) * s.normal
        corners = jnp.stack([p, p + duration * s.u, p + duration * u_end])
        lands = jnp.all(on_face(corners, row[CENTRE], row[HALF], faces.radius))
        clear = slab_clear(faces, f, jnp.min(corners, axis=0), jnp.max(corners, axis=0), apex)
    g_vec = jnp.array([0.0, 0.0, -1.0]) * gravity
    a_air = acceleration(air, gravity, params.radius, params.mass, params.drag_coefficient, s.spin, v,
                         params.lift_factor) - g_vec
    return (duration <= _zeno_time(a_air, slack)) & lands & clear


def _zeno_time(a_air, slack):
    """The longest bounce series whose air acceleration ``a_air`` moves the ball by at most
    ``slack``: ``sqrt(2 slack / |a_air|)`` (inf without air)."""
    air_scale = jnp.sqrt(inner(a_air, a_air))
    return jnp.where(air_scale > 0, jnp.sqrt(2.0 * slack / jnp.where(air_scale > 0, air_scale, 1.0)), jnp.inf)


def _zeno_possible(faces: Faces, g_vec, pending, v, a0, slack, t_left):
    """A cheap necessary condition of ``_zeno_allowed`` after a bounce on ``pending``: the
    series lasts at least its first flight ``2 w / |g_n|`` (or until ``t_end``), which must
    not exceed ``_zeno_time``."""
    n = face_normal(faces, jnp.maximum(pending, 0))
    a_n = -jnp.dot(n, g_vec)
    first = jnp.where(a_n > 0, 2.0 * jnp.dot(v, n) / jnp.where(a_n > 0, a_n, 1.0), jnp.inf)
    return (pending >= 0) & (jnp.minimum(first, t_left) <= _zeno_time(a0 - g_vec, slack))


class Plan(eqx.Module):
    """The accepted steps (leading axis ``max_steps``; slots from ``n_steps`` on are
    unused), their nodes in values and the state after the last step. An unused slot's
    node is a step of length 0 at the release (``replay``'s are at the end state: no one
    reads them, and setting them after the loop, a select of the whole buffer, made the
    table-tennis shot's samples 100 us slower)."""

    steps: Step
    nodes: Node
    end: State
    n_steps: Int[Array, ""]
    complete: Bool[Array, ""]


def _idle(f, t, y) -> Node:
    """The node of an unused slot at time t and state y: a step of length 0."""
    a = f(y, _free_args())[3:6]
    return Node(t, y[:3], y[3:6], a, t, y[:3], y[3:6], a, y[3:6], y[6:], y[6:])


def plan(scene, params, t_end, settings: OdeSettings) -> Plan:
    """Find the accepted steps and the events, and record each step's node (values only:
    ``nodes_of`` gives them derivatives)."""
    global TRACE_COUNT
    TRACE_COUNT += 1
    scene, params, t_end = jax.lax.stop_gradient((scene, params, t_end))
    faces, g, air = faces_for(scene, params.contact_radius), scene.gravity, scene.air
    law = law_of(scene)
    coef = law.coefficients(params)  # (the loop's carry is c)
    f = _vector_field(air, g, params)
    order = settings.solver.order(None)
    g_vec = jnp.array([0.0, 0.0, -1.0]) * g
    S = settings.max_steps
    none = jnp.int32(-1)
    # (Strongly typed zeros: a plan is also a program's result, estim.forward._simulate, and
    # the next program is compiled from its shapes and types alone.)
    zero = jnp.zeros(())
    empty = Step(jnp.int32(STEP_UNUSED), jnp.int32(FLIGHT), none, none, none, jnp.int32(0), zero)
    y0 = jnp.concatenate([params.position, params.velocity, params.spin])
    slots = jax.tree.map(lambda x: jnp.broadcast_to(x, (S,) + x.shape), (empty, _idle(f, zero, y0)))
    h0 = jnp.minimum(t_end, 1e-3)
    # carry: iteration, records, t, y, mode, support, wall, pending Zeno face, h, done, (steps, nodes)
    init = (jnp.int32(0), jnp.int32(0), zero, y0, jnp.int32(FLIGHT), none, none, none, h0,
            jnp.bool_(False), slots)

    def cond(c):
        i, k, *_, done, _ = c
        return (~done) & (i < S) & (k < S)

    def body(c):
        i, k, t, y, mode, support, wall, pending, h, _, slots = c
        p, v, w = y[:3], y[3:6], y[6:]
        sliding = mode == SLIDE
        n_sup = jnp.where(sliding, face_normal(faces, jnp.maximum(support, 0)), 0.0)
        # A wall the ball has moved away from (or that an event step left within the slack
        # of it) is a wall no more: its contacts are searched for again.
        n_w, h_w = faces.normal_offset(jnp.maximum(wall, 0))
        wall = jnp.where(sliding & (wall >= 0) & (inner(n_w, v) <= SPEED_TOL)
                         & (inner(n_w, p) - h_w <= settings.slack), wall, -1)
        # A support the ball moves away from is a support no more (the friction of a wall
        # it slid down onto can throw it off a vertical support): it slides on its wall
        # where it has one, else flies. Kept, such a support would hold a ball metres from
        # its face, and the wall's edge would be left and met again at one instant.
        leaves = sliding & (inner(n_sup, v) > REST_SPEED)
        support = jnp.where(leaves, wall, support)
        mode = jnp.where(leaves & (wall < 0), FLIGHT, mode)
        wall = jnp.where(leaves, -1, wall)
        sliding = mode == SLIDE
        n_sup = jnp.where(sliding, face_normal(faces, jnp.maximum(support, 0)), 0.0)
        on_wall = wall >= 0
        n_wall = jnp.where(on_wall, n_w, 0.0)
        rolling = mode == ROLL
        roll = _roll_args(faces, mode, support)
        args = (n_sup, sliding, n_wall, roll)
        a0 = f(y, args)[3:6]

        # A Zeno series closed in one piece (tried only after a bounce: a branch, since each
        # ball runs its own loop, estim.forward._simulate).
        zeno_ok, z_cut, z_dur, z_travel, z_vel, z_spin = jax.lax.cond(
            _zeno_possible(faces, g_vec, pending, v, a0, settings.slack, t_end - t),
            lambda: _zeno(faces, g, air, law, params, pending, p, v, w, settings.slack, t_end - t),
            lambda: (jnp.bool_(False), jnp.bool_(False), jnp.float64(0.0), jnp.zeros(3), v, w),
        )

        # The next event on the step's parabola.
        h_try = jnp.minimum(h, t_end - t)
        # Away from every solid the step is the tolerance's alone: the path stays within
        # the rigorous bound (4) of estim.model._air of its parabola, and a parabola whose
        # box, grown by that bound, meets no solid cannot touch one (``sweep_clear``); then
        # no contact is searched for. A sliding ball keeps the slack bound (its face's
        # edges are its events).
        a_max, lip = step_bounds(air, g, params.radius, params.mass, params.drag_coefficient, w, v, h_try,
                                 params.lift_factor)
        margin = lip * a_max * h_try**3 / 6.0 + settings.slack
        clear = ~sliding & ~rolling & sweep_clear(faces, p, v, a0, h_try, margin)
        # A step that cannot be cleared whole may be in part: its longest clear part (the
        # margin of the whole step still bounds it) is taken where that is at least a
        # tenth of the step, so that a ball nears a solid in long steps, and only the
        # last one, which reaches it, is bounded by the slack.
        h_part = jax.lax.cond(clear | sliding | rolling, lambda: h_try,
                              lambda: clear_time(faces, p, v, a0, h_try, margin))
        part = ~clear & ~sliding & ~rolling & (h_part >= 0.1 * h_try)
        h_try = jnp.where(part, h_part, h_try)
        clear = clear | part

        def predict():
            """The next event on the step's parabola, and its time on the RK path."""
            tau_c, face_c = first_contact(faces, p, v, a0, support, wall, sliding, leaving=True)
            tau_s = jnp.where(sliding, slide_exit_time(faces, jnp.maximum(support, 0), p, v, a0), jnp.inf)
            # Past the end of its wall the ball slides on without it.
            tau_w = jnp.where(on_wall, slide_exit_time(faces, jnp.maximum(wall, 0), p, v, a0), jnp.inf)
            exit_face = jnp.where(tau_w < tau_s, wall, support)
            tau_x = jnp.minimum(tau_s, tau_w)
            contact = (tau_c <= h_try) & (tau_c <= tau_x)
            leaves = (tau_x <= h_try) & ~contact
            tau_e = jnp.where(contact, tau_c, tau_x)
            q_e = p + v * jnp.where(leaves, tau_x, 0.0) + 0.5 * a0 * jnp.where(leaves, tau_x, 0.0) ** 2
            bound = _exit_bound(faces, exit_face, q_e)
            ev_kind = jnp.where(contact, STEP_CONTACT, STEP_EXIT)
            ev_face = jnp.where(contact, face_c, exit_face)
            guard = _guard(faces, ev_kind, ev_face, bound)
            event = contact | leaves
            tau_ev, miss = jax.lax.cond(
                event,
                lambda: _event_time(settings, f, t, y, args, guard, tau_e),
                lambda: (jnp.float64(0.0), jnp.float64(jnp.inf)),
            )
            # Newton finds no root within the step: the true path does not reach the face
            # (a graze within SLACK); step on.
            event = event & (miss <= settings.slack) & (tau_ev <= h_try)
            return event, ev_kind.astype(jnp.int32), ev_face.astype(jnp.int32), bound, tau_ev

        event, ev_kind, ev_face, bound, tau_ev = jax.lax.cond(
            clear | rolling,
            lambda: (jnp.bool_(False), jnp.int32(STEP_CONTACT), jnp.int32(-1), jnp.int32(0), jnp.float64(0.0)),
            predict,
        )
        h_step = jnp.where(event, tau_ev, h_try)

        y1, y_err = _rk_step(settings, f, t, h_step, y, args)
        # (The error of position and velocity: the spin's is 0, constant in flight.)
        scale = settings.atol + settings.rtol * jnp.maximum(jnp.abs(y[:6]), jnp.abs(y1[:6]))
        err = jnp.sqrt(jnp.mean((y_err[:6] / scale) ** 2))
        # A roll's end (it leaves the surface, or the piece's region) within the step.
        # (Only a scene with edges and corners has rolls: faces.curved, static.)
        if faces.curved:
            event, ev_kind, ev_face, bound, h_step, y1 = jax.lax.cond(
                rolling,
                lambda: _roll_end(settings, f, faces, t, y, args, support, h_step, y1),
                lambda: (event, ev_kind, ev_face, bound, h_step, y1),
            )
        stray = y1[:3] - (p + v * h_step + 0.5 * a0 * h_step**2)
        dev = jnp.sqrt(inner(stray, stray))
        keep = ((err <= 1.0) & ((dev <= settings.slack) | clear | rolling)) | (h_step <= 0.0) | zeno_ok
        by_error = 0.9 * jnp.where(err > 0, err, 1e-10) ** (-1.0 / order)
        by_slack = 0.9 * (settings.slack / jnp.where(dev > 0, dev, 1e-300)) ** (1.0 / 3.0)
        factor = jnp.clip(jnp.where(clear | rolling, by_error, jnp.minimum(by_error, by_slack)), 0.2, 5.0)

        last = ~event & (h_step >= t_end - t)
        kind = jnp.where(zeno_ok, STEP_ZENO, jnp.where(event, ev_kind, jnp.where(last, STEP_LAST, STEP_PLAIN)))
        # The state after an accepted step.
        p1, v1, w1 = y1[:3], y1[3:6], y1[6:]
        n_face = contact_normal(faces, jnp.maximum(ev_face, 0), p1)
        v_post, w_post = _contact(law, kind == STEP_CONTACT, v1, w1, n_face, g_vec, coef)
        # It slides on the face if it has no normal speed left and is pushed into the face:
        # by gravity in a vacuum, by gravity and the air here (so a ball that the wind
        # holds against a wall slides along it, instead of touching it again at every step).
        # (The acceleration at the end of the step, before the contact: the solver's last
        # stage. After it the normal speed is at most REST_SPEED, so the air's part barely
        # changes.)
        a_end = f(y1, args)[3:6]
        curved = (kind == STEP_CONTACT) & is_curved(faces, jnp.maximum(ev_face, 0))
        # (On an edge or a corner a hop lower than the contact slack is a touch: the step's
        # prediction cannot resolve it, and a missed landing let a ball fall through a tread.)
        w_n = inner(v_post, n_face)
        touches = (jnp.abs(w_n) <= REST_SPEED) | (curved & (w_n * w_n <= -2.0 * inner(n_face, a_end) * settings.slack))
        settled = touches & (inner(n_face, a_end) < 0) & ~curved
        # On an edge or a corner: a ball without normal speed that the push into the
        # surface holds on it rolls over it (mode ROLL, the vector field keeping it on the
        # surface); one that leaves flies on, not meeting that piece again in this flight.
        # A hop lower than the slack, pressed onto the surface, stands for the bounces that
        # would follow, a series that dies out: the ball leaves it as the law's limit of
        # one (``settle``).
        def pressed(u):
            return inner(n_face, a_end) + across_speed2(faces, jnp.maximum(ev_face, 0), u, n_face) / faces.radius < 0

        hops = curved & touches & (jnp.abs(w_n) > REST_SPEED) & pressed(v_post)
        v_post, w_post = _settled(law, hops, v_post, w_post, n_face, coef)
        rolls = curved & touches & pressed(v_post)
        grazed = curved & touches
        rec = Step(
            kind.astype(jnp.int32), mode, support, wall.astype(jnp.int32),
            jnp.where(zeno_ok, pending, jnp.where(event, ev_face, -1)).astype(jnp.int32),
            # A STEP_ZENO step records in ``bound`` whether the series was cut at t_end (1), a
            # STEP_CONTACT whether it is such a hop (1).
            jnp.where(zeno_ok, z_cut.astype(jnp.int32), jnp.where(kind == STEP_CONTACT, hops.astype(jnp.int32), bound)),
            jnp.where(zeno_ok, 0.0, h_step),
        )
        t_new = jnp.where(zeno_ok, t + z_dur, t + h_step)
        y_new = jnp.where(zeno_ok, jnp.concatenate([p + z_travel, z_vel, z_spin]), jnp.concatenate([p1, v_post, w_post]))
        # The step's node, as ``replay`` computes it (a summed series: its ends, at gravity's
        # acceleration).
        node = Node(t, p, v, jnp.where(zeno_ok, g_vec, a0), t_new, y_new[:3], jnp.where(zeno_ok, z_vel, v1),
                    jnp.where(zeno_ok, g_vec, a_end), y_new[3:6], w, y_new[6:])
        # (One slot written, in place: a select of the whole buffer would cost O(max_steps) per step.)
        slots = jax.tree.map(lambda b, x: b.at[k].set(jnp.where(keep, x, b[k])), slots, (rec, node))
        meets_wall = sliding & (jnp.abs(jnp.dot(n_face, n_sup)) < AXIS_TOL) & ~curved
        mode_c = jnp.where(rolls, ROLL, jnp.where(meets_wall | settled, SLIDE, FLIGHT))
        support_c = jnp.where(meets_wall, support, jnp.where(settled | grazed, ev_face, -1))
        # Leaving the wall's face (past its end) keeps the slide on the support.
        off_wall = (kind == STEP_EXIT) & (ev_face == wall) & on_wall
        # A roll that leaves its piece's region goes on over the next piece (past an edge's
        # end, the corner there), or flies from a face's edge (back on top of the edge: the
        # face's contact follows at once).
        onto, onto_ok = next_piece(faces, jnp.maximum(support, 0), bound // 2, v1)
        onto_ok = rolling & (kind == STEP_EXIT) & onto_ok & (faces.rank[onto] >= 2)
        new_mode = jnp.select([zeno_ok, kind == STEP_CONTACT, off_wall, onto_ok, (kind == STEP_EXIT) | (kind == STEP_DETACH)],
                              [SLIDE, mode_c, SLIDE, ROLL, FLIGHT], mode)
        new_support = jnp.select([zeno_ok, kind == STEP_CONTACT, onto_ok, kind == STEP_EXIT], [pending, support_c, onto, support],
                                 support)
        new_wall = jnp.where((kind == STEP_CONTACT) & meets_wall, ev_face,
                             jnp.where(zeno_ok | (kind == STEP_EXIT) | (kind == STEP_CONTACT), -1, wall))
        new_pending = jnp.where((kind == STEP_CONTACT) & (mode_c == FLIGHT) & ~curved, ev_face, -1)
        # After an event step the proposal stands (the event cut the step short).
        h_new = jnp.where(event | zeno_ok, h, jnp.maximum(h_step, 1e-12) * factor)
        h_rej = jnp.maximum(h_step, 1e-12) * factor

        return (
            i + 1,
            jnp.where(keep, k + 1, k),
            jnp.where(keep, t_new, t),
            jnp.where(keep, y_new, y),
            jnp.where(keep, new_mode, mode).astype(jnp.int32),
            jnp.where(keep, new_support, support).astype(jnp.int32),
            jnp.where(keep, new_wall, wall).astype(jnp.int32),
            jnp.where(keep, new_pending, pending).astype(jnp.int32),
            jnp.where(keep, h_new, h_rej),
            keep & ((kind == STEP_LAST) | (zeno_ok & z_cut)),
            slots,
        )

    _, k, t, y, *_, done, (steps, nodes) = jax.lax.while_loop(cond, body, init)

    return Plan(steps=steps, nodes=nodes, end=State(t, y[:3], y[3:6]), n_steps=k, complete=done)


def replay(scene, params, t_end, steps: Step, settings: OdeSettings, n_used=None) -> tuple[State, Node]:
    """Recompute every accepted step differentiably (a ``lax.scan`` that runs only the
    first ``n_used`` steps, default all: ``estim.forward._scan``). Returns the state after
    the last step and the steps' nodes (a caller that uses only the state leaves the nodes
    to JAX's dead-code elimination: the scan then stores nothing per step)."""
    faces, g, air = faces_for(scene, params.contact_radius), scene.gravity, scene.air
    law = law_of(scene)
    c = law.coefficients(params)
    f = _vector_field(air, g, params)
    g_vec = jnp.array([0.0, 0.0, -1.0]) * g

    def apply(carry, st: Step):
        t, y = carry
        p, v, w = y[:3], y[3:6], y[6:]
        sliding = st.mode == SLIDE
        n_sup = jnp.where(sliding, face_normal(faces, jnp.maximum(st.support, 0)), 0.0)
        rolling = st.mode == ROLL
        roll = _roll_args(faces, st.mode, st.support)
        args = (n_sup, sliding, jnp.where(st.wall >= 0, face_normal(faces, jnp.maximum(st.wall, 0)), 0.0), roll)
        is_event = (st.kind == STEP_CONTACT) | (st.kind == STEP_EXIT) | (st.kind == STEP_DETACH)
        guard_of = _guard(faces, st.kind, st.face, st.bound)
        # The step, to plan's event time tau* at an event. There one Newton step on the
        # guard, tau* - G / G', moves the step's end along the step's own rate in tau: its
        # value is plan's root, its derivative the implicit-function event-time
        # sensitivity d tau = -dG / G', the slope G' and the rate values (module docstring).
        tau_star = jax.lax.stop_gradient(st.h)
        h = jnp.select([st.kind == STEP_PLAIN, st.kind == STEP_LAST, is_event], [st.h, t_end - t, tau_star], 0.0)
        y_h, _ = _rk_step(settings, f, t, h, y, args)

        def guard(y1, f, faces, guard_of, roll):
            """The event's guard at the step's end state y1."""
            flat = _guard_at(guard_of, y1[:3], y1[3:6])[0]
            if not faces.curved:  # (no rolls: static)
                return flat
            push, bounds = _roll_guards(f, faces, roll, jnp.maximum(st.face, 0), _onto_piece(roll, faces.radius, y1))
            return jnp.where(rolling, jnp.where(st.kind == STEP_DETACH, push, bounds[st.bound]), flat)

        def newton_step():
            f_fixed = _vector_field(*jax.lax.stop_gradient((air, g, params)))
            y_fixed, args_fixed, faces_fixed, guard_fixed = jax.lax.stop_gradient((y, args, faces, guard_of))

            def end(tau):
                y1, _ = _rk_step(settings, f_fixed, t, tau, y_fixed, args_fixed)
                return guard(y1, f_fixed, faces_fixed, guard_fixed, args_fixed[3]), y1

            _, (slope, rate) = jax.jvp(end, (tau_star,), (jnp.ones_like(tau_star),))
            # No Newton step where the guard is flat (|G'| <= SPEED_TOL, as in plan's
            # ``_event_time``): an event entered at second order (zero normal speed, tau =
            # 0) has G' ~ 1e-15 from rounding, and dividing by it threw the ball ~1e15 m
            # away (then to NaN) where plan had not moved it.
            # Nor where a roll ends at its start (its guard negative there, not at a root).
            newton = (jnp.abs(slope) > SPEED_TOL) & (~rolling | (tau_star > 0))
            value = guard(y_h, f, faces, guard_of, roll)
            return -jnp.where(newton, value / jnp.where(newton, slope, 1.0), 0.0), rate

        # (A branch: each ball replays its own steps, estim.forward._simulate.)
        delta, rate = jax.lax.cond(is_event, newton_step, lambda: (0.0 * t, jnp.zeros_like(y)))
        h = h + delta
        y1 = y_h + rate * delta
        y1 = _onto_piece(roll, faces.radius, y1)
        p1, v1, w1 = y1[:3], y1[3:6], y1[6:]
        n_face = contact_normal(faces, jnp.maximum(st.face, 0), p1)
        v_post, w_post = _contact(law, st.kind == STEP_CONTACT, v1, w1, n_face, g_vec, c)
        hop = (st.kind == STEP_CONTACT) & (st.bound == 1)  # (a hop on an edge below the slack, as plan found)
        v_post, w_post = _settled(law, hop, v_post, w_post, n_face, c)
        a0 = f(y, args)[3:6]
        a1 = f(y1, args)[3:6]
        # A Zeno series summed in closed form.
        zeno = st.kind == STEP_ZENO
        _, _, z_dur, z_travel, z_vel, z_spin = jax.lax.cond(
            zeno,
            lambda: _zeno(faces, g, air, law, params, st.face, p, v, w, settings.slack, t_end - t,
                          cut=st.bound == 1),
            lambda: (jnp.bool_(False), jnp.bool_(False), 0.0 * t, 0.0 * v, v, w),
        )
        t1 = jnp.where(zeno, t + z_dur, t + h)
        p1 = jnp.where(zeno, p + z_travel, p1)
        v1 = jnp.where(zeno, z_vel, v1)
        v_post = jnp.where(zeno, z_vel, v_post)
        w_post = jnp.where(zeno, z_spin, w_post)
        node = Node(t, p, v, jnp.where(zeno, g_vec, a0), t1, p1, v1, jnp.where(zeno, g_vec, a1), v_post, w, w_post)
        return (t1, jnp.concatenate([p1, v_post, w_post])), node

    def idle(carry):
        """What ``apply`` gives for a STEP_UNUSED slot."""
        return _idle(f, *carry)

    # 0 * e, not a constant, for a single trace of the body (see estim.forward._solver.replay).
    init = (0.0 * params.e, jnp.concatenate([params.position, params.velocity, params.spin]))
    none = jnp.int32(-1)
    unused = Step(jnp.int32(STEP_UNUSED), jnp.int32(FLIGHT), none, none, none, jnp.int32(0), jnp.float64(0.0))
    n_used = steps.kind.shape[0] if n_used is None else n_used
    (t1, y1), nodes = scan_used(apply, init, steps, n_used, idle, unused, REPLAY_CHUNK)
    return State(t1, y1[:3], y1[3:6]), nodes


@jax.custom_jvp
def nodes_of(scene, params, t_end, settings: OdeSettings, pl: Plan, n_used) -> tuple[State, Node]:
    """The state after a plan's last step and its steps' nodes, with the derivatives of
    ``replay``.

    The forward pass reuses the values ``plan`` recorded (as the closed form's
    ``estim.forward._solver.segments_of`` does): a primal is the step loop alone (the drag
    scene's call, every part kept: 41,200 HLO lines instead of 60,600, XLA's compile 5.2 s
    instead of 6.1 s on a 2-core machine). Only derivatives run ``replay``, over the first ``n_used`` steps
    (forward mode directly, reverse mode through JAX's transpose of it). Its values are
    plan's recomputed: the same but at an event step, whose end replay moves by a Newton
    step of plan's residual (about 0)."""
    return pl.end, pl.nodes


@nodes_of.defjvp
def _nodes_of_jvp(primals, tangents):
    scene, params, t_end, settings, pl, n_used = primals
    d_scene, d_params, d_t_end, d_settings, _, _ = tangents

    def f(s, p, t, st):
        return replay(s, p, t, pl.steps, st, n_used)

    _, d_out = jax.jvp(f, (scene, params, t_end, settings), (d_scene, d_params, d_t_end, d_settings))
    return (pl.end, pl.nodes), d_out


def sample(nodes: Node, steps: Step, faces_normal_of, law: AbstractContactLaw, c, g, t, sums: bool):
    """Position and velocity at times ``t`` from the nodes: quintic Hermite interpolation
    within a step (exact for polynomials of degree 5; the RK steps themselves are the
    accuracy limit), the law's closed form within a summed Zeno series (``sums``:
    ``_sums_series``, static)."""
    shape = jnp.shape(t)
    t = jnp.reshape(t, (-1,))
    used = steps.kind != STEP_UNUSED
    starts = jnp.where(used, nodes.t0, jnp.inf)
    k = jnp.clip(jnp.searchsorted(starts, t, side="right") - 1, 0, starts.shape[0] - 1)
    nd = jax.tree.map(lambda x: x[k], nodes)
    h = nd.t1 - nd.t0
    hs = jnp.where(h > 0, h, 1.0)
    s = jnp.clip((t - nd.t0) / hs, 0.0, 1.0)[:, None]
    hh = hs[:, None]
    # Quintic Hermite basis on [0, 1] for value, first and second derivative at both ends.
    s2, s3, s4, s5 = s**2, s**3, s**4, s**5
    h00 = 1 - 10 * s3 + 15 * s4 - 6 * s5
    h10 = s - 6 * s3 + 8 * s4 - 3 * s5
    h20 = 0.5 * (s2 - 3 * s3 + 3 * s4 - s5)
    h01 = 10 * s3 - 15 * s4 + 6 * s5
    h11 = -4 * s3 + 7 * s4 - 3 * s5
    h21 = 0.5 * (s3 - 2 * s4 + s5)
    pos = h00 * nd.p0 + h10 * hh * nd.v0 + h20 * hh**2 * nd.a0 + h01 * nd.p1 + h11 * hh * nd.v1 + h21 * hh**2 * nd.a1
    d00 = -30 * s2 + 60 * s3 - 30 * s4
    d10 = 1 - 18 * s2 + 32 * s3 - 15 * s4
    d20 = 0.5 * (2 * s - 9 * s2 + 12 * s3 - 5 * s4)
    d01 = 30 * s2 - 60 * s3 + 30 * s4
    d11 = -12 * s2 + 28 * s3 - 15 * s4
    d21 = 0.5 * (3 * s2 - 8 * s3 + 5 * s4)
    vel = (d00 * nd.p0 + d10 * hh * nd.v0 + d20 * hh**2 * nd.a0 + d01 * nd.p1 + d11 * hh * nd.v1 + d21 * hh**2 * nd.a1) / hh

    after = t >= nd.t1
    if not sums:  # (no summed series)
        pos = jnp.where(after[:, None], nd.p1, pos)
        vel = jnp.where(after[:, None], nd.v1_post, vel)
        return pos.reshape(shape + (3,)), vel.reshape(shape + (3,))

    # Inside a Zeno series: the law's closed form, a branch taken only where a sample falls
    # in a series (its counts and powers for every sample, with their derivatives, made
    # the Jacobian of a table-tennis shot's 76 samples, with no series, take three times
    # as long).
    zeno = (steps.kind[k] == STEP_ZENO)
    a = jnp.array([0.0, 0.0, -1.0]) * g

    def in_series(v0, w0, normal, tau):
        ok = jnp.dot(v0, normal) > 0
        normal = jnp.where(ok, normal, jnp.array([0.0, 0.0, 1.0]))
        sr = series(jnp.where(ok, v0, normal), normal, a, w0)
        return law.state_at(sr, tau, c, jnp.inf)[:2]

    def with_series(pos, vel):
        normal = faces_normal_of(jnp.maximum(steps.face[k], 0))
        # Inputs of the unused branch are kept harmless: a NaN there would poison
        # reverse-mode derivatives through the where below.
        tau_z = jnp.where(zeno, jnp.clip(t - nd.t0, 0.0, nd.t1 - nd.t0), 0.0)
        normal = jnp.where(zeno[:, None], normal, jnp.array([0.0, 0.0, 1.0]))
        v_z0 = jnp.where(zeno[:, None], nd.v0, normal)
        dp, v_z = jax.vmap(in_series)(v_z0, nd.w0, normal, tau_z)
        return jnp.where(zeno[:, None], nd.p0 + dp, pos), jnp.where(zeno[:, None], v_z, vel)

    pos, vel = jax.lax.cond(some(zeno), with_series, lambda pos, vel: (pos, vel), pos, vel)
    pos = jnp.where(after[:, None], nd.p1, pos)
    vel = jnp.where(after[:, None], nd.v1_post, vel)
    return pos.reshape(shape + (3,)), vel.reshape(shape + (3,))


class OdeSolution(AbstractSolution):
    """The ODE path's solution: the accepted steps (dense output by quintic Hermite
    interpolation, closed form inside summed Zeno series).

    Attributes:
        nodes: start and end state of every step, per ball.
        steps: the steps' kinds and faces, per ball.
        normals: the unit normal of every face (per ball: the face table depends on r).
        law: the contact law (static; ``estim.forward.laws``), whose closed forms give the
            state inside a summed Zeno series.
        sums: whether the path summed the law's series (static; ``_sums_series``).
        coefficients: the law's numbers per ball (``law.coefficients``).
        gravity: the magnitude g of gravity.
    """

    nodes: Node
    steps: Step
    normals: Float[Array, "*batch faces 3"]
    law: AbstractContactLaw = eqx.field(static=True)
    sums: bool = eqx.field(static=True)
    coefficients: PyTree[Float[Array, "*batch"]]
    gravity: Float[Array, ""]

    def evaluate(self, t):
        batch = self.nodes.t0.shape[:-1]

        def flat(x):
            return x.reshape((-1,) + x.shape[len(batch):])

        nodes, steps, coefficients = jax.tree.map(flat, (self.nodes, self.steps, self.coefficients))

        def one(nd, st, normals, c):
            return sample(nd, st, lambda f: normals[f], self.law, c, self.gravity, t, self.sums)

        p, v = jax.vmap(one)(nodes, steps, flat(self.normals), coefficients)
        return p.reshape(batch + p.shape[1:]), v.reshape(batch + v.shape[1:])


def list_events(nodes: Node, steps: Step, normals, law: AbstractContactLaw, c, g, max_events: int,
                sums: bool) -> Events:
    """The contact events of one ball, as on the closed-form path (``estim.forward._trajectory``):
    every STEP_CONTACT step; for a summed series (STEP_ZENO) its bounces whose flight lasts
    at least ``LISTED_FLIGHT`` (all of them before ``t_end`` for e = 1), each from the law's
    closed form, then a settle event (``REST``) where it accumulates (none for a series cut
    at ``t_end``)."""
    zeno = steps.kind == STEP_ZENO
    contact = steps.kind == STEP_CONTACT
    cut = zeno & (steps.bound == 1)
    normal = normals[jnp.maximum(steps.face, 0)]
    # The first flight of a series lasts T0 = 2 w / |a_n| and flight j, T0 e^j.
    w = jnp.where(zeno, jnp.sum(nodes.v0 * normal, axis=1), 1.0)
    a_n = jnp.where(zeno, normal[:, 2], 1.0) * -g
    t_flight = jnp.where(zeno & (w > 0), 2.0 * w / -a_n, 1.0)
    if sums:  # (counted in a branch, as the series' bounces below: most calls have no series)
        def counted():
            before_end = law.bounces_within((nodes.t1 - nodes.t0) / t_flight, c)
            listable = law.flights_longer(t_flight, LISTED_FLIGHT, c)
            return jnp.where(zeno, jnp.minimum(before_end, listable), 0.0)

        bounces = jax.lax.cond(some(zeno), counted, lambda: jnp.zeros_like(t_flight))
    else:  # (no summed series)
        bounces = jnp.zeros_like(t_flight)
    total = jnp.where(contact, 1.0, bounces + (zeno & ~cut))
    # Slots are int32 indices; a count past max_events only marks the list truncated.
    capped = jnp.minimum(total, max_events + 1.0)
    ends = jnp.cumsum(capped)
    i = jnp.arange(max_events, dtype=jnp.float64)
    k = jnp.clip(jnp.searchsorted(ends, i, side="right"), 0, ends.shape[0] - 1)
    valid = i < ends[-1]
    j = i - (ends - capped)[k] + 1.0  # bounce number within a series, from 1
    in_series = zeno[k] & (j <= bounces[k])
    nd = jax.tree.map(lambda x: x[k], nodes)
    st = jax.tree.map(lambda x: x[k], steps)
    a = jnp.array([0.0, 0.0, -1.0]) * g

    def one_bounce(v0, w0, n, jj):
        ok = jnp.dot(v0, n) > 0
        n = jnp.where(ok, n, jnp.array([0.0, 0.0, 1.0]))
        return law.bounce(series(jnp.where(ok, v0, n), n, a, w0), jj, c)[:6]

    # The spin is constant in flight: before a step's contact it is the step's own, after
    # it the law's; a series' bounces have theirs from the law's closed form.
    spin_pre, spin_post = nd.w0, nd.w1_post
    t, pos, pre, post = nd.t1, nd.p1, nd.v1, nd.v1_post
    if sums:
        def with_series(t, pos, pre, post, spin_pre, spin_post):
            # Inputs of the unused branch are kept harmless (no NaN to poison derivatives).
            n_k = jnp.where(in_series[:, None], normal[k], jnp.array([0.0, 0.0, 1.0]))
            v_k = jnp.where(in_series[:, None], nd.v0, n_k)
            t_b, x_b, pre_b, post_b, w_pre, w_post = jax.vmap(one_bounce)(v_k, nd.w0, n_k,
                                                                          jnp.where(in_series, j, 1.0))
            return (jnp.where(in_series, nd.t0 + t_b, t), jnp.where(in_series[:, None], nd.p0 + x_b, pos),
                    jnp.where(in_series[:, None], pre_b, pre), jnp.where(in_series[:, None], post_b, post),
                    jnp.where(in_series[:, None], w_pre, jnp.where(zeno[k][:, None], nd.w1_post, spin_pre)),
                    jnp.where(in_series[:, None], w_post, spin_post))

        t, pos, pre, post, spin_pre, spin_post = jax.lax.cond(
            some(zeno[k]), with_series, lambda *x: x, t, pos, pre, post, spin_pre, spin_post)
    # A contact without normal speed is a landing to rest, not an impact.
    settle = (zeno[k] & ~in_series) | (~zeno[k] & (jnp.linalg.norm(pre - post, axis=1) <= REST_SPEED))
    zero = jnp.zeros_like(pos)
    return Events(
        t=jnp.where(valid, t, jnp.inf),
        position=jnp.where(valid[:, None], pos, zero),
        velocity_pre=jnp.where(valid[:, None], pre, zero),
        velocity_post=jnp.where(valid[:, None], post, zero),
        face=jnp.where(valid, st.face, -1).astype(jnp.int32),
        kind=jnp.where(valid, jnp.where(settle, REST, IMPACT), -1).astype(jnp.int32),
        count=jnp.minimum(ends[-1], max_events).astype(jnp.int32),
        truncated=ends[-1] > max_events,
        spin_pre=jnp.where(valid[:, None], spin_pre, zero),
        spin_post=jnp.where(valid[:, None], spin_post, zero),
    )


def ball_parts(scene, params, t_end, ts, settings: OdeSettings, max_events: int, keep: frozenset[str]) -> dict:
    """One ball's Trajectory parts (``estim.forward._trajectory.trajectory_parts``): its plan,
    then ``finish``."""
    pl = plan(scene, params, t_end, settings)
    return finish(scene, params, t_end, ts, settings, max_events, pl, pl.n_steps, keep)


def finish(scene, params, t_end, ts, settings: OdeSettings, max_events: int, pl: Plan, n_used,
           keep: frozenset[str]) -> dict:
    """One ball's Trajectory parts from its plan: its nodes (``nodes_of``, derivatives by
    the replay of its first ``n_used`` steps, at least ``pl.n_steps``), then only the samples, events and dense solution that
    ``keep`` keeps."""
    final, nodes = nodes_of(scene, params, t_end, settings, pl, n_used)
    normals = faces_for(scene, params.contact_radius).row[:, NORMAL]
    law = law_of(scene)
    c = law.coefficients(params)
    sums = _sums_series(law, scene.air)
    pos = vel = events = None
    if "samples" in keep:
        pos, vel = sample(nodes, pl.steps, lambda f: normals[f], law, c, scene.gravity, ts, sums)
    if "events" in keep:
        events = list_events(nodes, pl.steps, normals, law, c, scene.gravity, max_events, sums)
    solution = OdeSolution(nodes=nodes, steps=pl.steps, normals=normals, law=law, sums=sums, coefficients=c,
                           gravity=scene.gravity)
    return trajectory_parts(pos, vel, events, State(t_end, final.position, final.velocity), pl.complete,
                            solution, keep)
