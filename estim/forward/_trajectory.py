"""The trajectory type: sampled states, contact events, final state, exact dense output."""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PyTree

from ._constants import BOUNCES, CONTACT, LISTED_FLIGHT, REST_SPEED, ROLL, SETTLE, TRAIN, UNUSED
from ._constants import IMPACT as IMPACT
from ._constants import REST as REST
from ._contact import inner
from ._record import Layout, layout_of, pack, unpack
from ._roll import Roll, Spherical, roll_state, spherical_stand_in
from ._scan import scan_used
from ._solver import Decision, Segment
from .laws import AbstractContactLaw, series

# Event kinds (Events.kind: IMPACT, REST) are numbered in estim.forward._constants; bounces
# of a Zeno series whose flight is shorter than LISTED_FLIGHT are summed, not listed.
EVENT_KINDS = ("impact", "settle")


class State(eqx.Module):
    """Time, centre position and velocity of a ball."""

    t: Float[Array, "*batch"]
    position: Float[Array, "*batch 3"]
    velocity: Float[Array, "*batch 3"]


class Events(eqx.Module):
    """Contact events in time order, padded to ``max_events``.

    Attributes:
        t: event times (s); padding is ``inf``.
        position: ball centre at the event (m).
        velocity_pre, velocity_post: velocity just before and just after (m/s).
        face: index of the face touched (``Scene.face_label`` names it); padding -1.
        kind: ``IMPACT`` (0) for a bounce; ``REST`` (1) where a bounce series ends (Zeno
            accumulation) or the ball lands without normal speed, after which it rests or
            slides on the face.
        count: number of listed events.
        truncated: more events happened than ``max_events`` could hold.
        spin_pre, spin_post: the ball's angular velocity (rad/s) just before and just after,
            where the simulation carries spin (the ODE path: a scene with air or a law that
            couples spin); ``None`` on the closed-form path, where spin plays no part.
    """

    t: Float[Array, "*batch events"]
    position: Float[Array, "*batch events 3"]
    velocity_pre: Float[Array, "*batch events 3"]
    velocity_post: Float[Array, "*batch events 3"]
    face: Int[Array, "*batch events"]
    kind: Int[Array, "*batch events"]
    count: Int[Array, "*batch"]
    truncated: Bool[Array, "*batch"]
    spin_pre: Float[Array, "*batch events 3"] | None = None
    spin_post: Float[Array, "*batch events 3"] | None = None


class AbstractSolution(eqx.Module):
    """The whole solution of a simulation, densely: ``evaluate`` samples it anywhere."""

    gravity: eqx.AbstractVar[Float[Array, ""]]

    @abc.abstractmethod
    def evaluate(self, t: Float[Array, "*times"]) -> tuple[Array, Array]:
        """Position and velocity at times ``t`` (any shape), for every ball."""


class ClosedFormSolution(AbstractSolution):
    """The exact piecewise closed-form solution (gravity only, ``estim.forward._solver``).

    Attributes:
        segments: the segments (flights, bounce series, slides, rolls) per ball.
        structure: their discrete structure (kinds, faces, bounce counts).
        law: the contact law (static; ``estim.forward.laws``), whose closed forms give the
            state inside a bounce series.
        coefficients: the law's numbers per ball (``law.coefficients``: for the factor law
            ``.e`` and ``.mu_t``).
        gravity: the magnitude g of gravity.
        rolls: static: whether segments may be rolls over edges (exact geometry).
    """

    segments: Segment
    structure: Decision
    law: AbstractContactLaw = eqx.field(static=True)
    coefficients: PyTree[Float[Array, "*batch"]]
    gravity: Float[Array, ""]
    rolls: bool = eqx.field(static=True, default=False)

    def evaluate(self, t):
        batch = self.segments.t0.shape[:-1]
        flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[len(batch):]),
                            (self.segments, self.structure, self.coefficients))
        fn = jax.vmap(lambda s, d, c: sample(s, d, self.law, c, self.gravity, t, self.rolls))
        p, v = fn(*flat)
        return p.reshape(batch + p.shape[1:]), v.reshape(batch + v.shape[1:])


