"""A 3-D path from pixels, through the physics: the start of a fit in pixels.

One camera gives a ray per sample, not a point: depth is what the pixels leave open. The
physics closes it (the issue's "one camera" case). Between two bounces a ball in a vacuum
flies on the parabola ``X(t) = p + v (t - tau) + g (t - tau)^2 / 2`` with gravity ``g``
known in direction *and size*; a sample at time ``t_i`` seen along the unit ray ``d_i``
from the camera centre ``C`` puts ``X(t_i)`` on that ray,

    (I - d_i d_i^T) (p + v dt_i) = (I - d_i d_i^T) (C - g dt_i^2 / 2),    dt_i = t_i - tau,

which is *linear* in the flight's ``(p, v)``. Without the gravity term the equations are
homogeneous (a path twice as far and twice as fast looks the same); gravity's known size
fixes the scale, from a single camera. Flights meet at the bounces (their positions
agree there), and at a bounce on a known surface the centre is one radius above it: both
are linear too. Every flight of every camera goes into one linear least-squares problem
(:func:`reconstruct`), solved twice: first with gravity and the meetings alone, then with
the centre at each bounce on the scene's surface beneath it. Rows are weighted by the
inverse distance of the point from the camera, so that each measures an angle (a pixel
divided by the focal length), and rows far off the solution (beyond 5 robust standard
deviations) are set aside as outliers. With several cameras their rays meet in the same
problem: a triangulation through the physics, which needs no common sample times.

In a scene with air the flights are not parabolas: drag and the Magnus force (of a spin
the start does not know) add an acceleration of the order of g to a fast light ball. Each
flight then gets its own constant acceleration ``g + a_k``, still linear,

    X(t) = p + v dt + (g + a_k) dt^2 / 2,

with a Gaussian prior on ``a_k`` (rows ``W a_k`` weighted like the flight's samples
together, ``W`` the inverse of its standard deviations, :func:`air_weights`: ``AIR_PRIOR``
along the flight, the drag coefficient's spread; across it, where the Magnus force acts,
wider for a fast flight): without it gravity's size would no longer fix the
scale, and the bounce on a surface of known height would be the only thing that does.

At a bounce on a surface, friction changes the velocity along the surface by at most
``mu (1 + e) |v_n|``; a prior ``N(0, BOUNCE_PRIOR^2)`` per horizontal component on that
change (one row each, weighted like the later flight's rows together, as the air's prior)
ties the flight after a bounce to the flight before it. Without it a short flight seen nearly along its rays (four frames after
the bounce, from behind) runs off along them, at tens of m/s. Where the search finds no
bounce, or one that keeps almost none of its normal speed, it runs again with the normal
speeds tied too, ``v_z' = -e v_z`` with e the mean of the scene's prior
(``RESTITUTION_PRIOR``, ``TORN``).

Bounces are read from the pixels themselves (:func:`estim.tracks._flights.flight_contacts`
on the image coordinate along which the track bounces most clearly). The result is a
start, not an estimate: drag, spin and the cameras' clock offsets are left to the fit.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..model._air import spinless_acceleration
from ..model._params import DRAG_COEFFICIENT
from ..model._scene import Scene
from ._flights import flight_contacts
from ._image import ImageTracks

__all__ = ["Reconstruction", "reconstruct", "reconstructions", "surface_height"]

# Weight of a meeting of two flights and of a bounce on a surface, against one sample's
# ray (both in units of angle: metres over the distance from the camera).
_TIE = 30.0
_CUT = 5.0
# The share of a path's rows whose misses a score caps at _CUT noise levels (outliers).
OUTLIERS = 0.2
# The prior's standard deviation of a flight's air acceleration about the drag at the
# default coefficient (m/s^2): the Magnus force of a table-tennis ball at 6 m/s and 100
# rad/s, and the drag coefficient's spread, are about this size. The Magnus force, across
# the flight, grows with the speed at a given spin (and harder hits spin more), so across
# a faster flight the prior is wider in proportion to its speed above AIR_SPEED
# (:func:`air_weights`): a 15 m/s drive with 280 rad/s of topspin bends under about 2 g,
# 6 standard deviations of the slow prior, and its start, the bounce priced out, had read
# one parabola through the bounce, 5 m off. Along the flight the prior stays AIR_PRIOR: a
# flight seen head-on, wide there too, ran off along its rays (54 m/s^2 of extra drag).
AIR_PRIOR = 5.0
AIR_SPEED = 6.0
# A box top narrower than this many ball radii (a net, a wall's top) is no bounce surface
# for the start.
NARROW = 4.0
# A bounce point within this many ball radii of a solid is on it (the centre one radius
# above a top, up to sqrt(EDGE^2 - 1) radii past its outline). Read off the rays at a
# bounce time read between frames, the point is uncertain by centimetres along its ray: a
# drive at 15 m/s that bounced 11 cm inside the table's end, seen from behind, is read up
# to 13 cm farther on. Searched again with its normal speeds tied (the first reading kept
# almost none), its table candidates fell 3-4 cm past the outline grown by one radius, and
# the floor's won, 3.5 m farther along the rays (its fit 2.6 m off). A floor bounce whose
# ray meets the table's height that near its edge is a coincidence, as one inside the
# outline is.
EDGE = 2.0
# The prior's standard deviation of the change of a bounce's velocity along the surface
# (m/s): friction changes it by at most mu (1 + e) |v_n|, about 1 m/s for a table-tennis
# ball at 4 m/s onto the table (mu 0.25, e 0.9).
BOUNCE_PRIOR = 1.0
# Where no bounce is found (or a torn one, TORN), the search runs again with each bounce's
# normal speeds tied by the scene's prior on the restitution (not where the scene has no
# such prior): a row ``v_z' + e v_z = 0`` (after and before the bounce, e the prior's mean)
# of this standard deviation (m/s), about the prior's spread (0.05 in the table-tennis
# scene) times a bounce's normal speed (3-6 m/s), and the law's e against a real bounce's.
# It ties the flights' scales through the bounce: six frames about a bounce seen from
# behind, three rows a flight, let each flight run off along its rays (10-100 m/s), and no
# bounce time rebounded. Only there: tied, a wrong bounce rebounds as readily as the right
# one (a cusp read off noise was kept; a serve's single bounce passed for its two), so the
# rebound no longer tells a bounce from a bend.
RESTITUTION_PRIOR = 0.5
# ... and where a bounce found untied misses that tie by more than this many standard
# deviations: a flight run off along its rays rebounds with almost none of its normal
# speed (the same windows: ratios of 0.0-0.08 for 0.88, starts 0.5-7 m off).
TORN = 3.0
# The fewest rows of the first or the last flight beside a bounce on the scene's surfaces
# (3 elsewhere: a parabola's six unknowns from two pixels a row). Two: the bounce's height
# and the flights' meeting fix the rest. A shot hit hard spans 6 frames at 25 fps, its
# bounce among them; with two of them after it (or before), three rows a flight merged the
# bounce into one flight through it, a start metres off (docs/pages/cameras.md, "Short
# tracks").
ON_SURFACE_ROWS = 2
# The least noise (px) a start assumes of the pixels (the priors weigh against it): a clean
# track (a third-difference noise of 0.02-0.2 px) otherwise gave starts off by metres in
# depth (docs/pages/cameras.md, "Clean tracks").
START_NOISE = 1.0


@dataclass(frozen=True)
class Reconstruction:
    """A piecewise-parabolic 3-D path through the pixels of one ball.

    Attributes:
        t: ``(n,)`` the track's rows' times.
        position: ``(n, 3)`` the path at those times (m).
        bounces: times of the bounces read from the pixels (s).
        bounce_points: ``(len(bounces), 3)`` the path at the bounces (m).
        depth: ``(n,)`` distance of each row's point along its camera's axis (m).
        inlier: ``(n,)`` rows that the least squares kept.
        ray_rms: rms distance of the kept rows' points from their rays, over their depth
            (radians: a pixel over the focal length).
        flights: ``(len(bounces) + 1, k, 3)`` each flight's position and velocity at its
            reference time (the first row's time, then the bounces), and in air (k = 3)
            its own acceleration besides gravity.
        refs: ``(len(bounces) + 1,)`` the flights' reference times.
        gravity: the gravity vector (m/s^2).
    """

    t: np.ndarray
    position: np.ndarray
    bounces: tuple[float, ...]
    bounce_points: np.ndarray
    depth: np.ndarray
    inlier: np.ndarray
    ray_rms: float
    flights: np.ndarray
    refs: np.ndarray
    gravity: np.ndarray

    def velocity(self, t: float, flight: int | None = None) -> np.ndarray:
        """The path's velocity at time ``t`` (m/s), on ``flight`` (default: the flight
        that holds t; at a bounce, the flight before it is ``flight = k``, after it ``k + 1``)."""
        k = int(np.searchsorted(np.asarray(self.bounces), t, side="right")) if flight is None else flight
        u = self.flights[k]
        return u[1] + self.acceleration(k) * (t - self.refs[k])

    def scaled(self, factor: float, centre) -> Reconstruction:
        """The path scaled by ``factor`` about the point ``centre`` (a camera's centre: its
        pixels stay where they are, the depth changes): positions ``centre + factor (p -
        centre)``, velocities and accelerations (gravity's included) times ``factor``."""
        c = np.asarray(centre, dtype=np.float64)
        flights = np.zeros((self.flights.shape[0], 3, 3))
        flights[:, 0] = c + factor * (self.flights[:, 0] - c)
        flights[:, 1] = factor * self.flights[:, 1]
        flights[:, 2] = np.stack([factor * self.acceleration(k) - self.gravity for k in range(len(flights))])
        return dataclasses.replace(self, position=c + factor * (self.position - c),
                                   bounce_points=c + factor * (self.bounce_points - c), flights=flights,
                                   depth=factor * self.depth)

    def released_at(self, factor: float, centre) -> Reconstruction:
        """The path with its first flight's reference point moved along the ray from
        ``centre`` by ``factor`` and the flight re-aimed at its first bounce: the velocity
        that reaches the bounce point at the bounce's time under the flight's acceleration
        (``(B - p - a dt^2 / 2) / dt``); the bounces and the later flights kept. The bounce
        on a surface holds its depth better than a first flight seen along the rays, whose
        velocity along them is as wrong as its depth. Without a bounce: :meth:`scaled`."""
        if not self.bounces:
            return self.scaled(factor, centre)
        c = np.asarray(centre, dtype=np.float64)
        a = self.acceleration(0)
        p = c + factor * (self.flights[0, 0] - c)
        span = self.bounces[0] - self.refs[0]
        v = (self.bounce_points[0] - p - 0.5 * a * span**2) / span
        flights = self.flights.copy()
        flights[0, 0], flights[0, 1] = p, v
        first = self.t < self.bounces[0]
        dt = (self.t[first] - self.refs[0])[:, None]
        position = self.position.copy()
        position[first] = np.where(np.isfinite(position[first]), p + v * dt + 0.5 * a * dt**2, np.nan)
        return dataclasses.replace(self, position=position, flights=flights)

    def acceleration(self, flight: int) -> np.ndarray:
        """The acceleration of ``flight`` (gravity, and in air its own besides)."""
        u = self.flights[flight]
        return self.gravity + (u[2] if u.shape[0] == 3 else 0.0)


def surface_height(scene: Scene, x: float, y: float, z: float, radius: float) -> float | None:
    """The height of the scene's upward-facing surface under ``(x, y)`` nearest to the
    height ``z - radius`` (the top of a box whose outline, grown by the radius, holds
    ``(x, y)``, or a plane facing up); ``None`` where there is none."""
    tops = []
    for c, h in zip(np.asarray(scene.box_centre), np.asarray(scene.box_half), strict=True):
        if abs(x - c[0]) <= h[0] + radius and abs(y - c[1]) <= h[1] + radius:
            tops.append(c[2] + h[2])
    for n, o in zip(np.asarray(scene.plane_normal), np.asarray(scene.plane_offset), strict=True):
        if n[2] > 0.5:
            tops.append(o)
    if not tops:
        return None
    return float(min(tops, key=lambda top: abs(top - (z - radius))))


def _bounce_times(tracks: ImageTracks, ball: str) -> tuple[float, ...]:
    """Bounce times from the camera with the most rows, on the image coordinate (and sign)
    with the most resolved bounces."""
    view, t, uv = tracks.view[ball], tracks.t[ball], tracks.uv[ball]
    ok = tracks.valid(ball)
    best = max(range(len(tracks.cameras)), key=lambda k: int(np.sum(ok & (view == k))))
    rows = ok & (view == best)
    found: tuple[float, ...] = ()
    for axis, sign in ((1, 1.0), (1, -1.0), (0, 1.0), (0, -1.0)):
        bounces, _, contacts = flight_contacts(t[rows], sign * uv[rows, axis])
        times = {i: float(t[rows][i]) for i in bounces}
        times.update({i: float(tc) for i, tc, *_ in contacts})
        if len(times) > len(found):
            found = tuple(times[i] for i in sorted(times))
    return found


def reconstruct(tracks: ImageTracks, ball: str, scene: Scene, *, radius: float | None = None,
                bounces: tuple[float, ...] | None = None) -> Reconstruction:
    """The most likely 3-D path of ``ball`` through its pixels: the first of
    :func:`reconstructions`."""
    return reconstructions(tracks, ball, scene, radius=radius, bounces=bounces)[0]


def reconstructions(tracks: ImageTracks, ball: str, scene: Scene, *, radius: float | None = None,
                    bounces: tuple[float, ...] | None = None, alternatives: int = 1) -> list[Reconstruction]:
    """The 3-D path of ``ball`` through its pixels (module docstring).

    Bounces come from the pixels' cusps. Every bounce, a cusp's too, must earn its place:
    the one whose removal raises the misfit least goes while the misfit without it is less
    than 1.5 times the misfit with it (a cusp read off noisy pixels, with the real bounce
    added beside it, had led a fit to a path 2.6 m off). Where the rays then miss the path
    by more than twice the pixels' noise (a bounce seen head-on makes no clear cusp), or
    where no bounce is in at all, the bounce that lowers the misfit most (tried at each
    sample and between each two, at the quarter frames where none of those rebounds and
    none is in, then at its best time between the samples beside it, those already in on
    their surfaces) is added while it lowers the misfit by a third or more; before any is
    in, two at once where they lower it by a third more than one (a serve's, and only
    where the misfit asks: the best pair between the samples, then each of its bounces at
    its best time between the samples beside it). Pruned and added again until that
    changes nothing. Each bounce time is then refined between its neighbouring samples
    (golden-section search on the misfit, kept where it scores no worse).

    Each bounce is put on each of the scene's upward surfaces in turn (:func:`_on_surfaces`);
    the paths whose bounce points lie on their surfaces come first, and among those the
    ones with the fewest bounces on unbounded planes (a bounce point that falls inside a
    table's outline is evidence for the table, while a plane, such as the floor far behind
    it on the same ray, holds any point), the least misfit first. ``alternatives`` returns
    up to that many paths of that first kind, for a fit to choose between with the whole
    physics.

    Args:
        tracks: the pixels and the cameras that saw them.
        ball: which ball.
        scene: gravity and the surfaces the ball bounces on.
        radius: the ball's radius (default: the scene's ball of that name).
        bounces: the bounce times (default: read from the pixels as above).
        alternatives: how many paths to return at most (different surfaces of the bounces).

    Raises:
        ValueError: too few rows to fix the path (six unknowns per flight).
    """
    radius = scene.ball(ball).radius if radius is None else float(radius)
    drag = None if scene.air is None else spinless_acceleration(scene.air, radius, scene.ball(ball).mass,
                                                                   DRAG_COEFFICIENT)
    rays = _Rays(tracks, ball, np.array([0.0, 0.0, -float(scene.gravity)]), drag)
    surfaces = _surfaces(scene, radius)
    e = next((mean for name, mean, _ in scene.priors if name == "e"), None)
    if bounces is None:
        bounces = _find_bounces(rays, _bounce_times(tracks, ball), surfaces)
        if surfaces and e is not None and (not bounces or _torn(rays, bounces, surfaces, e)):
            # None found, or a bounce that keeps almost none of its normal speed (a flight
            # run off along its rays): again with the bounce's normal speeds tied
            # (RESTITUTION_PRIOR), kept where its bounces fit the tied rays better.
            tied = rays.tied(e)
            found = _find_bounces(tied, (), surfaces)
            if found and (not bounces or _tied_score(tied, found, surfaces) < _tied_score(tied, bounces, surfaces)):
                rays, bounces = tied, found
    bounces = _viable(tuple(sorted(bounces)), rays.t, bool(surfaces))
    t_all, view = tracks.t[ball], tracks.view[ball]
    out = []
    for x, keep, miss, _, _ in _on_surfaces(rays, bounces, surfaces, ranked=alternatives):
        position = rays.evaluate(x, bounces, t_all)
        bounce_points = np.array([rays.at(x, bounces, b, k + 1) for k, b in enumerate(bounces)]).reshape(-1, 3)
        axis_depth = np.array([tracks.cameras[k].depth(p) for k, p in zip(view, position, strict=True)])
        inlier = np.zeros(t_all.size, bool)
        inlier[rays.rows[keep]] = True
        out.append(Reconstruction(t=t_all.copy(), position=position, bounces=bounces, bounce_points=bounce_points,
                                  depth=axis_depth, inlier=inlier, ray_rms=float(np.sqrt(np.mean(miss[keep] ** 2))),
                                  flights=x.reshape(len(bounces) + 1, -1, 3), refs=rays.refs(bounces),
                                  gravity=rays.g))
    return out


class _Surface(NamedTuple):
    """An upward-facing surface a bounce can be on: the ball centre's height there, and
    the outline ``(x_lo, x_hi, y_lo, y_hi)`` that holds the centre (None: a plane): the
    top's grown by ``sqrt(EDGE^2 - 1)`` radii."""

    height: float
    outline: tuple[float, float, float, float] | None

    def holds(self, point) -> bool:
        if self.outline is None:
            return True
        x_lo, x_hi, y_lo, y_hi = self.outline
        return bool(x_lo <= point[0] <= x_hi and y_lo <= point[1] <= y_hi)


def _surfaces(scene: Scene, radius: float) -> list[_Surface]:
    """The scene's upward faces: box tops (outlines grown by ``sqrt(EDGE^2 - 1)`` radii)
    at least ``NARROW`` radii wide, and planes."""
    grow = math.sqrt(EDGE**2 - 1.0) * radius
    out = [_Surface(float(c[2] + h[2] + radius), (c[0] - h[0] - grow, c[0] + h[0] + grow,
                                                  c[1] - h[1] - grow, c[1] + h[1] + grow))
           for c, h in zip(np.asarray(scene.box_centre), np.asarray(scene.box_half), strict=True)
           if 2 * min(h[0], h[1]) >= NARROW * radius]
    out += [_Surface(float(o + radius), None)
            for n, o in zip(np.asarray(scene.plane_normal), np.asarray(scene.plane_offset), strict=True) if n[2] > 0.5]
    return out


def _on_surfaces(rays, bounces, surfaces, chosen=None, ranked: int = 0):
    """The path with each bounce on a surface: every assignment of surfaces to the bounces
    (up to three bounces; beyond, one bounce at a time), the centre one radius above its
    surface at the bounce. The assignment whose bounce points lie on their surfaces, with
    the fewest on unbounded planes, and whose rays miss least wins (:meth:`_Rays.score`). Returns ``(x, keep, miss, depth,
    surfaces chosen)``; with ``ranked``, a list of up to that many, best first. ``chosen``
    fixes a surface per bounce (``None``: any of them)."""
    if not bounces or not surfaces:
        return [(*rays.fit(bounces), ())] if ranked else (*rays.fit(bounces), ())
    if chosen is not None:
        options = [surfaces if c is None else [c] for c in chosen]
    elif len(bounces) <= 3:
        options = [surfaces] * len(bounces)
    else:
        options = [[min(surfaces, key=lambda s: s.height)]] * len(bounces)
    found = []
    for combo in itertools.product(*options):
        try:
            x, keep, miss, depth = rays.fit(bounces, heights=[s.height for s in combo])
        except ValueError:
            continue
        points = [rays.at(x, bounces, b, k + 1) for k, b in enumerate(bounces)]
        held = all(s.holds(p) for s, p in zip(combo, points, strict=True))
        # A bounce point inside a bounded surface's outline is evidence for it (a wrong
        # depth puts it there by chance only); a plane holds any point.
        key = (not held, sum(s.outline is None for s in combo), rays.score(miss, x, bounces))
        found.append((key, (x, keep, miss, depth, combo)))
    if not found:
        raise ValueError(f"a flight with too few tracked rows (3, or {ON_SURFACE_ROWS} for the first or the last beside "
                         "a bounce on a surface) to fix its 3-D path from pixels")
    found.sort(key=lambda f: f[0])
    if ranked:
        return [f[1] for f in found if f[0][:2] == found[0][0][:2]][:ranked]
    return found[0][1]


class _Rays:
    """The rays of one ball's valid rows, and least-squares paths through them."""

    def __init__(self, tracks: ImageTracks, ball: str, g: np.ndarray, drag):
        self.g = g
        self.e = None  # the restitution a bounce's normal speeds keep (RESTITUTION_PRIOR); None: untied
        self.drag = drag  # v -> the air's drag acceleration at the default coefficient; None: a vacuum
        ok = tracks.valid(ball)
        self.rows = np.flatnonzero(ok)
        view = tracks.view[ball][self.rows]
        uv = tracks.uv[ball][self.rows]
        self.t = tracks.t[ball][self.rows]
        self.centres = np.stack([c.centre for c in tracks.cameras])[view]
        self.dirs = np.zeros((self.rows.size, 3))
        for k, cam in enumerate(tracks.cameras):
            self.dirs[view == k] = cam.rays(uv[view == k])
        # The rays' noise as an angle (rad): the pixels' noise over the focal length.
        focal = np.median([float(np.asarray(c.matrix)[0, 0]) for c in tracks.cameras])
        # No less than START_NOISE: below it the third differences read the projection's own
        # curvature, not noise, and the priors below would vanish against rays whose depth
        # no path can honour.
        self.noise = max(tracks.noise(ball), START_NOISE) / focal

    def tied(self, e: float) -> _Rays:
        """The same rays with each bounce's normal speeds tied in the ratio ``e``."""
        out = copy.copy(self)
        out.e = e
        return out

    def refs(self, bounces):
        """Each flight's reference time: the first sample, then the bounces."""
        return np.concatenate([[self.t.min()], bounces])

    def evaluate(self, x, bounces, t):
        flight = np.searchsorted(np.asarray(bounces), t, side="right")
        return self.at(x, bounces, t, flight)

    def at(self, x, bounces, t, flight):
        unknowns = x.reshape(len(bounces) + 1, -1, 3)[flight]
        dt = np.asarray(t - self.refs(bounces)[flight])[..., None]
        a = self.g + (unknowns[..., 2, :] if unknowns.shape[-2] == 3 else 0.0)
        return unknowns[..., 0, :] + unknowns[..., 1, :] * dt + 0.5 * a * dt**2

    def fit(self, bounces, *, heights=None, keep=None, depth=None):
        """``(x, keep, miss, depth)``: the flights' ``(p, v)``, the rows kept (within 5 robust
        standard deviations), each row's miss (angle) and its distance from its camera,
        after a few rounds of reweighting."""
        keep = np.ones(self.rows.size, bool) if keep is None else keep
        depth = np.ones(self.rows.size) if depth is None else depth
        flight = np.searchsorted(np.asarray(bounces), self.t, side="right")
        on_surfaces = bool(bounces) and heights is not None and all(h is not None for h in heights)
        least = _fewest(len(bounces) + 1, on_surfaces)
        if np.any(np.bincount(flight, minlength=len(bounces) + 1) < least):
            raise ValueError(f"a flight with fewer than {least.min()} tracked rows: too few to fix its 3-D path from "
                             "pixels")
        # In air, the flights' own accelerations only where a bounce on a surface holds
        # the scale: without one, their freedom would let the path shrink onto the camera.
        air = self.drag is not None and heights is not None and any(h is not None for h in heights)
        x = None
        for _ in range(4 if air else 3):
            x = _solve(self, bounces, flight, keep, depth, heights, air, x)
            pos = self.at(x, bounces, self.t, flight)
            v = pos - self.centres
            depth = np.maximum(np.linalg.norm(v, axis=1), 1e-3)
            along = np.sum(v * self.dirs, axis=1)
            miss = np.linalg.norm(v - along[:, None] * self.dirs, axis=1) / depth
            scale = 1.4826 * _median(miss[keep]) + 1e-12
            keep = miss <= _CUT * max(scale, self.noise if np.isfinite(self.noise) else 0.0)
        # The sine of the angle between each ray and its point, growing on past 1 for a point
        # behind the camera (2 - sine: 2 straight behind), as the path is scored: a ray is a
        # half-line, and a path through the rays' backward extensions (a drive seen from far
        # behind, read as one flight that passes behind the lens) is no path.
        return x, keep, np.where(along >= 0.0, miss, 2.0 - miss), depth

    def score(self, miss, x=None, bounces=()) -> float:
        """The misfit of a path: the mean square of the rays' misses, the worst ``OUTLIERS``
        of them capped at 5 times the noise (an outlier counts, but only so much), plus, in air, the prior's cost of
        the flights' accelerations (:func:`_solve`) per row; its square root (rad)."""
        noise = self.noise if np.isfinite(self.noise) else float(np.median(miss))
        # Only the worst OUTLIERS of the rows are capped: a path that calls most rows
        # outliers (one parabola through a bounce, all its misses capped) is no cheap path.
        capped = np.argsort(miss)[::-1][:int(OUTLIERS * miss.size)]
        cost = np.sum(miss**2) - np.sum(miss[capped] ** 2 - np.minimum(miss[capped], _CUT * noise) ** 2)
        if x is not None:
            refs, ends = self.refs(bounces), np.concatenate([bounces, [self.t.max()]])
            flight = np.searchsorted(np.asarray(bounces), self.t, side="right")
            flights = x.reshape(len(refs), -1, 3)
            for f, u in enumerate(flights):
                n = np.sum(flight == f)
                if u.shape[0] == 3:
                    middle = self.velocity_at(u, 0.5 * (ends[f] - refs[f]))
                    cost += n * noise**2 * np.sum((air_weights(middle) @ (u[2] - self.drag(middle))) ** 2)
                if f > 0:
                    slip = u[1] - self.velocity_at(flights[f - 1], bounces[f - 1] - refs[f - 1])
                    cost += n * noise**2 * np.sum(slip[:2] ** 2) / BOUNCE_PRIOR**2
                    if self.e is not None:
                        before = self.velocity_at(flights[f - 1], bounces[f - 1] - refs[f - 1])[2]
                        cost += n * noise**2 * (u[1][2] + self.e * before) ** 2 / RESTITUTION_PRIOR**2
        return float(np.sqrt(cost / miss.size))

    def velocity_at(self, unknowns, dt: float) -> np.ndarray:
        """A flight's velocity ``dt`` after its reference time."""
        a = self.g + (unknowns[2] if unknowns.shape[0] == 3 else 0.0)
        return unknowns[1] + a * dt


def _find_bounces(rays: _Rays, bounces, surfaces) -> tuple[float, ...]:
    """Bounces added where the misfit asks for them, then refined (:func:`reconstruct`).
    Each candidate set of bounces is scored with its bounces on the scene's surfaces
    (:func:`_on_surfaces`): a path that merely bends (drag, spin) is no bounce."""

    on = {}  # the surfaces of each scored set's bounces

    def score(candidate, chosen=None):
        try:
            x, _, miss, _, on[tuple(candidate)] = _on_surfaces(rays, tuple(candidate), surfaces, chosen)
        except ValueError:
            return np.inf
        if not _rebounds(rays, x, tuple(candidate)):
            return np.inf
        return rays.score(miss, x, tuple(candidate))

    times = np.unique(rays.t)
    mids = 0.5 * (times[1:] + times[:-1])
    # A bounce is tried between samples and at them: a drive's, seen from in front, fell on
    # a frame, and neither midpoint beside it rebounds.
    singles = np.union1d(mids, times[1:-1])
    # Finer times between the samples, tried in turn where no coarser one rebounds.
    finer = [np.concatenate([(1.0 - f) * times[:-1] + f * times[1:] for f in np.arange(1, n) / n if f != 0.5])
             for n in (4, 16)]

    def prune(bounces, current):
        # A bounce stays only if it earns its place as an added one must (lowering the
        # misfit by a third), the cusps' included: a cusp read off noisy pixels is no
        # bounce, and a bounce added beside it can be the real one.
        while bounces:
            best, k = min((score(bounces[:k] + bounces[k + 1:]), k) for k in range(len(bounces)))
            if not best < 1.5 * current:
                break
            bounces, current = bounces[:k] + bounces[k + 1:], best
        return bounces, current

    def plus(bounces, b):
        # The bounces already in keep their surfaces; only the added one's is chosen (half
        # the least-squares paths of every surface for every bounce, the same bounces found).
        held = dict(zip(bounces, on.get(tuple(bounces), ()), strict=False))
        candidate = sorted(bounces + [b])
        return score(candidate, [held.get(c) for c in candidate] if held else None)

    def add(bounces, current):
        # With no bounce in, one is tried even where a single flight misses the rays by
        # less than twice the noise: the noise read off a short track's third differences
        # holds its bounce's kink (4.3 px for 2 px on 8 frames about a bounce, seen at an
        # angle), and one parabola metres off the table passed.
        while not (fits := current <= 2.0 * rays.noise) or not bounces:
            trial = [(plus(bounces, b), (b,)) for b in singles if b not in bounces]
            best, added = min(trial) if trial else (np.inf, ())
            for grid in finer if not bounces else ():
                if best < current / 1.5:
                    break
                # None rebounds there, or none that fits: a few rows a flight fit well only
                # near the bounce's own time (a track picked up three frames before it, seen
                # from behind: at the samples and midpoints beside the bounce each fit ran
                # off along its rays; six frames, three a flight, seen from behind: only
                # within a few ms of the bounce), so the quarter frames are tried, then
                # sixteenths.
                best, added = min([(best, added)] + [(plus(bounces, b), (b,)) for b in grid])
            if np.isfinite(best):
                # The best bounce at its best time between the samples beside it, the next
                # one then tried against it: a serve's first bounce at the midpoint 20 ms
                # off, or its second 10 ms off, lowered the misfit by less than a third.
                lo, hi = times[times < added[0]][-1], times[times > added[0]][0]  # (the samples beside it)
                refined = _golden(lambda b, bounces=bounces: plus(bounces, b), lo, hi)
                best, added = min((best, added), (plus(bounces, refined), (refined,)))
            if not bounces and not fits:
                # Two bounces at once, where they lower the misfit by a third more than the
                # best one alone (a serve's, on each half: one alone rarely turns both falls
                # into rises, and the one that does, added first, left no room for the other).
                pairs = [(score([b, c]), (b, c)) for b, c in itertools.combinations(mids, 2)
                         if np.sum((times > b) & (times < c)) >= 3]
                if pairs:
                    # The best pair with each bounce at its best time between the samples
                    # beside it, the other held: a serve seen from behind whose first bounce
                    # fell 6 ms after a sample, its pair at the midpoints missed by 14 ms
                    # and 22 ms and lowered the misfit by less than a third more than one.
                    pair = list(min(pairs)[1])
                    for k in range(2):
                        lo, hi = times[times < pair[k]][-1], times[times > pair[k]][0]
                        pair[k] = _golden(lambda b, k=k, pair=pair: score(pair[:k] + [b] + pair[k + 1:]), lo, hi)
                    pairs.append((score(pair), tuple(pair)))
                if pairs and min(pairs)[0] < min(best, current) / 1.5:
                    best, added = min(pairs)
            if not best < current / 1.5:
                break
            bounces, current = sorted(bounces + list(added)), best
        return bounces, current

    # Pruned, added, pruned, until that changes nothing (at most a few rounds): a cusp read
    # at a sample next to the bounce, pruned, leaves room for the bounce between the
    # samples (a drive's, its start 5 m off without it), and one that no path rebounds at
    # goes before any bounce is added beside it.
    bounces, current = prune(list(bounces), score(list(bounces)))
    for _ in range(3):
        grown, current = add(bounces, current)
        if grown == bounces:  # (nothing added: a pruned set stays as it is)
            break
        before, (bounces, current) = bounces, prune(grown, current)
        if bounces == before:
            break
    if bounces:
        chosen = _on_surfaces(rays, tuple(bounces), surfaces)[4] or None
        for k in range(len(bounces)):
            lo = times[max(np.searchsorted(times, bounces[k], side="left") - 1, 0)]
            hi = times[min(np.searchsorted(times, bounces[k], side="right"), times.size - 1)]
            if k > 0:
                lo = max(lo, bounces[k - 1])
            if k + 1 < len(bounces):
                hi = min(hi, bounces[k + 1])
            def at(b, k=k):
                return score(bounces[:k] + [b] + bounces[k + 1:], chosen)

            # (Kept where it scores no worse: where no path rebounds, the misfit is infinite,
            # and a search that meets such a stretch can end there.)
            refined = _golden(at, lo, hi)
            bounces[k] = refined if at(refined) <= at(bounces[k]) else bounces[k]
    return tuple(bounces)


def _normal_speeds(rays: _Rays, x, bounces) -> np.ndarray:
    """``(len(bounces), 2)``: each bounce's vertical velocity before and after it."""
    flights, refs = x.reshape(len(bounces) + 1, -1, 3), rays.refs(bounces)
    return np.array([[rays.velocity_at(flights[k], b - refs[k])[2], flights[k + 1][1][2]]
                     for k, b in enumerate(bounces)]).reshape(-1, 2)


def _torn(rays: _Rays, bounces, surfaces, e: float) -> bool:
    """Whether a bounce of the path through ``bounces`` misses the restitution ``e`` by more
    than ``TORN`` prior standard deviations (``|v_z' + e v_z|``)."""
    x = _on_surfaces(rays, tuple(bounces), surfaces)[0]
    speeds = _normal_speeds(rays, x, tuple(bounces))
    return bool(np.any(np.abs(speeds[:, 1] + e * speeds[:, 0]) > TORN * RESTITUTION_PRIOR))


def _tied_score(tied: _Rays, bounces, surfaces) -> float:
    """The misfit of the path through ``bounces`` with its normal speeds tied."""
    x, _, miss, _, _ = _on_surfaces(tied, tuple(bounces), surfaces)
    return tied.score(miss, x, tuple(bounces))


def _rebounds(rays: _Rays, x, bounces) -> bool:
    """Every bounce of the path turns the ball's fall into a rise (the vertical velocity
    from below zero before to above zero after): a path that merely bends, which the air's
    free accelerations could fit with an extra flight, has no bounce there."""
    flights = x.reshape(len(bounces) + 1, -1, 3)
    refs = rays.refs(bounces)
    for k, b in enumerate(bounces):
        u = flights[k]
        a = rays.g + (u[2] if u.shape[0] == 3 else 0.0)
        before = u[1][2] + a[2] * (b - refs[k])
        if not (before < 0.0 < flights[k + 1][1][2]):
            return False
    return True


def _fewest(flights: int, on_surfaces: bool) -> np.ndarray:
    """The fewest rows each of ``flights`` flights needs: 3, or ``ON_SURFACE_ROWS`` for the
    first and the last beside a bounce on a surface (between two bounces a flight of two
    rows is free to take the bend of a path for a bounce pair)."""
    least = np.full(flights, 3)
    if on_surfaces and flights > 1:
        least[[0, -1]] = ON_SURFACE_ROWS
    return least


def _viable(bounces: tuple[float, ...], t: np.ndarray, on_surfaces: bool = False) -> tuple[float, ...]:
    """``bounces`` without those that leave a flight fewer rows than it needs (:func:`_fewest`;
    too few to fix it): such a bounce is merged into its neighbour flight (the fit still
    sees it, through the physics, where the data show it)."""
    bounces = list(bounces)
    while bounces:
        counts = np.bincount(np.searchsorted(np.asarray(bounces), t, side="right"), minlength=len(bounces) + 1)
        short = np.flatnonzero(counts < _fewest(len(bounces) + 1, on_surfaces))
        if not short.size:
            break
        k = int(short[0])
        bounces.pop(min(k, len(bounces) - 1))
    return tuple(bounces)


def air_weights(velocity) -> np.ndarray:
    """The inverse of the prior's standard deviations of a flight's air acceleration, a
    3 x 3 matrix, for the flight's ``velocity`` at its middle (m/s): ``1 / AIR_PRIOR``
    along it, ``1 / (AIR_PRIOR max(1, speed / AIR_SPEED))`` across it; ``1 / AIR_PRIOR``
    where the velocity is not known (``None``)."""
    if velocity is None:
        return np.eye(3) / AIR_PRIOR
    speed = math.sqrt(velocity @ velocity)
    along = np.outer(velocity, velocity) / max(speed, 1e-12) ** 2
    across = AIR_PRIOR * max(1.0, speed / AIR_SPEED)
    return along / AIR_PRIOR + (np.eye(3) - along) / across


def _median(x) -> float:
    """``np.median`` of a 1-D array, to the last bit, without its dispatch (called per
    least-squares round); NaN where x holds one."""
    s = np.sort(x)
    if s.size == 0 or np.isnan(s[-1]):
        return np.nan
    return 0.5 * (s[(s.size - 1) // 2] + s[s.size // 2])


def noise_of(rays: _Rays) -> float:
    """The rays' noise (rad), 1 mrad where the pixels cannot tell."""
    return rays.noise if np.isfinite(rays.noise) else 1e-3


def _golden(f, lo, hi, iterations: int = 16) -> float:
    """The minimum of ``f`` on ``[lo, hi]`` by golden-section search: ``iterations`` shrink
    the bracket by 0.618 each, 16 to 5e-4 of it (20 us of a 40 ms frame: the fit refines
    the bounce times; 30 steps found the same bounces, at twice the cost)."""
    r = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = lo + (1 - r) * (hi - lo), lo + r * (hi - lo)
    fa, fb = f(a), f(b)
    for _ in range(iterations):
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = lo + (1 - r) * (hi - lo)
            fa = f(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + r * (hi - lo)
            fb = f(b)
    return float(0.5 * (lo + hi))


def _solve(rays: _Rays, bounces, flight, keep, depth, heights, air, previous):
    """The flights' unknowns by weighted linear least squares (module docstring); in
    ``air`` the prior on each flight's acceleration is centred on the drag at the
    ``previous`` solution's mean velocity of that flight."""
    refs = rays.refs(bounces)
    m = 9 if air else 6
    n = m * len(refs)
    rows = np.flatnonzero(keep)
    d = rays.dirs[rows]
    P = (np.eye(3)[None] - d[:, :, None] * d[:, None, :]) / depth[rows, None, None]
    dt = rays.t[rows] - refs[flight[rows]]
    powers = np.stack([np.ones_like(dt), dt, 0.5 * dt**2][:m // 3], axis=1)
    # Row i's block of its flight's unknowns (p, v, a): P_i, P_i dt_i, P_i dt_i^2 / 2.
    A = np.zeros((rows.size, 3, len(refs), m // 3, 3))
    A[np.arange(rows.size), :, flight[rows]] = P[:, :, None, :] * powers[:, None, :, None]
    A = A.reshape(rows.size, 3, n)
    rhs = np.einsum("nij,nj->ni", P, rays.centres[rows] - 0.5 * rays.g * dt[:, None] ** 2)
    blocks, values = [A.reshape(-1, n)], [rhs.reshape(-1)]
    counts = np.bincount(flight[rows], minlength=len(refs))
    tie = _TIE / _median(depth[rows])
    eye = np.eye(3)
    for k, b in enumerate(bounces):
        dt = b - refs[k]
        a = np.zeros((3, n))
        a[:, m * k:m * (k + 1)] = np.concatenate([-eye * power * tie for power in (1.0, dt, 0.5 * dt**2)[:m // 3]], axis=1)
        a[:, m * (k + 1):m * (k + 1) + 3] = eye * tie
        blocks.append(a)
        values.append(0.5 * rays.g * dt**2 * tie)
        if heights is not None and heights[k] is not None:
            a = np.zeros((1, n))
            a[0, m * (k + 1) + 2] = tie
            blocks.append(a)
            values.append(np.array([heights[k] * tie]))
            # Friction changes the velocity along the surface by at most mu (1 + e) |v_n|:
            # a prior on that change keeps a short flight after the bounce from running
            # off along its rays, where its few pixels cannot hold it. Weighted like the
            # flight's rows together, as the air's prior below.
            w = noise_of(rays) / BOUNCE_PRIOR * np.sqrt(counts[k + 1])
            a = np.zeros((2, n))
            a[:, m * (k + 1) + 3:m * (k + 1) + 5] = eye[:2, :2] * w
            a[:, m * k + 3:m * k + 5] = -eye[:2, :2] * w
            if m == 9:
                a[:, m * k + 6:m * k + 8] = -eye[:2, :2] * w * dt
            blocks.append(a)
            values.append(rays.g[:2] * dt * w)
            if rays.e is not None:
                # Tied (RESTITUTION_PRIOR): v_z' + e (v_z + (g_z + a_z) dt) = 0, weighted alike.
                w = noise_of(rays) / RESTITUTION_PRIOR * np.sqrt(counts[k + 1])
                a = np.zeros((1, n))
                a[0, m * (k + 1) + 5] = w
                a[0, m * k + 5] = rays.e * w
                if m == 9:
                    a[0, m * k + 8] = rays.e * w * dt
                blocks.append(a)
                values.append(np.array([-rays.e * w * rays.g[2] * dt]))
    if m == 9:
        # The prior on each flight's air acceleration, weighted like the flight's samples together.
        noise = noise_of(rays)
        ends = np.concatenate([bounces, [rays.t.max()]])
        for f in range(len(refs)):
            mean, middle = np.zeros(3), None
            if previous is not None and previous.size == n:
                middle = rays.velocity_at(previous.reshape(len(refs), 3, 3)[f], 0.5 * (ends[f] - refs[f]))
                mean = rays.drag(middle)  # the drag at mid-flight
            weight = noise * np.sqrt(counts[f]) * air_weights(middle)
            a = np.zeros((3, n))
            a[:, m * f + 6:m * f + 9] = weight
            blocks.append(a)
            values.append(weight @ mean)
    return np.linalg.lstsq(np.concatenate(blocks), np.concatenate(values), rcond=None)[0]
