"""The exact event-driven solver for scenes where only gravity acts.

The motion of a ball is a sequence of *segments*, each in closed form:

- ``FLIGHT``: a parabola ``p + v tau + a tau^2 / 2`` ending at a contact or at ``t_end``;
- ``TRAIN``: a whole series of bounces on one face, summed in closed form by the contact
  law (``estim.forward.laws``). For the seed's factor law, after a bounce with post-impact
  horizontal velocity u and vertical speed w, flight j lasts ``T0 e^j`` (``T0 = 2 w / g``)
  and carries horizontal velocity ``u mu^j``, so bounce n happens at

      t_n = t_0 + T0 (1 - e^n) / (1 - e),   x_n = x_0 + u T0 (1 - (e mu)^n) / (1 - e mu).   (1)

  For e < 1 the series accumulates at ``t_0 + T0 / (1 - e)`` (Zeno): infinitely many
  bounces in finite time, summed exactly. A train continues as long as the ball provably
  lands on the same face with nothing in the way (``estim.forward._contact.train_reach``);
- ``SLIDE``: motion along a face after the bounces have died out (a ball at rest is a
  slide with zero velocity); it ends where the ball slides off the face, at a wall, or at
  ``t_end``;
- ``ROLL``: a ball pressed onto an edge or a corner (exact geometry) rolls over it, its
  centre on a circle about the edge line: an inverted pendulum in closed form
  (``estim.forward._roll``); it ends where the ball leaves the edge, comes back onto the
  face above it, reaches the edge's end, or at ``t_end``.

So the number of segments is bounded by the number of faces a ball visits, not by the
number of bounces, and compute stays bounded for every e, including e = 0 and e = 1.

The contact law is the scene's (``estim.forward.laws.law_of``): every reset and every
series closed form below is the law's. A law that is not summable has no TRAIN: every
bounce is a segment of its own, a ball comes to rest where its rebound falls below
``REST_SPEED``, and compute is bounded by ``max_segments``.

Two passes keep this exact *and* differentiable:

1. ``plan`` (a ``lax.while_loop`` on values with gradients stopped) finds the discrete
   structure: the kind of each segment, the face it ends on, how many bounces a train has.
2. ``replay`` (a ``lax.scan``) recomputes every segment from the structure with
   differentiable closed forms. Its derivatives are the event-time sensitivities of the
   hybrid system (the implicit-function derivative of each contact time, composed with the
   reset maps), exact for the given sequence of contacts.

Both passes call the same ``advance`` function, so they agree to the last bit.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..model._scene import Scene
from ._constants import (
    AXIS_TOL,
    BOUNCES,
    CONTACT,
    END,
    EXIT,
    FLIGHT,
    REST_SPEED,
    ROLL,
    SETTLE,
    SLIDE,
    TIE_TIME,
    TRAIN,
    UNUSED,
)
from ._contact import (
    DIRECTION,
    Faces,
    across_speed2,
    ballistic,
    contact_normal,
    face_entering_time,
    face_normal,
    faces_for,
    first_contact,
    inner,
    is_corner,
    is_curved,
    next_piece,
    piece_at,
    roll_axis,
    roll_exit_time,
    slide_exit_time,
    train_reach,
)
from ._roll import Roll, Spherical, roll_state, spherical_stand_in
from ._scan import scan_used
from .laws import AbstractContactLaw, law_of, series

# Segment kinds (Decision.kind: FLIGHT, TRAIN, SLIDE, UNUSED) and why a segment ends
# (Decision.reason: END, CONTACT, EXIT, BOUNCES, SETTLE) are numbered once, in
# estim.forward._constants, for this planner, the ODE path's modes and the native kernels.


class Decision(eqx.Module):
    """The discrete structure of one segment (found by ``plan``)."""

    kind: Int[Array, ""]
    support: Int[Array, ""]  # face slid or bounced on (TRAIN, SLIDE) or slid off (FLIGHT), else -1
    n: Float[Array, ""]  # bounces in a TRAIN (inf for a Zeno train)
    reason: Int[Array, ""]  # END, CONTACT, EXIT, BOUNCES or SETTLE
    face: Int[Array, ""]  # face hit at a CONTACT, else -1


class Segment(eqx.Module):
    """One segment in closed form: its start state and acceleration, its end state."""

    t0: Float[Array, ""]
    p0: Float[Array, "3"]
    v0: Float[Array, "3"]
    acc: Float[Array, "3"]
    t1: Float[Array, ""]
    p1: Float[Array, "3"]
    v1: Float[Array, "3"]  # just before the end (pre-impact at a contact)
    v1_post: Float[Array, "3"]  # just after the end (post-impact at a contact)
    normal: Float[Array, "3"]  # normal of the face a TRAIN bounces on, the axis a ROLL turns about (else zero)
    pivot: Float[Array, "3"]  # a point of the axis a ROLL turns about (else zero)


def _slide_frame(faces, support, v, a):
    """Velocity and acceleration of a ball sliding on face ``support``."""
    n = face_normal(faces, jnp.maximum(support, 0))
    return v - inner(v, n) * n, a - inner(a, n) * n


class RollOver:
    """The roll of a ball at p with velocity v over curved piece ``face`` (an edge or a
    corner, ``roll_axis``): the pendulum about a horizontal line (``estim.forward._roll.Roll``)
    over an edge, or over a corner in the vertical plane through its vertex; elsewhere over
    a corner the spherical pendulum (``Spherical``, ``spherical``). ``ends``: the time to
    its end (it leaves the surface or the piece's region); ``axis`` the line's direction
    (zero for a spherical roll), ``pivot`` a point of it (the vertex on a corner);
    ``exit_axis`` the axis whose bound a spherical roll crosses at its end (-1: it leaves
    the surface). Both motions are computed and one is selected; the one not taken from
    a stand-in state (no NaN in values or derivatives)."""

    def __init__(self, faces: Faces, face, p, v, g):
        pivot, axis, planar = roll_axis(faces, face, p, v)
        corner = is_corner(faces, face)
        self.spherical = corner & ~planar
        self.pivot, self.axis = pivot, jnp.where(self.spherical, 0.0, axis)
        self.plane = Roll(pivot, axis, p, v, g)
        p_s, v_s = spherical_stand_in(self.spherical, pivot, p, v, faces.radius, g)
        self.sphere = Spherical(pivot, p_s, v_s, g, faces.row[face, DIRECTION])
        self.exit_axis = jnp.where(self.spherical, self.sphere.exit_axis, -1)
        ends = jnp.minimum(self.plane.duration, roll_exit_time(faces, face, pivot, axis, p, v))
        self.ends = jnp.where(self.spherical, self.sphere.duration, ends)

    def state(self, tau):
        """Position and velocity ``tau`` after the start."""
        return roll_state(self.spherical, self.plane, self.sphere, tau)

    @staticmethod
    def follows(faces: Faces, face, p, v):
        """Whether a roll over ``face`` from (p, v) is one estim follows: every roll over a
        corner, over an edge where the edge is horizontal."""
        return roll_axis(faces, face, p, v)[2] | is_corner(faces, face)


def advance(faces: Faces, gravity, law: AbstractContactLaw, c, t, p, v, d: Decision, t_end, found,
            rolls: bool = True) -> Segment:
    """Carry the state (t, p, v) through one segment with structure ``d``, under the
    contact law ``law`` with the ball's coefficients ``c`` (``law.coefficients``).
    ``found``: the contact time the search found (values: used on an edge or a corner,
    ``estim.forward._contact.face_entering_time``). ``rolls`` (static): ``False`` leaves
    ``ROLL`` segments out (they are carried as if in flight), for a caller that knows its
    plans have none (``replay``)."""
    g = gravity
    a = jnp.array([0.0, 0.0, -1.0]) * g
    slide_v, slide_a = _slide_frame(faces, d.support, v, a)
    sliding = d.kind == SLIDE
    v0 = jnp.where(sliding, slide_v, v)
    acc = jnp.where(sliding, slide_a, a)
    face = jnp.maximum(d.face, 0)

    # FLIGHT and SLIDE: ballistic motion to a contact, a slide exit, or t_end.
    tau_contact = face_entering_time(faces, face, p, v0, acc, found)
    tau_exit = slide_exit_time(faces, jnp.maximum(d.support, 0), p, v0, acc)
    tau_b = jnp.where(d.reason == CONTACT, tau_contact, jnp.where(d.reason == EXIT, tau_exit, t_end - t))
    tau_b = jnp.where(jnp.isfinite(tau_b), tau_b, 0.0)
    p_b, v_b = ballistic(p, v0, acc, tau_b)
    n_face = contact_normal(faces, face, p_b)
    v_b_post = jnp.where(d.reason == CONTACT, law.contact_velocity(v_b, n_face, a, c), v_b)

    # TRAIN: a closed-form series of bounces, to bounce n, to its accumulation, or to t_end.
    # (lax.cond: for one ball a branch, so a flight skips the series' closed forms; under
    # vmap both branches run, and the guards below keep the one not taken finite.)
    is_train = d.kind == TRAIN
    up = jnp.array([0.0, 0.0, 1.0])

    def train(_):
        n_sup = jnp.where(is_train, face_normal(faces, jnp.maximum(d.support, 0)), up)
        s = series(jnp.where(is_train, v, up), n_sup, a)  # a finite series off-branch: no NaN cotangents
        n_tr = jnp.where(is_train, d.n, 1.0)
        at_end = d.reason == END
        # The end of the whole series is used only when it ends before t_end; a series cut at
        # t_end may be one that never ends (e = 1, n = inf: duration T0 * inf, whose derivative
        # w.r.t. T0 is inf and turned the discarded branch's zero cotangent into NaN in
        # reverse mode), so it is evaluated at a harmless n = 1 there.
        duration, travel, v_full, _ = law.series_end(s, jnp.where(at_end, 1.0, n_tr), c)
        tau_t = jnp.where(at_end, t_end - t, jnp.where(jnp.isfinite(duration), duration, 0.0))
        tr_travel, tr_vel, _ = law.state_at(s, tau_t, c, n_tr)
        return tau_t, p + jnp.where(at_end, tr_travel, travel), jnp.where(at_end, tr_vel, v_full), n_sup

    def no_train(_):
        return 0.0 * t, p, v, up + 0.0 * v

    if law.summable:
        tau_t, p_tr, v_tr_end, n_sup = jax.lax.cond(is_train, train, no_train, None)
    else:  # (no TRAIN segments: every bounce is a segment of its own)
        tau_t, p_tr, v_tr_end, n_sup = no_train(None)

    tau = jnp.where(is_train, tau_t, tau_b)
    unused = d.kind == UNUSED
    p1 = jnp.where(unused, p, jnp.where(is_train, p_tr, p_b))
    v1 = jnp.where(unused, v, jnp.where(is_train, v_tr_end, v_b))
    v1_post = jnp.where(unused, v, jnp.where(is_train, v_tr_end, v_b_post))
    normal, pivot = jnp.where(is_train, n_sup, 0.0), jnp.zeros(3)

    if faces.curved and rolls:  # ROLL: over an edge or a corner, to its end or to t_end
        is_roll = d.kind == ROLL

        def roll(_):
            motion = RollOver(faces, jnp.maximum(d.support, 0), p, v, g)
            ends = motion.ends
            tau_r = jnp.where(d.reason == END, t_end - t, jnp.where(jnp.isfinite(ends), ends, 0.0))
            p_r, v_r = motion.state(tau_r)
            return tau_r, p_r, v_r, motion.axis, motion.pivot

        def no_roll(_):
            return tau, p1, v1, normal, pivot

        tau, p_r, v_r, normal, pivot = jax.lax.cond(is_roll, roll, no_roll, None)
        p1, v1, v1_post = p_r, v_r, jnp.where(is_roll, v_r, v1_post)
    t1 = jnp.where(unused, t, t + tau)
    return Segment(t, p, v0, acc, t1, p1, v1, v1_post, normal, pivot)


def _next_structure(faces: Faces, gravity, law: AbstractContactLaw, c, seg: Segment, d: Decision):
    """Kind, support and bounce count of the segment that follows ``seg``, and whether the
    ball goes on (``False`` where it would roll over an edge that is not horizontal: not
    followed)."""
    g = gravity
    a = jnp.array([0.0, 0.0, -1.0]) * g
    face = jnp.maximum(d.face, 0)
    n_face = contact_normal(faces, face, seg.p1)
    post = seg.v1_post
    curved = is_curved(faces, face) & (d.reason == CONTACT)
    touches = jnp.abs(inner(post, n_face)) <= REST_SPEED
    settled = touches & (inner(n_face, a) < 0) & ~curved
    # On an edge or a corner a ball without normal speed follows the curve (rolls over it)
    # where gravity's push into the surface exceeds the centripetal acceleration of its
    # tangential motion across the curve, |u|^2 / r; else it leaves the surface at once.
    rolls = curved & touches & (inner(n_face, a) + across_speed2(faces, face, post, n_face) / faces.radius < 0)
    up = (n_face[2] > 1.0 - AXIS_TOL) & ~curved

    def on_upward(_):
        """A bounce series on an upward face: how many bounces provably land on it."""
        w = post[2]
        u = post.at[2].set(0.0)
        t_flight = 2.0 * w / g
        reach = train_reach(faces, face, seg.p1, u, w * w / (2.0 * g))
        speed = jnp.sqrt(u[0] ** 2 + u[1] ** 2)
        y = jnp.where(speed > 0, reach / jnp.where(speed > 0, speed * t_flight, 1.0), jnp.inf)
        return jnp.where(reach < 0, 0.0, law.landings_within(y, c))

    if law.summable:
        # (lax.cond: for one ball only the count its face needs is computed.)
        n_train = jax.lax.cond(up, on_upward, lambda _: jnp.float64(0.0), None)
    else:  # bounce by bounce
        n_train = jnp.float64(0.0)
    # A wall hit while sliding keeps the ball on its face.
    if_support = face_normal(faces, jnp.maximum(d.support, 0))
    stays = (d.kind == SLIDE) & (jnp.abs(inner(n_face, if_support)) < AXIS_TOL) & ~curved

    after_contact_kind = jnp.where(stays | settled, SLIDE, jnp.where(up & (n_train >= 1), TRAIN, FLIGHT))
    after_contact_kind = jnp.where(rolls, ROLL, after_contact_kind)
    # A ball that touches an edge or a corner without normal speed and leaves it does not
    # meet that piece again in the flight that follows (it is excluded, as a face slid off);
    # one that rolls over it rolls on that piece.
    grazed = curved & touches
    after_contact_support = jnp.where(stays | grazed, jnp.where(stays, d.support, face), face)
    kind = jnp.select(
        [d.reason == CONTACT, d.reason == SETTLE, d.reason == END],
        [after_contact_kind, SLIDE, UNUSED],
        FLIGHT,
    )
    support = jnp.select(
        [d.reason == CONTACT, d.reason == SETTLE, d.reason == EXIT],
        [after_contact_support, d.support, d.support],
        -1,
    )
    # A FLIGHT keeps as support the face it slid off (excluded from its contacts).
    keeps = (kind == TRAIN) | (kind == SLIDE) | (kind == ROLL) | (d.reason == EXIT) | ((d.reason == CONTACT) & grazed)
    support = jnp.where(keeps, support, -1)
    goes_on = jnp.bool_(True)
    if faces.curved:
        def roll_next(_):
            """A ball that starts to roll rolls about a horizontal line (estim.forward._roll)
            where that is its motion; one whose roll reaches the end of its edge goes on
            over the corner there (a flight would find the edge, the face above it and the
            corner all touched at once)."""
            sup = jnp.maximum(d.support, 0)
            motion = RollOver(faces, sup, seg.p0, seg.v0, g)
            # Off an edge's end onto the corner there; off a corner's region onto the edge
            # it crossed into.
            at_end = jnp.where(motion.spherical, motion.exit_axis >= 0,
                               roll_exit_time(faces, sup, motion.pivot, motion.axis, seg.p1, seg.v1) <= TIE_TIME)
            free = jnp.where(motion.spherical, motion.exit_axis, jnp.argmin(piece_at(faces, sup)[1]))
            onward, found = next_piece(faces, sup, jnp.maximum(free, 0), seg.v1)
            # (Onto it only if pressed onto it, as at a contact: a ball that rolls along an
            # edge to its end faster than the corner holds flies off from the edge.)
            n_on = contact_normal(faces, onward, seg.p1)
            pressed = inner(n_on, a) + across_speed2(faces, onward, seg.v1, n_on) / faces.radius < 0
            onto = (d.kind == ROLL) & (d.reason == EXIT) & at_end & found & pressed
            piece, u = jnp.where(onto, onward, face), jnp.where(onto, seg.v1, post)
            followed = RollOver.follows(faces, piece, seg.p1, u)
            return jnp.where(onto, ROLL, kind), jnp.where(onto, onward, support), ~(rolls | onto) | followed

        # (lax.cond: for one ball, the work of a roll only where one starts or ends.)
        kind, support, goes_on = jax.lax.cond(rolls | (d.kind == ROLL), roll_next,
                                              lambda _: (kind, support, goes_on), None)
    n = jnp.where(kind == TRAIN, n_train, 0.0)
    return kind.astype(jnp.int32), support.astype(jnp.int32), n, goes_on


def _decide_end(faces: Faces, gravity, law: AbstractContactLaw, c, t, p, v, kind, support, n, t_end):
    """How the segment starting at (t, p, v) ends: ``(reason, face, tau)``, tau the time to
    a contact (else inf)."""
    g = gravity
    a = jnp.array([0.0, 0.0, -1.0]) * g
    is_train = kind == TRAIN

    def ballistic_end(_):
        slide_v, slide_a = _slide_frame(faces, support, v, a)
        sliding = kind == SLIDE
        v0 = jnp.where(sliding, slide_v, v)
        acc = jnp.where(sliding, slide_a, a)
        # A slide's own face, and after sliding off a face that face, are excluded: the ball
        # is on its plane, pressed towards it, but beyond its edge.
        tau_c, face = first_contact(faces, p, v0, acc, support, sliding=sliding)
        tau_x = jnp.where(sliding, slide_exit_time(faces, jnp.maximum(support, 0), p, v0, acc), jnp.inf)
        tau_b = jnp.minimum(tau_c, tau_x)
        reason_b = jnp.where(t + tau_b >= t_end, END, jnp.where(tau_c <= tau_x, CONTACT, EXIT))
        return reason_b.astype(jnp.int32), jnp.where(reason_b == CONTACT, face, -1).astype(jnp.int32), tau_c

    def train_end(_):
        up = jnp.array([0.0, 0.0, 1.0])
        n_sup = jnp.where(is_train, face_normal(faces, jnp.maximum(support, 0)), up)
        s = series(jnp.where(is_train, v, up), n_sup, a)
        duration, *_ = law.series_end(s, jnp.where(is_train, n, 1.0), c)
        reason_t = jnp.where(t + duration >= t_end, END, jnp.where(jnp.isfinite(n), BOUNCES, SETTLE))
        return reason_t.astype(jnp.int32), jnp.int32(-1), jnp.float64(jnp.inf)

    def roll_end(_):
        ends = RollOver(faces, jnp.maximum(support, 0), p, v, g).ends
        reason_r = jnp.where(t + ends >= t_end, END, EXIT)
        return reason_r.astype(jnp.int32), jnp.int32(-1), jnp.float64(jnp.inf)

    # (lax.switch: for one ball only the end its segment's kind needs is computed.)
    branches = [ballistic_end]
    if law.summable:  # (else no TRAIN segments)
        branches.append(train_end)
    if faces.curved:  # (else no ROLL segments)
        branches.append(roll_end)
    which = jnp.where(is_train, 1, 0) if law.summable else 0
    which = jnp.where(kind == ROLL, len(branches) - 1, which) if faces.curved else which
    return jax.lax.switch(which, branches, None) if len(branches) > 1 else ballistic_end(None)


class Plan(eqx.Module):
    """Discrete structure of a whole solution, and its segments (values, no gradients)."""

    decisions: Decision  # each field has a leading axis of length max_segments
    segments: Segment  # likewise
    n_segments: Int[Array, ""]
    complete: Array  # bool: reached t_end within max_segments


def plan(scene: Scene, params, t_end, max_segments: int) -> Plan:
    """Find the discrete structure of one ball's solution (no gradients flow through this
    pass): a ``lax.while_loop`` over its segments, writing one slot of the record per
    iteration. One ball, not a batch: ``estim.forward._simulate`` runs it for each ball inside its
    loop over balls, so that the branches of a segment (``lax.cond``) are branches."""
    scene, params, t_end = jax.lax.stop_gradient((scene, params, jnp.asarray(t_end, jnp.float64)))
    g = scene.gravity
    law = law_of(scene)
    table = faces_for(scene, jnp.float64(0.0))  # the ball's radius is attached in the loop
    S = max_segments
    d0 = Decision(jnp.int32(UNUSED), jnp.int32(-1), jnp.float64(0.0), jnp.int32(END), jnp.int32(-1))
    zero, z3 = jnp.float64(0.0), jnp.zeros(3)
    blank = Segment(zero, z3, z3, z3, zero, z3, z3, z3, z3, z3)  # each slot is written, or filled below
    record = jax.tree.map(lambda x: jnp.broadcast_to(x, (S,) + x.shape), (d0, blank))

    def cond(carry):
        k, _, done, _, _ = carry
        return (k < S) & (done == 0)

    def body(carry):
        k, (t, p, v, kind, support, n), _, record, (params, t_end) = carry
        faces = eqx.tree_at(lambda f: f.radius, table, params.contact_radius)
        c = law.coefficients(params)
        reason, face, tau = _decide_end(faces, g, law, c, t, p, v, kind, support, n, t_end)
        d = Decision(kind, support, n, reason, face)
        seg = advance(faces, g, law, c, t, p, v, d, t_end, tau)
        *following, goes_on = _next_structure(faces, g, law, c, seg, d)
        record = jax.tree.map(lambda r, x: r.at[k].set(x), record, (d, seg))
        state = (seg.t1, seg.p1, seg.v1_post) + tuple(following)
        # The parameters go round the loop through an optimization barrier, so that XLA does
        # not hoist their share of the work out of it (as some 70 separate kernels).
        done = jnp.where(goes_on, (d.reason == END).astype(jnp.int32), jnp.int32(-1))  # -1: cannot go on
        return k + 1, state, done, record, jax.lax.optimization_barrier((params, t_end))

    state = (zero, params.position, params.velocity, jnp.int32(FLIGHT), jnp.int32(-1), zero)
    init = (jnp.int32(0), state, jnp.int32(0), record, (params, t_end))
    count, _, done, (decisions, segments), _ = jax.lax.while_loop(cond, body, init)
    # Unused slots hold the final state, so that sampling past the last segment is exact.
    last = jax.tree.map(lambda x: x[jnp.maximum(count - 1, 0)], segments)
    fill = Segment(last.t1, last.p1, last.v1_post, z3, last.t1, last.p1, last.v1_post, last.v1_post, z3, z3)
    unused = jnp.arange(S) >= count
    segments = jax.tree.map(
        lambda x, f: jnp.where(unused.reshape((S,) + (1,) * f.ndim), f, x), segments, fill
    )
    return Plan(decisions=decisions, segments=segments, n_segments=count, complete=done == 1)


def replay(scene: Scene, params, t_end, decisions: Decision, durations, n_used=None, rolls: bool = True) -> Segment:
    """Recompute every segment from the structure, differentiably (a ``lax.scan`` that runs
    only the first ``n_used`` segments, default all: ``estim.forward._scan``).
    ``durations``: each segment's duration in the plan (values; the contact times on edges
    and corners are taken from them, not searched for again). ``rolls`` (static):
    ``False`` for structures without ``ROLL`` segments (``advance``): on exact geometry
    the roll's closed forms are most of a replay's program (``segments_of``)."""

    faces = faces_for(scene, params.contact_radius)
    a = jnp.array([0.0, 0.0, -1.0]) * scene.gravity
    law = law_of(scene)
    c = law.coefficients(params)

    def step(state, item):
        t, p, v = state
        d, found = item
        seg = advance(faces, scene.gravity, law, c, t, p, v, d, t_end, found, rolls)
        return (seg.t1, seg.p1, seg.v1_post), seg

    def idle(state):
        """What ``advance`` gives for an UNUSED slot: the state, unchanged."""
        t, p, v = state
        return Segment(t, p, v, a, t, p, v, v, jnp.zeros(3), jnp.zeros(3))

    # t starts as 0 * e, not a constant: its tangent and batch axis are then those of the
    # rest of the carry from the start, and JAX traces the scan's body once, not to a
    # fixed point (seconds of tracing inside a fit's jacfwd and vmap).
    init = (0.0 * params.e, params.position, params.velocity)
    unused = Decision(jnp.int32(UNUSED), jnp.int32(-1), jnp.float64(0.0), jnp.int32(END), jnp.int32(-1))
    n_used = decisions.kind.shape[0] if n_used is None else n_used
    _, segments = scan_used(step, init, (decisions, durations), n_used, idle, (unused, jnp.float64(0.0)))
    return segments


@functools.partial(jax.custom_jvp, nondiff_argnums=(6,))
def segments_of(scene: Scene, params, t_end, decisions: Decision, planned: Segment, n_used,
                rolls: bool = True) -> Segment:
    """The segments of a plan, with the derivatives of ``replay``.

    The forward pass reuses the values ``plan`` already computed; only derivatives run
    ``replay`` (forward mode directly, reverse mode through JAX's transpose of it), over
    the first ``n_used`` segments (at least the plan's ``n_segments``; one number for a
    whole batch makes the rest free, ``estim.forward._scan``). ``rolls`` (static):
    ``False`` where the plan has no ``ROLL`` segment (``replay``; its derivatives are
    wrong on one).
    """
    return planned


@segments_of.defjvp
def _segments_of_jvp(rolls, primals, tangents):
    scene, params, t_end, decisions, planned, n_used = primals
    d_scene, d_params, d_t_end, _, _, _ = tangents

    durations = jax.lax.stop_gradient(planned.t1 - planned.t0)

    def f(s, p, t):
        return replay(s, p, t, decisions, durations, n_used, rolls)

    _, d_out = jax.jvp(f, (scene, params, t_end), (d_scene, d_params, d_t_end))
    return planned, d_out