# What ``estim.simulate(..., keep=...)`` may keep besides the final state and completion,
# and the parts of a Trajectory each one is.
KEEP = ("samples", "events", "solution")
_KEPT_AS = {"samples": ("position", "velocity"), "events": ("events",), "solution": ("solution",)}
_PART_OF = {part: name for name, parts in _KEPT_AS.items() for part in parts}


def _view(read, *arrays):
    """``read(*arrays)``, where ``read`` slices: traced arrays (free slices) and NumPy arrays
    directly; concrete JAX arrays through their NumPy views (zero-copy on the CPU), handing
    back JAX arrays. Eager JAX slices would compile one small program per slice shape
    (0.3 s for the first reads of a trajectory in a fresh process, against 0.3 ms so)."""
    if any(isinstance(x, jax.core.Tracer) or not isinstance(x, jax.Array) for x in arrays):
        return read(*arrays)
    return jax.tree.map(jnp.asarray, read(*(np.asarray(x) for x in arrays)))


class Trajectory(eqx.Module):
    """What :func:`estim.simulate` returns, on either path (closed form or ODE).

    Attributes:
        ts: the requested sample times, shape ``(times,)``.
        position, velocity: the state at ``ts``, shape ``(*batch, times, 3)``.
        events: every contact event (see :class:`Events`).
        final: the state at ``t_end``.
        complete: whether ``t_end`` was reached within the step or segment budget.
        solution: the dense solution; ``evaluate`` samples it at any time.
        gravity: the magnitude g of the scene's gravity (m/s^2).

    Every attribute is a view of three arrays: ``record`` (the numbers of each ball in one
    row) and ``flags`` (its integers and flags), laid out by the static ``layout``
    (``estim.forward._record``), and ``clock`` (the sample times, then g). A jitted function hands
    back every array of its result as a buffer of its own, at about 1.5 us each on the
    CPU: packed, a trajectory is 3 arrays instead of 32, and the seed's forward call takes
    about half the time (docs/pages/speed.md). Build one with :meth:`Trajectory.pack`, or
    ``Trajectory(ts, record, flags, gravity, layout)`` from packed rows.

    ``traj[i]`` is the trajectory of the balls ``i`` selects (indexing the batch axes). A
    trajectory simulated with ``keep`` (:func:`estim.simulate`) has only what it kept:
    reading the samples, events or solution it left out raises ``ValueError``.
    """

    clock: Float[Array, " times_and_g"]
    record: Float[Array, "*batch numbers"]
    flags: Int[Array, "*batch integers"]
    layout: Layout = eqx.field(static=True)

    def __init__(self, ts: Float[ArrayLike, " times"], record, flags, gravity: Float[ArrayLike, ""], layout: Layout):
        self.clock = jnp.concatenate([jnp.asarray(ts, jnp.float64), jnp.reshape(jnp.asarray(gravity, jnp.float64), (1,))])
        self.record = record
        self.flags = flags
        self.layout = layout

    def _clock(self, index):
        return _view(lambda c: c[index], self.clock)

    @property
    def ts(self) -> Float[Array, " times"]:
        """The requested sample times."""
        return self._clock((..., slice(None, -1)))

    @property
    def gravity(self) -> Float[Array, ""]:
        """The magnitude g of the scene's gravity (m/s^2)."""
        return self._clock((..., -1))

    @classmethod
    def pack(cls, ts, position, velocity, events: Events, final: State, complete, solution,
             batch_ndim: int | None = None, keep: frozenset[str] = frozenset(KEEP)) -> Trajectory:
        """A trajectory from its parts (``batch_ndim`` batch axes, default those of
        ``complete``), keeping those ``keep`` names."""
        parts = trajectory_parts(position, velocity, events, final, complete, solution, keep)
        batch_ndim = jnp.ndim(complete) if batch_ndim is None else batch_ndim
        layout = layout_of(parts, batch_ndim)
        record, flags = pack(parts, layout, jnp.shape(complete)[:batch_ndim])
        return cls(ts=ts, record=record, flags=flags, gravity=solution.gravity, layout=layout)

    def _part(self, name):
        if not any(part == name for part, *_ in self.layout.parts):
            kept = ", ".join(repr(k) for k in KEEP if any(p in _KEPT_AS[k] for p, *_ in self.layout.parts))
            raise ValueError(
                f"this trajectory has no {name}: it was simulated with keep=({kept}); "
                f"pass keep=... with {_PART_OF[name]!r} to estim.simulate"
            )
        return _view(lambda record, flags: unpack(record, flags, self.layout, name), self.record, self.flags)

    def __getitem__(self, index) -> Trajectory:
        """The balls ``index`` selects (NumPy indexing of the batch axes): ``traj[0]`` is
        the first ball's trajectory, ``traj[:3]`` the first three."""
        if index is Ellipsis or (isinstance(index, tuple) and Ellipsis in index):
            raise IndexError("index a Trajectory's batch axes without '...'")
        record, flags = self.record[index], self.flags[index]
        if record.ndim < 1 or record.shape[-1] != self.record.shape[-1]:
            raise IndexError(f"{index!r} indexes more than the batch axes {self.record.shape[:-1]}")
        return eqx.tree_at(lambda tr: (tr.record, tr.flags), self, (record, flags))

    @property
    def position(self) -> Float[Array, "*batch times 3"]:
        return self._part("position")

    @property
    def velocity(self) -> Float[Array, "*batch times 3"]:
        return self._part("velocity")

    @property
    def events(self) -> Events:
        return self._part("events")

    @property
    def final(self) -> State:
        return self._part("final")

    @property
    def complete(self) -> Bool[Array, "*batch"]:
        return self._part("complete")

    @property
    def solution(self) -> AbstractSolution:
        """The dense solution; ``evaluate`` samples it at any time."""
        return eqx.tree_at(lambda s: s.gravity, self._part("solution"), self.gravity,
                           is_leaf=lambda x: x is None)

    def evaluate(self, t: Float[Array, "*times"]) -> tuple[Array, Array]:
        """Position and velocity at times ``t`` (any shape), for every ball: exact on the
        closed-form path, the solver's accuracy on the ODE path. Every t must be finite and
        lie in ``[0, t_end]`` (checked in Python for concrete values, in the program
        inside ``jit``): the solution describes that interval only."""
        t_end = self.final.t
        if isinstance(t, jax.core.Tracer) or isinstance(t_end, jax.core.Tracer):
            t = jnp.asarray(t, dtype=jnp.float64)
            ok = jnp.all(jnp.isfinite(t)) & (jnp.min(t, initial=0.0) >= 0) & (jnp.max(t, initial=0.0) <= jnp.min(t_end))
            t = eqx.error_if(t, ~ok, "Trajectory.evaluate: t must be finite and lie in [0, t_end]")
        else:
            tv, end = np.asarray(t, dtype=np.float64), float(np.min(np.asarray(t_end)))
            if not np.all(np.isfinite(tv) & (tv >= 0) & (tv <= end)):
                bad = tv[~(np.isfinite(tv) & (tv >= 0) & (tv <= end))].ravel()[:4].tolist()
                raise ValueError(f"Trajectory.evaluate: t must be finite and lie in [0, t_end={end}], got {bad}")
        return self.solution.evaluate(t)


