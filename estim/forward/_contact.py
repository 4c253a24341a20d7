"""Contact math for a ball against the faces of a scene, in closed form.

Between contacts the ball centre moves on ``q(tau) = p + v tau + a tau^2 / 2`` (a parabola
in flight, a line or parabola while sliding on a face). For a face with unit outward normal
n and offset H, the guard

    G(tau) = n . q(tau) - H = G0 + G1 tau + G2 tau^2 / 2,
    G0 = n . p - H,   G1 = n . v,   G2 = n . a,                                (1)

is the signed distance of the centre from the face plane, minus nothing: H already contains
the radius (see ``estim.model._scene``). The ball *enters* a face at a root of G where G is
decreasing, ``G'(tau) = G1 + G2 tau < 0``. With ``s = sqrt(G1^2 - 2 G2 G0)`` the two roots
have ``G' = +-s``, so the entering one is

    tau = (-G1 - s) / G2 = 2 G0 / (s - G1),                                   (2)

the second form being free of cancellation when G1 < 0 and also covering G2 = 0. Its
derivatives are exactly the implicit-function event-time sensitivities,
``d tau = -(dG0 + tau dG1 + tau^2/2 dG2) / G'(tau)``, and stay finite while s > 0. A tangent
touch (s = 0, a grazing contact) is not an event: the ball does not cross the face.

What a contact does to the ball is the contact law's (``estim.forward.laws``); the
tolerances below are defined in ``estim.forward._constants``, shared with the native
kernels.
"""

from __future__ import annotations

import functools
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..model._scene import Scene
from ._constants import (
    ACCEL_TOL,
    AXIS_TOL,
    FACE_CENTRE,
    FACE_DIRECTION,
    FACE_HALF,
    FACE_NORMAL,
    FACE_OFFSET,
    FACE_ROW,
    FACE_SOLID,
    ON_FACE_TOL,
    POSITION_TOL,
    SPEED_TOL,
    TIE_TIME,
)


class Faces(eqx.Module):
    """Every contact face of a scene for one ball radius, packed for fast lookup.

    ``row`` holds one row per face: unit normal (3), plane offset H of the face itself (1),
    centre (3) and half sizes (3) of the owning box (infinite for a plane), face direction
    m (3), index of the owning solid (1). ``box_lo``/``box_hi`` are the corners of every
    solid's box (planes are boxes with infinite sides). The ball's radius r enters only
    through ``offset`` (the face plane moved out by r: H + r growth, growth = 1/|m|) and
    ``lo``/``hi`` (the boxes grown by r along each axis), so the table itself is shared by
    balls of any radius: a batch of balls needs one table, not one each.
    """

    row: Float[Array, "faces 14"]  # FACE_ROW columns
    growth: Float[Array, " faces"]
    rank: Int[Array, " faces"]
    lower: Int[Array, "faces 6"]  # faces of the same box that border this one, of lower rank (-1: none)
    box_lo: Float[Array, "solids 3"]
    box_hi: Float[Array, "solids 3"]
    radius: Float[Array, ""]

    @property
    def offset(self) -> Float[Array, " faces"]:
        """Plane offset of every face for the ball's centre: ``n . x = offset`` on contact."""
        return self.row[:, OFFSET] + self.radius * self.growth

    @property
    def lo(self) -> Float[Array, "solids 3"]:
        return self.box_lo - self.radius

    @property
    def hi(self) -> Float[Array, "solids 3"]:
        return self.box_hi + self.radius

    def normal_offset(self, face):
        """Unit normal and offset (for the ball's centre) of face ``face``."""
        return self.row[face, NORMAL], self.row[face, OFFSET] + self.radius * self.growth[face]


