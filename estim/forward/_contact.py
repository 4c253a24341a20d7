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
touch (s = 0, a grazing contact) is not an event where the ball curves away from the face
(G2 >= 0); pressed towards it (G2 < 0), a flight whose apex touches the plane enters it
right after, and the apex is its contact (s = 0, to ``POSITION_TOL``).

What a contact does to the ball is the contact law's (``estim.forward.laws``); the
tolerances below are defined in ``estim.forward._constants``, shared with the native
kernels.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._fold import inner
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
    FAR_HORIZON,
    HOP_HEIGHT,
    ON_FACE_TOL,
    POSITION_TOL,
    SPEED_TOL,
    TIE_TIME,
    WINDOW_MARGIN,
)
from ._curved import distance_terms, entering_times, implicit_time, piece_normal


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
    box_lo: Float[Array, "solids 3"]
    box_hi: Float[Array, "solids 3"]
    radius: Float[Array, ""]
    n_flat: int = eqx.field(static=True, default=0)  # faces [0, n_flat) are flat, the rest edges and corners

    @property
    def curved(self) -> bool:
        """Whether the table has edges and corners (exact geometry)."""
        return self.n_flat < self.rank.shape[0]

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
    geometry and the radius). Rank is 1 for flat faces (box faces and planes), 2 for edges
    and 3 for corners (curved: their normal and offset columns are not used, their contact
    surface is ``piece_frame``'s, ``estim.forward._curved``)."""
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
    return Faces(row=row, growth=jnp.asarray(np.where(is_box, 1.0 / norm, 1.0)), rank=jnp.asarray(rank),
                 box_lo=box_lo, box_hi=box_hi, radius=jnp.asarray(radius),
                 n_flat=int(np.sum(rank == 1)))


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
    # Pressed towards the plane (g2 < 0), a flight whose apex reaches it to within
    # POSITION_TOL touches it there (disc = 2 |g2| G_max rounds to <= 0: the apex of a
    # flight over a tread's top, rising from beyond its edge, was no root and the ball
    # flew through the tread) and then enters it: a root at the apex, s = 0.
    positive = disc > 0
    has_root = positive | ((g2 < -ACCEL_TOL) & (disc >= 2.0 * g2 * POSITION_TOL))
    s = jnp.where(positive, jnp.sqrt(jnp.where(positive, disc, 1.0)), 0.0)
    # Double where: the unused branch must not produce inf/nan that poisons gradients.
    neg = g1 < 0
    den_a = jnp.where(neg, s - g1, 1.0)
    den_b = jnp.where(neg | (g2 == 0), -1.0, g2)
    tau = jnp.where(neg, 2.0 * g0 / den_a, (-g1 - s) / den_b)
    future = has_root & (tau > 0) & (neg | (g2 < 0))
    # A ball touching the plane and leaving it slower than rounding resolves (a hop of
    # 1e-17 m off a tread, with g0 = -2e-16 there is no real root) is back after
    # -2 g1 / g2: without this it fell through the tread.
    hop = touching & ~future & (g1 > SPEED_TOL) & (g2 < 0)
    back = -2.0 * g1 / jnp.where(g2 < 0, g2, -1.0)
    return jnp.where(touching & pushed, 0.0, jnp.where(future & ~along, tau, jnp.where(hop, back, jnp.inf)))


def ballistic(p, v, a, tau):
    """Position and velocity after time ``tau`` under constant acceleration ``a``."""
    return p + v * tau + 0.5 * a * tau * tau, v + a * tau


def on_face(q, centre, half, radius) -> Bool[Array, "*f"]:
    """Whether a point on a face's plane lies on the face: inside the grown box, eq. (1)
    of ``estim.model._scene``, to within ``ON_FACE_TOL``."""
    excess = jnp.maximum(jnp.abs(q - centre) - half, 0.0)
    return jnp.sum(excess, axis=-1) <= radius + ON_FACE_TOL


def piece_frame(faces: Faces):
    """Anchor (edge or vertex point) and axis mask of every face as a curved piece
    (``estim.forward._curved``; meaningful for edges and corners only)."""
    return _frame_of(faces.row)


def piece_at(faces: Faces, face):
    """``piece_frame`` of one face: its anchor and axis mask."""
    return _frame_of(faces.row[face])


def _frame_of(row):
    m, half = row[..., DIRECTION], row[..., HALF]
    return row[..., CENTRE] + m * jnp.where(jnp.isfinite(half), half, 0.0), jnp.abs(m)


def in_piece(q, row) -> Bool[Array, "*f"]:
    """Whether the centre q lies in the Voronoi region of box piece ``row`` (to
    ``ON_FACE_TOL``): beyond the box along its direction's axes, within it along the others."""
    m, c, h = row[..., DIRECTION], row[..., CENTRE], row[..., HALF]
    d = q - c
    beyond = jnp.where(m != 0, m * d - h >= -ON_FACE_TOL, True)
    within = jnp.where(m == 0, jnp.abs(d) - h <= ON_FACE_TOL, True)
    return jnp.all(beyond & within, axis=-1)


def _touching_terms(A, B, C, r):
    """G = |P| - r and its first two derivatives at tau = 0 (``estim.forward._curved``)."""
    rho = jnp.sqrt(inner(A, A))
    rho_s = jnp.where(rho > 0, rho, 1.0)
    g1 = inner(A, B) / rho_s
    g2 = (inner(B, B) + 2.0 * inner(A, C)) / rho_s - g1 * g1 / rho_s
    return rho - r, g1, g2


def _curved_time(faces: Faces, anchor, mask, row, p, v, a, start, horizon):
    """Earliest time the ball enters each curved piece within ``[start, horizon]``, inside
    the piece's region; 0 if it touches the piece and moves into it; ``inf`` if never.
    Values only."""
    A, B, C = distance_terms(p, v, a, anchor, mask)
    r = jnp.broadcast_to(faces.radius, A.shape[:-1])
    g0, g1, g2 = _touching_terms(A, B, C, r)
    touching = jnp.abs(g0) <= POSITION_TOL
    now = touching & moves_into(g1, g2)
    roots = entering_times(A, B, C, r, jnp.broadcast_to(start, r.shape), jnp.broadcast_to(horizon, r.shape))
    # A hop off the surface lower than HOP_HEIGHT is below what D resolves (D ~ 2 r G
    # rounds at ~r^2 1e-16: a 1e-17 m hop on an edge read as never leaving it, and the ball
    # fell through the tread); its landing is the root of G's own quadratic model
    # g1 tau + g2 tau^2 / 2, exact to O(tau^3) over a hop that short.
    low = touching & (g1 > 0) & (g2 < 0) & (g1 * g1 <= -2.0 * g2 * HOP_HEIGHT)
    hop = jnp.where(low, -2.0 * g1 / jnp.where(low, g2, -1.0), jnp.inf)
    roots = jnp.concatenate([jnp.where(low, hop, jnp.inf)[..., None], roots], axis=-1)
    at = jnp.where(jnp.isfinite(roots), roots, 0.0)[..., None]
    q = p[..., None, :] + v[..., None, :] * at + 0.5 * a[..., None, :] * at * at
    valid = jnp.isfinite(roots) & in_piece(q, row[..., None, :])
    return jnp.where(now, 0.0, jnp.min(jnp.where(valid, roots, jnp.inf), axis=-1))


def parabola_box(p, v, a, h):
    """The bounding box ``(lo, hi)`` of the parabola ``p + v tau + a tau^2 / 2`` over
    ``0 <= tau <= h``: per axis, its end points and its apex where that falls inside."""
    p1, _ = ballistic(p, v, a, h)
    apex = jnp.where(a != 0, -v / jnp.where(a != 0, a, 1.0), 0.0)
    inside = (apex > 0) & (apex < h)
    q_apex, _ = ballistic(p, v, a, jnp.where(inside, apex, 0.0))
    return (jnp.minimum(jnp.minimum(p, p1), jnp.where(inside, q_apex, p)),
            jnp.maximum(jnp.maximum(p, p1), jnp.where(inside, q_apex, p)))


def _reach_box(faces: Faces):
    """Each piece's box of reach: for an edge or a corner, the box beyond the solid's box by
    at most r along its direction's axes (a superset of the piece), grown by
    ``POSITION_TOL``: ``(lo, hi)``."""
    row = faces.row
    m, c, half = row[:, DIRECTION], row[:, CENTRE], row[:, HALF]
    r = faces.radius
    lo = jnp.where(m > 0, c + half, jnp.where(m < 0, c - half - r, c - half)) - POSITION_TOL
    hi = jnp.where(m > 0, c + half + r, jnp.where(m < 0, c - half, c + half)) + POSITION_TOL
    return lo, hi


def _reaches(faces: Faces, p, v, a, horizon):
    """Whether the bounding box of the parabola over [0, horizon] meets each piece's box of
    reach (a cheap screen, before ``_reach_window``)."""
    lo, hi = parabola_box(p, v, a, jnp.minimum(horizon, FAR_HORIZON))
    b_lo, b_hi = _reach_box(faces)
    return jnp.all((lo <= b_hi) & (hi >= b_lo), axis=1)


def _axis_window(p, v, a, lo, hi, horizon):
    """Per axis, the hull ``(t0, t1)`` of the times in ``[0, horizon]`` at which
    ``p + v t + a t^2 / 2`` lies in ``[lo, hi]`` (``t0 > t1``: never): its ends are among
    0, the horizon and the times it crosses lo or hi."""
    h = jnp.minimum(horizon, FAR_HORIZON)

    def crossings(c):
        # (a/2) t^2 + v t + (p - c) = 0, both roots without cancellation (Numerical Recipes 5.6).
        a2, c0 = 0.5 * a, p - c
        disc = v * v - 4.0 * a2 * c0
        s = jnp.sqrt(jnp.where(disc >= 0, disc, 0.0))
        q = -0.5 * (v + jnp.where(v >= 0, s, -s))
        ok = disc >= 0
        r1 = jnp.where(ok & (a2 != 0), q / jnp.where(a2 != 0, a2, 1.0), jnp.nan)
        r2 = jnp.where(ok & (q != 0), c0 / jnp.where(q != 0, q, 1.0), jnp.nan)
        return r1, r2

    cands = jnp.stack([jnp.zeros_like(lo), jnp.broadcast_to(h, lo.shape), *crossings(lo), *crossings(hi)], axis=-1)
    t = jnp.where(jnp.isfinite(cands), cands, -1.0)
    q = p[..., None] + v[..., None] * t + 0.5 * a[..., None] * t * t
    # The crossings are on the bounds up to rounding: a relative margin keeps them.
    margin = WINDOW_MARGIN * (1.0 + jnp.abs(lo) + jnp.abs(hi))[..., None]
    valid = (t >= 0) & (t <= h) & (q >= lo[..., None] - margin) & (q <= hi[..., None] + margin)
    return (jnp.min(jnp.where(valid, t, jnp.inf), axis=-1), jnp.max(jnp.where(valid, t, -jnp.inf), axis=-1))


def _reach_window(faces: Faces, p, v, a, horizon):
    """For each face, the time window within ``[0, horizon]`` in which the parabola can be in
    its box of reach (for an edge or a corner: the box beyond the solid's box by at most r
    along its direction's axes, a superset of the piece): ``(t0, t1)``, empty if
    ``t0 > t1``. A screen: only pieces with a window need their quartic, and only within it."""
    b_lo, b_hi = _reach_box(faces)
    # The hull over x and y (one interval each along a flight in vacuum, where x and y are
    # linear in time), then whether z, over that interval, comes into the box's z range:
    # exact where x and y are linear (a flight leaving a tread meets its edge's box in x
    # only long after it has risen above it in z), a superset elsewhere.
    t0, t1 = _axis_window(p[:2], v[:2], a[:2], b_lo[:, :2], b_hi[:, :2], horizon)
    t0, t1 = jnp.maximum(jnp.max(t0, axis=1), 0.0), jnp.min(t1, axis=1)
    z0 = p[2] + v[2] * t0 + 0.5 * a[2] * t0 * t0
    z1 = p[2] + v[2] * t1 + 0.5 * a[2] * t1 * t1
    apex = jnp.where(a[2] != 0, -v[2] / jnp.where(a[2] != 0, a[2], 1.0), -1.0)
    at_apex = (apex > t0) & (apex < t1)
    za = jnp.where(at_apex, p[2] + v[2] * apex + 0.5 * a[2] * apex * apex, z0)
    z_lo, z_hi = jnp.minimum(jnp.minimum(z0, z1), za), jnp.maximum(jnp.maximum(z0, z1), za)
    meets = (t0 <= t1) & (z_lo <= b_hi[:, 2]) & (z_hi >= b_lo[:, 2])
    return jnp.where(meets, t0, jnp.inf), jnp.where(meets, t1, -jnp.inf)


# Edges and corners searched together; a flight near more of them at once (near a corner)
# searches them in turns of this many.
NEAR_PIECES = 4


def first_contact(
    faces: Faces,
    p: Float[Array, "3"],
    v: Float[Array, "3"],
    a: Float[Array, "3"],
    exclude: Int[Array, ""],
    also: Int[Array, ""] | int = -1,
    sliding: Bool[Array, ""] | bool = False,
    leaving: bool = False,
) -> tuple[Float[Array, ""], Int[Array, ""]]:
    """Earliest face the ball enters, and when: ``(tau, face)``, ``(inf, -1)`` if none.

    ``exclude`` is a face the ball is sliding on (or -1), ``also`` a second one (a wall it
    slides along, or -1). ``sliding``: the ball slides on ``exclude``, so it meets none of
    that face's own edges and corners (on the face's plane it only touches them, where it
    slides off the face: its exit, not a contact; a contact there, at a root of a tangent
    quartic that rounding puts a few nm early, was an impact of 3e-9 m/s). Faces reached at
    the same instant (to ``TIE_TIME``, 1e-12 s) are resolved in favour of faces over edges
    over corners, so a ball landing exactly where a tread's top meets its edge lands on the
    top (the two have the same normal there).

    ``leaving`` (the ODE path, where the air may press a ball into a face it does not fall
    onto): a ball that already touches a wall (a flat face that gravity does not press
    into: vertical, or facing down) and is pressed into it (``tau = 0``) at an end of the
    wall, moving (or pushed) out past that end, leaves it, and does not meet it. Where a
    tread and the riser across it end together, a ball the wind slid along both was
    otherwise met again by the riser at the instant it left the tread, slid on it, met the
    tread, and so on at that one instant forever. (A face gravity presses into keeps the
    seed's rule: a ball released at a tread's edge, moving off it, touches it first.)

    Flat faces first, in closed form (equation (2)); then the edges and corners whose box
    of reach the flight meets before that contact (``_reaches``), each by its quartic
    (``estim.forward._curved``), ``NEAR_PIECES`` at a time, in a loop that flights far from
    every edge skip.
    """
    k = faces.n_flat
    row = faces.row[:k]
    normal, offset = row[:, NORMAL], faces.offset[:k]
    centre, half = row[:, CENTRE], row[:, HALF]
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
    index = jnp.arange(faces.rank.shape[0])
    ok = finite & (excess <= faces.radius + ON_FACE_TOL) & (index[:k] != exclude) & (index[:k] != also)
    if leaving:
        m = row[:, DIRECTION]
        out = jnp.zeros(k, bool)
        for i in range(3):  # (along the face: its own axis is the plane's)
            rel = p[i] - centre[:, i]
            side = jnp.where(rel >= 0, 1.0, -1.0)
            outward = (side * v[i] > SPEED_TOL) | ((jnp.abs(v[i]) <= SPEED_TOL) & (side * a[i] > ACCEL_TOL))
            out = out | ((m[:, i] == 0) & (jnp.abs(rel) - half[:, i] >= -ON_FACE_TOL) & outward)
        ok = ok & ~((tau <= 0) & out & (normal[:, 2] <= AXIS_TOL))
    tau = jnp.where(ok, tau, jnp.inf)
    if faces.curved:
        pieces = eqx.tree_at(lambda f: (f.row, f.rank), faces, (faces.row[k:], faces.rank[k:]))
        horizon = jnp.min(tau)
        # A cheap screen first (the flight's bounding box against each piece's box of
        # reach), then the exact window of the few it leaves, then their quartics.
        own = faces.row[jnp.maximum(exclude, 0)]
        borders = (jnp.sum(pieces.row[:, DIRECTION] * own[DIRECTION], axis=1) == 1) & (pieces.row[:, SOLID] == own[SOLID])
        near = _reaches(pieces, p, v, a, horizon) & (index[k:] != exclude) & (index[k:] != also)
        near = near & ~(sliding & (exclude >= 0) & borders)

        def search(rows, t0, t1):
            anchor, mask = piece_frame(eqx.tree_at(lambda f: f.row, pieces, rows))
            return _curved_time(faces, anchor, mask, rows, p, v, a, jnp.maximum(t0, 0.0), t1)

        rank = jnp.cumsum(near) - 1
        n = near.shape[0]

        def chunk(j, found):
            """The near pieces of ranks ``j NEAR_PIECES ...``, gathered, searched, and
            their times put back in place."""
            # (The j-th near piece by an integer min, and back by a compare: a nonzero or a
            # scatter would be a library call in the event loop, estim._config.)
            pick = jnp.stack([jnp.min(jnp.where(near & (rank == j * NEAR_PIECES + i), jnp.arange(n), n))
                              for i in range(NEAR_PIECES)])
            real = pick < n
            pick = jnp.minimum(pick, n - 1)
            rows = pieces.row[pick]
            t0, t1 = _reach_window(eqx.tree_at(lambda f: f.row, pieces, rows), p, v, a, horizon)
            ok = real & near[pick] & (t0 <= t1)
            got = jax.lax.cond(jnp.any(ok), lambda: search(rows, t0, jnp.where(ok, t1, 0.0)),
                               lambda: jnp.full(ok.shape, jnp.inf))
            got = jnp.where(ok, got, jnp.inf)
            return jnp.minimum(found, jnp.min(jnp.where(pick[:, None] == jnp.arange(n), got[:, None], jnp.inf), axis=0))

        # NEAR_PIECES at a time: one copy of the quartic search in the program, however
        # many pieces a flight nears (near a corner, more than NEAR_PIECES).
        chunks = (jnp.sum(near) + NEAR_PIECES - 1) // NEAR_PIECES
        tau = jnp.concatenate([tau, jax.lax.fori_loop(0, chunks, chunk, jnp.full(n, jnp.inf))])

    n_faces = tau.shape[0]
    # Ties broken by rank, then by index, with one integer min (an argmin is a two-operand
    # reduction, slower on the CPU).
    order = faces.rank * n_faces + jnp.arange(n_faces, dtype=faces.rank.dtype)
    t_min = jnp.min(tau)
    near = tau <= t_min + TIE_TIME
    face = (jnp.min(jnp.where(near, order, 4 * n_faces)) % n_faces).astype(jnp.int32)
    return t_min, jnp.where(jnp.isfinite(t_min), face, -1)


def face_normal(faces: Faces, face):
    """Unit outward normal of flat face ``face`` (of a curved one: see ``contact_normal``)."""
    return faces.row[face, NORMAL]


def has_edges(scene: Scene) -> bool:
    """Whether a scene's boxes have edges and corners (exact geometry): whether a ball may
    roll over them (static)."""
    return scene.geometry == "exact" and scene.n_boxes > 0


def is_curved(faces: Faces, face) -> Bool[Array, ""]:
    """Whether face ``face`` is an edge or a corner (a curved piece)."""
    return faces.rank[face] >= 2


def is_corner(faces: Faces, face) -> Bool[Array, ""]:
    """Whether face ``face`` is a corner."""
    return faces.rank[face] == 3


def contact_normal(faces: Faces, face, q):
    """Unit outward normal of face ``face`` at the centre q: the face's own on a flat face,
    from the edge or vertex to q on a curved piece (``estim.model._scene``)."""
    flat = faces.row[face, NORMAL]
    if not faces.curved:
        return flat
    anchor, mask = piece_at(faces, face)
    return jnp.where(is_curved(faces, face), piece_normal(q, anchor, mask), flat)


def across_speed2(faces: Faces, face, v, n):
    """Squared speed of v across curved piece ``face`` at normal n: its tangential part,
    less its part along the axis of an edge (along which the surface does not curve)."""
    along = 1.0 - jnp.abs(faces.row[face, DIRECTION])  # an edge's free axis (none at a corner)
    tangential = v - inner(v, n) * n
    edge = jnp.sum(along) == 1
    return inner(tangential, tangential) - jnp.where(edge, inner(along, v) ** 2, 0.0)


def contact_normals(scene: Scene, face: Int[Array, "*n"], position: Float[Array, "*n 3"]) -> Float[Array, "*n 3"]:
    """Unit contact normals (from the solid towards the ball's centre) of balls touching
    faces ``face`` (``Events.face``) with their centres at ``position``
    (``Events.position``); zero where ``face`` is -1 (padding). (The normal does not depend
    on the ball's radius: on an edge or a corner it points from the edge or the vertex to
    the centre.)"""
    faces = faces_for(scene, jnp.float64(0.0))
    face, position = jnp.asarray(face), jnp.asarray(position, jnp.float64)
    flat_f, flat_q = face.reshape(-1), position.reshape(-1, 3)
    n = jax.vmap(lambda f, q: contact_normal(faces, jnp.maximum(f, 0), q))(flat_f, flat_q)
    return jnp.where((flat_f >= 0)[:, None], n, 0.0).reshape(position.shape)


def _length(x):
    """|x|, 0 at x = 0 with a zero derivative there: the square root's derivative at 0 is
    infinite, and reverse mode multiplies it by the zero cotangent of a branch that
    ``where`` discards: every reverse-mode derivative of a ball that rolls off an edge
    from rest (``w`` in ``roll_axis`` is 0) was NaN, its forward-mode ones finite."""
    xx = inner(x, x)
    return jnp.where(xx > 0, jnp.sqrt(jnp.where(xx > 0, xx, 1.0)), 0.0)


def roll_axis(faces: Faces, face, p, v):
    """The horizontal line a ball at p with velocity v, pressed onto curved piece ``face``,
    rolls about (``estim.forward._roll``): ``(pivot, axis, exact)``, the axis oriented so
    that ``up x axis`` points away from the solid. On an edge the edge
    line; on a corner the line through the vertex perpendicular to the vertical plane
    through the vertex and the ball's centre (or its motion, where the centre is right
    above the vertex). ``exact`` is false where that is not the ball's motion: an edge
    that is not horizontal, or a corner where the ball moves out of that plane (the
    spherical pendulum: ``estim.forward._solver.RollOver``)."""
    pivot, mask = piece_at(faces, face)
    up = jnp.array([0.0, 0.0, 1.0])
    edge = jnp.sum(mask) == 2
    flat = jnp.array([1.0, 1.0, 0.0])
    # The horizontal direction away from the solid: on an edge its direction's horizontal
    # part; on a corner from the vertex to the centre, or along the motion.
    m = faces.row[face, DIRECTION] * flat
    d, w = (p - pivot) * flat, v * flat
    d_len, w_len = _length(d), _length(w)
    h = jnp.where(d_len > 0, d / jnp.where(d_len > 0, d_len, 1.0), w / jnp.where(w_len > 0, w_len, 1.0))
    h = jnp.where(edge, m / jnp.sqrt(jnp.maximum(inner(m, m), 1.0)), h)
    h = jnp.where(inner(h, h) > 0, h, jnp.array([1.0, 0.0, 0.0]))  # (at rest right above a vertex)
    planar = jnp.abs(d[0] * w[1] - d[1] * w[0]) <= AXIS_TOL * d_len * w_len
    # The axis with up x axis = h, the direction in which the roll's angle grows.
    return pivot, jnp.cross(h, up), jnp.where(edge, (mask[2] == 1) & (inner(m, m) == 1), planar)


def roll_exit_time(faces: Faces, face, pivot, axis, p, v):
    """Time at which a ball rolling about edge ``face`` (at p, velocity v) reaches an end
    of the edge, where a corner begins (inf on a corner, whose roll stays in one plane
    through its vertex). A speed along the edge below ``SPEED_TOL`` counts as none (the
    ball moves less than 1e-12 m per second along it): the time ``(end - along) / u`` and
    its derivative ``-tau / u`` overflow as u goes to 0 (at u = 1e-160 m/s the derivative
    was infinite, and the minimum with the roll's own end made it NaN)."""
    half = jnp.sum(faces.row[face, HALF] * jnp.abs(axis))
    along, u = inner(p - pivot, axis), inner(v, axis)
    moves = jnp.abs(u) > SPEED_TOL
    end = jnp.where(u > 0, half, -half)
    tau = (end - along) / jnp.where(moves, u, 1.0)
    edge = jnp.sum(1.0 - piece_at(faces, face)[1]) == 1
    return jnp.where(edge & moves, jnp.maximum(tau, 0.0), jnp.inf)


def next_piece(faces: Faces, face, axis, v):
    """The piece of the same box that a ball rolling on edge or corner ``face`` moves onto
    when it leaves that piece's region across ``axis`` (0, 1, 2) with velocity v: past an
    edge's end, the corner there (the axis gains v's sign); back within the box along an
    axis where the piece lies beyond it, the piece without that axis (a corner's edge, an
    edge's face). ``(piece, found)``."""
    row = faces.row
    m = row[face, DIRECTION]
    e = jnp.zeros(3).at[axis].set(1.0)
    target = m * (1.0 - e) + jnp.where(m[axis] == 0, jnp.sign(inner(v, e)), 0.0) * e
    match = jnp.all(row[:, DIRECTION] == target, axis=1) & (row[:, SOLID] == row[face, SOLID])
    return jnp.argmax(match).astype(jnp.int32), jnp.any(match) & jnp.any(target != 0)


def face_entering_time(faces: Faces, face, p, v, a, found):
    """``entering_time`` for one face, recomputed from the state (differentiable). On an
    edge or a corner, ``found`` is the time the contact search found (values), made
    differentiable by the implicit-function theorem (``estim.forward._curved``): the
    search is not run again."""
    n, h = faces.normal_offset(face)
    flat = entering_time(inner(n, p) - h, inner(n, v), inner(n, a))
    if not faces.curved:
        return flat
    anchor, mask = piece_at(faces, face)
    A, B, C = distance_terms(p, v, a, anchor, mask)
    found = jax.lax.stop_gradient(jnp.where(jnp.isfinite(found), found, 0.0))
    curved = jnp.where(found > 0, implicit_time(found, A, B, C, faces.radius), 0.0 * found)
    return jnp.where(is_curved(faces, face), curved, flat)


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


def slab_clear(faces: Faces, face, lo, hi, height):
    """Whether a bounce series on an upward face whose centre stays over the rectangle
    ``lo[:2] .. hi[:2]`` and within ``height`` (its first apex) above its height on the
    face, ``lo[2]``, meets no other solid: no other solid's box grown by r in every axis
    has its interior in that slab (as ``train_reach``: a series that touches a grown box's
    boundary never enters the solid)."""
    solid = faces.row[face][SOLID]
    zeta = lo[2]
    overlap = ((faces.lo[:, 2] < zeta + height - POSITION_TOL) & (faces.hi[:, 2] > zeta + POSITION_TOL)
               & jnp.all((faces.lo[:, :2] < hi[:2] - POSITION_TOL) & (faces.hi[:, :2] > lo[:2] + POSITION_TOL), axis=1))
    return ~jnp.any(overlap & (jnp.arange(faces.lo.shape[0]) != solid))


def sweep_clear(faces: Faces, p, v, a, h, margin):
    """Whether a ball whose centre stays within ``margin`` of the parabola
    ``p + v tau + a tau^2 / 2`` over ``0 <= tau <= h`` provably touches no solid then.

    The parabola lies in its bounding box (per axis: the end points and the apex where it
    falls inside the step); every point of the ball's contact region with a solid lies in
    that solid's box grown by r along each axis (``Faces.lo``/``hi``: the region's L1 excess
    is at most r). So if the box of the parabola, grown by ``margin``, meets no grown box,
    no contact is possible within the step. Conservative: a ball that touches a solid (just
    bounced off it, or lands within the step) is never clear."""
    lo, hi = parabola_box(p, v, a, h)
    lo, hi = lo - margin, hi + margin
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