def check_keep(keep) -> frozenset[str]:
    """``keep`` of ``estim.simulate`` as a set (None: everything)."""
    if keep is None:
        return frozenset(KEEP)
    if isinstance(keep, str):
        keep = (keep,)
    unknown = [k for k in keep if k not in KEEP]
    if unknown:
        raise ValueError(f"keep may name {', '.join(map(repr, KEEP))} (the final state is always kept), "
                         f"got {unknown[0]!r}")
    return frozenset(keep)


def trajectory_parts(position, velocity, events: Events, final: State, complete, solution,
                     keep: frozenset[str] = frozenset(KEEP)) -> dict:
    """The per-ball parts of a :class:`Trajectory` that ``keep`` keeps, as
    ``Trajectory.record`` and ``flags`` hold them (the solution's gravity, one number for
    all balls, apart)."""
    parts = {"final": final, "complete": complete}
    if "samples" in keep:
        parts |= {"position": position, "velocity": velocity}
    if "events" in keep:
        parts["events"] = events
    if "solution" in keep:
        parts["solution"] = eqx.tree_at(lambda s: s.gravity, solution, None)
    return parts


def roll_states(seg: Segment, is_roll, tau, g):
    """Position and velocity ``tau`` after their start of segments ``seg`` that are rolls
    (``is_roll``; elementwise over a leading axis), from their start, axis and pivot
    (``estim.forward._roll``). Elsewhere a harmless roll stands in (no NaN in the cotangents
    of a branch not taken)."""
    spherical = is_roll & jnp.all(seg.normal == 0, axis=-1)  # (a roll over a corner off its plane: no axis)
    planar = (is_roll & ~spherical)[:, None]
    axis = jnp.where(planar, seg.normal, jnp.array([1.0, 0.0, 0.0]))
    p0 = jnp.where(planar, seg.p0, seg.pivot + jnp.array([0.0, 0.0, 1.0]))
    v0 = jnp.where(planar, seg.v0, jnp.array([0.0, 1.0, 0.0]))

    def one(spherical, pivot, axis, p0, v0, p0_s, v0_s, tau):
        p_s, v_s = spherical_stand_in(spherical, pivot, p0_s, v0_s, 1.0, g)
        return roll_state(spherical, Roll(pivot, axis, p0, v0, g), Spherical(pivot, p_s, v_s, g), tau)

    return jax.vmap(one)(spherical, seg.pivot, axis, p0, v0, seg.p0, seg.v0, tau)