# The columns of a row (estim.forward._constants, shared with the native kernels).
NORMAL, OFFSET = slice(FACE_NORMAL, FACE_NORMAL + 3), FACE_OFFSET
CENTRE, HALF = slice(FACE_CENTRE, FACE_CENTRE + 3), slice(FACE_HALF, FACE_HALF + 3)
DIRECTION, SOLID = slice(FACE_DIRECTION, FACE_DIRECTION + 3), FACE_SOLID
assert FACE_SOLID + 1 == FACE_ROW  # (the row of faces_for below, column by column)


def faces_for(scene: Scene, radius: Float[Array, ""]) -> Faces:
    """The face table of ``scene`` for a ball of radius ``radius`` (differentiable in the
    geometry and the radius). Rank is 1 for box faces and planes, 2 for edge bevels, 3 for
    corner faces."""
    solid = np.asarray(scene.face_solid)
    m = np.asarray(scene.face_direction)
    is_box = solid < scene.n_boxes
    box = np.where(is_box, solid, 0)
    plane = np.where(is_box, 0, solid - scene.n_boxes)
    norm = np.linalg.norm(m, axis=1)
    if scene.n_boxes:
        c, h = scene.box_centre[box], scene.box_half[box]
    else:  # planes only
        c = h = jnp.zeros((len(solid), 3))
    offset = (jnp.sum(m * c, axis=1) + jnp.sum(np.abs(m) * h, axis=1)) / norm
    normal = jnp.asarray(m / norm[:, None])
    if scene.plane_offset.shape[0]:
        offset = jnp.where(is_box, offset, scene.plane_offset[plane])
        normal = jnp.where(is_box[:, None], normal, scene.plane_normal[plane])
    half = jnp.where(is_box[:, None], h, jnp.inf)
    centre = jnp.where(is_box[:, None], c, 0.0)
    row = jnp.concatenate(
        [normal, offset[:, None], centre, half, jnp.asarray(m), jnp.asarray(solid, float)[:, None]],
        axis=1,
    )
    # Solids as boxes (grown by r per axis in ``Faces.lo``/``hi``); a plane sigma x_k <= s
    # is x_k <= s (+ r) for sigma = 1 or x_k >= -s (- r) for sigma = -1, unbounded along
    # the other axes.
    pn, ps = scene.plane_normal, scene.plane_offset[:, None]
    box_lo = jnp.concatenate([scene.box_centre - scene.box_half, jnp.where(pn < 0, -ps, -jnp.inf)])
    box_hi = jnp.concatenate([scene.box_centre + scene.box_half, jnp.where(pn > 0, ps, jnp.inf)])
    rank = np.where(is_box, np.abs(m).sum(axis=1), 1).astype(np.int32)
    lower = _lower_faces(scene.face_solid, scene.face_direction, scene.n_boxes)
    return Faces(row=row, growth=jnp.asarray(np.where(is_box, 1.0 / norm, 1.0)), rank=jnp.asarray(rank),
                 lower=jnp.asarray(lower), box_lo=box_lo, box_hi=box_hi, radius=jnp.asarray(radius))


@functools.lru_cache(maxsize=64)
def _lower_faces(face_solid, face_direction, n_boxes) -> np.ndarray:
    """For each face of a box, the faces of the same box that border it and have lower
    rank: those whose direction keeps some of its nonzero components and zeroes the others
    (a bevel (1, 0, 1) borders (1, 0, 0) and (0, 0, 1); a corner borders 3 bevels and 3
    faces). Faces removed as unreachable are left out. ``(faces, 6)``, -1 for none."""
    solid, m = np.asarray(face_solid), np.asarray(face_direction, dtype=np.float64)
    index = {(int(b), tuple(d)): f for f, (b, d) in enumerate(zip(solid, m.tolist(), strict=True))}
    out = np.full((len(solid), 6), -1, dtype=np.int32)
    for f in np.flatnonzero(solid < n_boxes):
        nz = np.flatnonzero(m[f])
        found = []
        for k in range(1, len(nz)):
            for keep in itertools.combinations(nz, k):
                d = np.zeros(3)
                d[list(keep)] = m[f, list(keep)]
                g = index.get((int(solid[f]), tuple(d.tolist())))
                if g is not None:
                    found.append(g)
        out[f, : len(found)] = found
    return out