def sample(seg: Segment, d: Decision, law: AbstractContactLaw, c, g, t, rolls: bool = False):
    """Position and velocity of one ball at times ``t`` from its segments, under the contact
    law ``law`` with the ball's coefficients ``c``. ``rolls`` (static): whether segments
    may be ``ROLL`` (a scene with edges and corners: ``estim.forward._contact.has_edges``)."""
    shape = jnp.shape(t)
    t = jnp.reshape(t, (-1,))
    starts = jnp.where(d.kind != UNUSED, seg.t0, jnp.inf)
    # searchsorted(starts, t, side="right") written as a count (starts are sorted): no
    # search loop, whose index tables XLA would compute in a kernel of every call.
    k = jnp.clip(jnp.sum(starts <= t[:, None], axis=1) - 1, 0, starts.shape[0] - 1)
    s = jax.tree.map(lambda x: x[k], seg)
    kind, n = d.kind[k], d.n[k]
    tau = t - s.t0
    p_bal = s.p0 + s.v0 * tau[:, None] + 0.5 * s.acc * tau[:, None] ** 2
    v_bal = s.v0 + s.acc * tau[:, None]

    a = jnp.array([0.0, 0.0, -1.0]) * g
    if rolls:
        is_roll = (kind == ROLL)[:, None]
        p_roll, v_roll = roll_states(s, kind == ROLL, tau, g)
        p_bal = jnp.where(is_roll, p_roll, p_bal)
        v_bal = jnp.where(is_roll, v_roll, v_bal)
    if not law.summable:  # (no trains)
        return p_bal.reshape(shape + (3,)), v_bal.reshape(shape + (3,))

    def in_train(v0, normal, tau, n):
        is_train = inner(v0, normal) > 0
        normal = jnp.where(is_train, normal, jnp.array([0.0, 0.0, 1.0]))
        s = series(jnp.where(is_train, v0, normal), normal, a)
        return law.state_at(s, tau, c, n)[:2]

    dp, v_tr = jax.vmap(in_train)(s.v0, s.normal, tau, n)
    is_train = (kind == TRAIN)[:, None]
    p = jnp.where(is_train, s.p0 + dp, p_bal)
    v = jnp.where(is_train, v_tr, v_bal)
    return p.reshape(shape + (3,)), v.reshape(shape + (3,))