def moves_into(g1, g2):
    """Whether a ball touching a plane (G = 0) moves into it: its normal speed G1 is
    negative, or zero with a negative normal acceleration G2 (each to within its
    tolerance, so that rounding never makes a ball moving along a plane enter it)."""
    return (g1 < -SPEED_TOL) | ((jnp.abs(g1) <= SPEED_TOL) & (g2 < -ACCEL_TOL))


@jax.jit  # traced once per signature, not at each call (estim._config, TRACING)
def entering_time(
    g0: Float[Array, "*f"], g1: Float[Array, "*f"], g2: Float[Array, "*f"]
) -> Float[Array, "*f"]:
    """First time tau >= 0 at which ``G0 + G1 tau + G2 tau^2/2`` enters ``G <= 0``.

    Returns 0 when the ball already touches the face and moves (or is pushed) into it, and
    ``inf`` when it never enters. Uses equation (2) of the module docstring.
    """
    touching = jnp.abs(g0) <= POSITION_TOL
    pushed = moves_into(g1, g2)
    # A ball touching the plane with no normal speed nor acceleration (to rounding) moves
    # along it: G is zero exactly, and a root of its rounded coefficients (g0 ~ 1e-16 over
    # g2 ~ -1e-15 puts one ~1 s ahead) is no contact.
    along = touching & (jnp.abs(g1) <= SPEED_TOL) & (jnp.abs(g2) <= ACCEL_TOL)
    disc = g1 * g1 - 2.0 * g2 * g0
    has_root = disc > 0
    s = jnp.sqrt(jnp.where(has_root, disc, 1.0))
    # Double where: the unused branch must not produce inf/nan that poisons gradients.
    neg = g1 < 0
    den_a = jnp.where(neg, s - g1, 1.0)
    den_b = jnp.where(neg | (g2 == 0), -1.0, g2)
    tau = jnp.where(neg, 2.0 * g0 / den_a, (-g1 - s) / den_b)
    future = has_root & (tau > 0) & (neg | (g2 < 0))
    return jnp.where(touching & pushed, 0.0, jnp.where(future & ~along, tau, jnp.inf))


def inner(x: Float[Array, "*n 3"], y: Float[Array, "*n 3"]) -> Float[Array, "*n"]:
    """``x . y`` over the last axis of 3, written out: XLA:CPU compiles a ``dot`` as a call
    into a linear-algebra library, and one such call in an event loop keeps the whole loop
    from being compiled into a single kernel (``estim._config``)."""
    return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2]


def ballistic(p, v, a, tau):
    """Position and velocity after time ``tau`` under constant acceleration ``a``."""
    return p + v * tau + 0.5 * a * tau * tau, v + a * tau


def on_face(q, centre, half, radius) -> Bool[Array, "*f"]:
    """Whether a point on a face's plane lies on the face: inside the grown box, eq. (1)
    of ``estim.model._scene``, to within ``ON_FACE_TOL``."""
    excess = jnp.maximum(jnp.abs(q - centre) - half, 0.0)
    return jnp.sum(excess, axis=-1) <= radius + ON_FACE_TOL


def first_contact(
    faces: Faces,
    p: Float[Array, "3"],
    v: Float[Array, "3"],
    a: Float[Array, "3"],
    exclude: Int[Array, ""],
    also: Int[Array, ""] | int = -1,
) -> tuple[Float[Array, ""], Int[Array, ""]]:
    """Earliest face the ball enters, and when: ``(tau, face)``, ``(inf, -1)`` if none.

    ``exclude`` is a face the ball is sliding on (or -1), ``also`` a second one (a wall it
    slides along, or -1). Faces reached at the same instant
    (to ``TIE_TIME``, 1e-12 s) are resolved in favour of box faces over bevels over corners, so a ball
    landing exactly on a tread edge lands on the tread.

    At an edge of a solid's contact region (where a face meets a face of lower rank, e.g. a
    bevel meets the tread top) the ball enters the solid only if it enters the lower-rank
    face too: a ball that touches the tread top there but leaves it (a rebound from the
    edge point) or moves along it (a slide on the top) is not stopped by the bevel.
    """
    normal, offset = faces.row[:, NORMAL], faces.offset
    centre, half = faces.row[:, CENTRE], faces.row[:, HALF]
    tau = entering_time(inner(normal, p) - offset, inner(normal, v), inner(normal, a))
    finite = jnp.isfinite(tau)
    # on_face at the entering points, one axis at a time: (faces, 3) arrays reduced over
    # their axis of 3 do not vectorise on the CPU, and this test over every face was most
    # of the cost of a segment in large batches (0.9 instead of 1.8 us per ball).
    at = jnp.where(finite, tau, 0.0)
    excess = sum(
        jnp.maximum(jnp.abs(p[i] + v[i] * at + 0.5 * a[i] * at * at - centre[:, i]) - half[:, i], 0.0)
        for i in range(3)
    )
    ok = finite & (excess <= faces.radius + ON_FACE_TOL)
    ok = ok & (jnp.arange(tau.shape[0]) != exclude) & (jnp.arange(tau.shape[0]) != also)
    tau = jnp.where(ok, tau, jnp.inf)

    n_faces = tau.shape[0]
    # Ties broken by rank, then by index, with one integer min (an argmin is a two-operand
    # reduction, slower on the CPU).
    order = faces.rank * n_faces + jnp.arange(n_faces, dtype=faces.rank.dtype)

    def earliest(tau):
        t_min = jnp.min(tau)
        near = tau <= t_min + TIE_TIME
        return t_min, (jnp.min(jnp.where(near, order, 4 * n_faces)) % n_faces).astype(jnp.int32)

    def blocked(face, t):
        """The ball touches a lower-rank face bordering ``face`` at its contact point
        without entering it."""
        lower = faces.lower[face]
        nj = normal[jnp.maximum(lower, 0)]
        qf, wf = ballistic(p, v, a, jnp.where(jnp.isfinite(t), t, 0.0))
        gj0 = inner(nj, qf) - offset[jnp.maximum(lower, 0)]
        gj1, gj2 = inner(nj, wf), inner(nj, a)
        touches = (lower >= 0) & (jnp.abs(gj0) <= POSITION_TOL)
        # A ball at the apex of a graze leaves the face by no more than gj1^2 / (2 |gj2|)
        # before falling into it: within POSITION_TOL that is entering it, not leaving
        # (a flight whose apex touched a tread top 1e-12 m inside its edge, rising at
        # 1e-11 m/s there, had its bevel contact dropped and flew through the tread).
        grazes = (gj2 < -ACCEL_TOL) & (gj1 * gj1 <= -2.0 * gj2 * POSITION_TOL)
        enters = moves_into(gj1, gj2) | grazes
        return jnp.isfinite(t) & jnp.any(touches & ~enters)

    # A blocked candidate is dropped and the next earliest taken: at a corner of a box at
    # most three (two bevels and the corner face) can be blocked at once. (A loop, not
    # three unrolled copies: the event loop compiles as one kernel, 0.7 s faster so; and one
    # that stops at the first candidate not blocked, which for one ball is the first.)
    def is_blocked(c):
        rounds, tau, t_min, face = c
        return (rounds < 3) & blocked(face, t_min)

    def drop(c):
        rounds, tau, t_min, face = c
        tau = jnp.where(jnp.arange(tau.shape[0]) == face, jnp.inf, tau)
        return (rounds + 1, tau) + earliest(tau)

    _, _, t_min, face = jax.lax.while_loop(is_blocked, drop, (jnp.int32(0), tau) + earliest(tau))
    return t_min, jnp.where(jnp.isfinite(t_min), face, -1)