def _listed(seg: Segment, d: Decision, law: AbstractContactLaw, c, g, max_events: int):
    """Events of each segment (elementwise: one segment or many): the bounces of a train
    that are listed, and the number of event slots the segment takes (capped, so that slots
    stay int32 indices; a count past max_events only marks the list truncated)."""
    is_train = d.kind == TRAIN
    contact = (d.reason == CONTACT) & (d.kind != UNUSED)
    if not law.summable:  # (no trains: a slot per contact)
        return jnp.zeros_like(d.n), jnp.minimum(jnp.where(contact, 1.0, 0.0), max_events + 1.0)
    a_n = jnp.where(is_train, seg.normal[..., 2], 1.0) * -g
    w = jnp.where(is_train, inner(seg.v0, seg.normal), 1.0)
    t_flight = 2.0 * w / -a_n
    # Bounces of a train: all n when it ran to bounce n; up to t_end when cut there ...
    before_end = law.bounces_within((seg.t1 - seg.t0) / t_flight, c)
    bounces = jnp.where(d.reason == BOUNCES, d.n, jnp.minimum(before_end, d.n))
    # ... and of a Zeno series only those whose flight lasts at least LISTED_FLIGHT.
    listable = law.flights_longer(t_flight, LISTED_FLIGHT, c)
    bounces = jnp.where(jnp.isfinite(d.n), bounces, jnp.minimum(bounces, listable))
    settles = is_train & (d.reason == SETTLE)
    total = jnp.where(contact, 1.0, jnp.where(is_train, bounces, 0.0) + settles)
    return bounces, jnp.minimum(total, max_events + 1.0)


def _slot_of(d: Decision, bounces, capped, ends, i):
    """Event slot i (float; elementwise): its segment k, its bounce number j in a train
    (from 1), whether it is a train's slot and whether it is the train's settling."""
    # searchsorted(ends, i, side="right") written as a count, as in `sample`
    k = jnp.clip(jnp.sum(ends <= jnp.expand_dims(i, -1), axis=-1), 0, ends.shape[0] - 1)
    local = i - (ends - capped)[k] + 1.0
    train_slot = d.kind[k] == TRAIN
    settle_slot = train_slot & (d.reason[k] == SETTLE) & (local > bounces[k])
    return k, jnp.where(train_slot & ~settle_slot, local, 1.0), train_slot, settle_slot


def _event_slots(seg: Segment, d: Decision, law: AbstractContactLaw, c, g, max_events: int):
    """Map event slots to segments: which segment, which bounce of a train."""
    bounces, capped = _listed(seg, d, law, c, g, max_events)
    ends = jnp.cumsum(capped)
    i = jnp.arange(max_events, dtype=jnp.float64)
    k, bounce_no, train_slot, settle_slot = _slot_of(d, bounces, capped, ends, i)
    return k, bounce_no, i < ends[-1], train_slot, settle_slot, ends[-1]


def _bounce(v0, normal, t0, p0, j, law, c, g):
    """Bounce j (from 1) of a train: time, position, velocity before and after, and the
    start (time, position, velocity) of the flight that ends at it."""
    is_train = inner(v0, normal) > 0
    normal = jnp.where(is_train, normal, jnp.array([0.0, 0.0, 1.0]))
    s = series(jnp.where(is_train, v0, normal), normal, jnp.array([0.0, 0.0, -1.0]) * g)
    t, x, pre, post, _, _, (t_s, x_s, v_s) = law.bounce(s, j, c)
    return t0 + t, p0 + x, pre, post, (t0 + t_s, p0 + x_s, v_s)


def _event(s: Segment, d: Decision, j, train_slot, settle_slot, valid, law, c, g):
    """One listed event (one slot): ``(t, position, pre, post, face, kind)``, padding where
    ``valid`` is false. ``s`` and ``d`` are its segment; ``j`` its bounce number in a train."""
    t, pos, pre, post = s.t1, s.p1, s.v1, s.v1_post
    if law.summable:  # (else there are no trains)
        bt, bp, bpre, bpost, _ = _bounce(s.v0, s.normal, s.t0, s.p0, j, law, c, g)
        plain = ~train_slot | settle_slot
        t = jnp.where(plain, t, bt)
        pos = jnp.where(plain, pos, bp)
        pre = jnp.where(plain, pre, bpre)
        post = jnp.where(plain, post, bpost)
    face = jnp.where(train_slot, d.support, d.face)
    # A contact without normal speed is a landing to rest, not an impact: an impact changes
    # the velocity by at least (1 + e) times the normal speed.
    kind = jnp.where(settle_slot | (jnp.linalg.norm(pre - post) <= REST_SPEED), REST, IMPACT)
    zero = jnp.zeros(3)
    return (
        jnp.where(valid, t, jnp.inf),
        jnp.where(valid, pos, zero),
        jnp.where(valid, pre, zero),
        jnp.where(valid, post, zero),
        jnp.where(valid, face, -1).astype(jnp.int32),
        jnp.where(valid, kind, -1).astype(jnp.int32),
    )