def face_normal(faces: Faces, face):
    """Unit outward normal of face ``face``."""
    return faces.row[face, NORMAL]


def face_entering_time(faces: Faces, face, p, v, a):
    """``entering_time`` for one face, recomputed from the state (differentiable)."""
    n, h = faces.normal_offset(face)
    return entering_time(inner(n, p) - h, inner(n, v), inner(n, a))


def slide_exit_time(faces: Faces, face, p, v, a):
    """Time at which a ball sliding on box face ``face`` leaves it (inf on a plane).

    The face of direction m is the set of grown-box points with ``s_i (q_i - c_i) >= h_i``
    where ``m_i = s_i != 0`` and ``|q_i - c_i| <= h_i`` elsewhere; each bound is a guard of
    the form (1), so the exit time is the earliest ``entering_time`` among them.
    """
    r = faces.row[face]
    m, c, h = r[DIRECTION], r[CENTRE], r[HALF]
    q = p - c
    # Two bounds per axis, phi = sign * q + bound >= 0: the low side (q_i >= -h_i, or
    # -q_i >= h_i on a face pointing to -i) and the high side (q_i <= h_i, or q_i >= h_i).
    sign_lo = jnp.where(m < 0, -1.0, 1.0)
    bound_lo = jnp.where(m < 0, -h, h)
    sign_hi = jnp.where(m > 0, 1.0, -1.0)
    bound_hi = jnp.where(m > 0, -h, h)
    finite = jnp.isfinite(h)
    t_lo = entering_time(sign_lo * q + jnp.where(finite, bound_lo, 1.0), sign_lo * v, sign_lo * a)
    t_hi = entering_time(sign_hi * q + jnp.where(finite, bound_hi, 1.0), sign_hi * v, sign_hi * a)
    t_lo = jnp.where(finite & (m <= 0), t_lo, jnp.inf)
    t_hi = jnp.where(finite & (m >= 0), t_hi, jnp.inf)
    return jnp.minimum(jnp.min(t_lo), jnp.min(t_hi))


def train_reach(faces: Faces, face, p, u, height):
    """How far (m) a bounce series on an upward face may travel along ``u`` undisturbed.

    The flights of a series on one horizontal face all stay in the slab
    ``zeta <= z <= zeta + height`` (zeta the centre height on the face, height the first
    apex) above the segment from p along u. Returns the distance to the first place where
    that slab meets another solid's box grown by r in every axis (a superset of the solid's
    contact region, so the bound is conservative), or where the face ends; ``-1`` when the
    slab is blocked from the start. Only the interior of a grown box blocks: the contact
    region lies inside it, so a series that merely touches its boundary (a ball bouncing in
    place against a riser, or away from it) never enters the solid.
    """
    r = faces.row[face]
    solid = r[SOLID]
    lo, hi = faces.lo, faces.hi
    inf = jnp.inf
    zeta = p[2]
    overlap = (lo[:, 2] < zeta + height - POSITION_TOL) & (hi[:, 2] > zeta + POSITION_TOL)
    speed = jnp.sqrt(u[0] ** 2 + u[1] ** 2)
    moving = speed > 0
    d = jnp.where(moving, u[:2] / jnp.where(moving, speed, 1.0), 0.0)
    # 2-D slab test of the ray p + d s, s >= 0, against every rectangle. A component of d
    # below AXIS_TOL (1e-12) counts as zero: over the metres a series travels it moves the
    # ball less than ON_FACE_TOL, and a ball released touching a riser with vx = -5e-189
    # (found by tests/test_properties.py) had the riser's box "entered" at s = 0, which cut
    # its bounce series into 48 single flights.
    dz = jnp.abs(d) > AXIS_TOL
    dd = jnp.where(dz, d, 1.0)
    t1 = (lo[:, :2] - p[:2]) / dd
    t2 = (hi[:, :2] - p[:2]) / dd
    inside = (p[:2] > lo[:, :2] + POSITION_TOL) & (p[:2] < hi[:, :2] - POSITION_TOL)
    s_in = jnp.where(dz, jnp.minimum(t1, t2), jnp.where(inside, -inf, inf))
    s_out = jnp.where(dz, jnp.maximum(t1, t2), jnp.where(inside, inf, -inf))
    enter = jnp.maximum(jnp.max(s_in, axis=1), 0.0)
    leave = jnp.min(s_out, axis=1)
    hit = overlap & (enter < leave - POSITION_TOL) & (jnp.arange(lo.shape[0]) != solid)
    obstacle = jnp.min(jnp.where(hit, enter, inf))
    # Where the face itself ends (box top faces; planes, with infinite half sizes, never end).
    c, h = r[CENTRE][:2], r[HALF][:2]
    edge = jnp.where(d > 0, c + h, c - h)
    to_edge = jnp.where(dz & jnp.isfinite(h), (edge - p[:2]) / dd, inf)
    exit_face = jnp.where(moving, jnp.min(to_edge), inf)
    reach = jnp.minimum(obstacle, exit_face)
    return jnp.where(obstacle <= POSITION_TOL, -1.0, jnp.maximum(reach, 0.0))