def list_events(seg: Segment, d: Decision, law: AbstractContactLaw, c, g, max_events: int) -> Events:
    """Expand the segments of one ball into its list of contact events (every slot at once:
    vectorises over slots, and over the balls of a batch under ``vmap``), under the
    contact law ``law`` with the ball's coefficients ``c``."""
    k, j, valid, train_slot, settle_slot, total = _event_slots(seg, d, law, c, g, max_events)
    s, dk = jax.tree.map(lambda x: x[k], (seg, d))
    event = jax.vmap(lambda *a: _event(*a, law, c, g))
    fields = event(s, dk, j, train_slot, settle_slot, valid)
    return Events(*fields, count=jnp.minimum(total, max_events).astype(jnp.int32), truncated=total > max_events)


def list_events_used(seg: Segment, d: Decision, law: AbstractContactLaw, c, g, max_events: int,
                     n_segments) -> Events:
    """``list_events`` slot by slot, doing the work of the used segments and the listed
    events only (a ``lax.scan`` whose unused items skip their work with ``lax.cond``).

    For a ball in a loop compiled as one kernel (``estim.forward._simulate``), where nothing is
    vectorised and every slot costs its closed forms: the seed's balls list 9, 6 and 4 of
    64 events. Under ``vmap`` the skips become selects and both branches run: there use
    ``list_events``. The same closed forms (``_listed``, ``_event``), so the same values (to
    rounding: compiled differently, multiply-adds may be fused differently).
    """
    n_seg = d.kind.shape[0]

    def count(_, k):
        one = jax.tree.map(lambda x: x[k], (seg, d))
        return None, jax.lax.cond(k < n_segments, lambda sd: _listed(*sd, law, c, g, max_events),
                                  lambda sd: none, one)

    none = (jnp.float64(0.0), jnp.float64(0.0))
    _, (bounces, capped) = scan_used(count, None, np.arange(n_seg), n_segments, lambda _: none, n_seg)
    ends = jnp.cumsum(capped)
    total = ends[-1]

    def listed(i):
        k, j, train_slot, settle_slot = _slot_of(d, bounces, capped, ends, i)
        s, dk = jax.tree.map(lambda x: x[k], (seg, d))
        return _event(s, dk, j, train_slot, settle_slot, True, law, c, g)

    def padding(i):
        zero, none = jnp.zeros(3), jnp.int32(-1)
        return jnp.full((), jnp.inf), zero, zero, zero, none, none

    def slot(_, i):
        i = i.astype(jnp.float64)
        return None, jax.lax.cond(i < total, listed, padding, i)

    _, fields = scan_used(slot, None, np.arange(max_events), total, lambda _: padding(0.0), max_events)
    return Events(*fields, count=jnp.minimum(total, max_events).astype(jnp.int32), truncated=total > max_events)


def event_flights(seg: Segment, d: Decision, law: AbstractContactLaw, c, g, max_events: int):
    """For every listed event, the start ``(t, position, velocity, acceleration)`` of the
    ballistic piece that ends at it, and whether the event is a crossing of a face (not a
    settle). Used by the implicit-function sensitivities of ``estim.event_sensitivities``."""
    k, j, valid, train_slot, settle_slot, _ = _event_slots(seg, d, law, c, g, max_events)
    s = jax.tree.map(lambda x: x[k], seg)
    if not law.summable:  # (no trains: every event ends the segment's own flight)
        return s.t0, s.p0, s.v0, s.acc, valid & ~settle_slot
    *_, (t_s, p_s, v_s) = jax.vmap(lambda *a: _bounce(*a, law, c, g))(s.v0, s.normal, s.t0, s.p0, j)
    in_train = train_slot & ~settle_slot
    t0 = jnp.where(in_train, t_s, s.t0)
    p0 = jnp.where(in_train[:, None], p_s, s.p0)
    v0 = jnp.where(in_train[:, None], v_s, s.v0)
    return t0, p0, v0, s.acc, valid & ~settle_slot