def series_clear(faces: Faces, face, p, v, duration, gravity):
    """Whether a bounce series on face ``face`` that starts at p with velocity v and lasts
    ``duration`` provably meets no other solid: every point of it lies within
    ``D = |v| T + g T^2 / 2`` of p (T the duration), so the cube of half-side D around p
    must not meet another solid's box grown by r. Conservative; for a series on an inclined
    face (an edge bevel), where the slab test of ``train_reach`` does not apply."""
    d = jnp.sqrt(jnp.sum(v * v)) * duration + 0.5 * gravity * duration**2
    meets = jnp.all(p - d < faces.hi, axis=1) & jnp.all(p + d > faces.lo, axis=1)
    return ~jnp.any(meets & (jnp.arange(faces.lo.shape[0]) != faces.row[face, SOLID]))


def sweep_clear(faces: Faces, p, v, a, h, margin):
    """Whether a ball whose centre stays within ``margin`` of the parabola
    ``p + v tau + a tau^2 / 2`` over ``0 <= tau <= h`` provably touches no solid then.

    The parabola lies in its bounding box (per axis: the end points and the apex where it
    falls inside the step); every point of the ball's contact region with a solid lies in
    that solid's box grown by r along each axis (``Faces.lo``/``hi``: the region's L1 excess
    is at most r). So if the box of the parabola, grown by ``margin``, meets no grown box,
    no contact is possible within the step. Conservative: a ball that touches a solid (just
    bounced off it, or lands within the step) is never clear."""
    p1, _ = ballistic(p, v, a, h)
    apex = jnp.where(a != 0, -v / jnp.where(a != 0, a, 1.0), 0.0)
    inside = (apex > 0) & (apex < h)
    q_apex, _ = ballistic(p, v, a, jnp.where(inside, apex, 0.0))
    lo = jnp.minimum(jnp.minimum(p, p1), jnp.where(inside, q_apex, p)) - margin
    hi = jnp.maximum(jnp.maximum(p, p1), jnp.where(inside, q_apex, p)) + margin
    meets = jnp.all(lo < faces.hi, axis=1) & jnp.all(hi > faces.lo, axis=1)
    return ~jnp.any(meets)


def clear_time(faces: Faces, p, v, a, h, margin, iterations: int = 12):
    """The longest ``tau <= h`` (to ``h / 2^iterations``) for which ``sweep_clear`` holds,
    by bisection: the test is monotone in the step length (a shorter parabola has a
    smaller box). 0 if none."""

    def halve(_, bracket):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        ok = sweep_clear(faces, p, v, a, mid, margin)
        return jnp.where(ok, mid, lo), jnp.where(ok, hi, mid)

    lo, _ = jax.lax.fori_loop(0, iterations, halve, (0.0 * h, h))
    return lo
