"""Starting values from the data itself: split a track into flights, fit each flight.

The loss of a bouncing ball is rough in its parameters (a bounce that moves onto the next
tread changes the whole rest of the trajectory), so a fit must start close to the answer.
Flights are easy to read off the data: with gravity known, the height in flight k is

    z(t) = z_k + v_k (t - t_k) - g (t - t_k)^2 / 2,

so ``w(t) = z(t) + g t^2 / 2`` is a straight line within a flight and bends upward at every
bounce (the vertical velocity jumps up by (1 + e) |v|). Flights are the maximal runs on which
w is a line to within the noise. Two consecutive flights meet at the bounce, where the
parabolas intersect; there ``e = -v_after / v_before`` and ``mu_t = u_after / u_before``
(u the horizontal speed, a straight-line fit of x(t) per flight), and for the friction law
(``estim.FrictionLaw``: an impact that slides throughout changes the tangential velocity by
mu times the normal impulse) ``mu = |u_after - u_before| / (v_after - v_before)``, a lower
bound where the ball grips. In air, the spin of the first flight comes from its curvature
(:func:`spin_start`). The flights and the
noise level come from ``estim.tracks._flights`` (:func:`split_flights`, ``robust_noise``),
which the track readers' flight analysis shares.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..model._air import Air, spin_for_lift
from ..tracks._flights import Flight, robust_noise, robust_std, split_flights, still_range


class Rest(NamedTuple):
    """A run at a track's start without vertical motion (``_still_start``): a ball that
    slides or rolls on a surface before it leaves the edge, or is held still. Its first and
    last sample times, and the release state read from it at the release time: the
    run's mean height, its horizontal line, no vertical speed (in the scene's coordinates;
    ``None`` where the data do not say, as in ``Initial``)."""

    start: float
    stop: float
    position: tuple[float, float | None, float]
    velocity: tuple[float, float | None, float]


@dataclass(frozen=True)
class Initial:
    """Starting values read from the flights of one track.

    The release state is in the scene's coordinates. ``y0`` and ``vy0`` are ``None`` where
    the data does not say (a track without y: the fit then takes the ball's y in the
    scene and no lateral speed). ``flights`` are fitted in the ball's plane of travel: their
    ``x`` lines are the horizontal coordinate along ``direction`` (the unit horizontal
    vector of the motion; ``(1, 0, 0)`` for a track without y), their ``w`` lines the height.
    The release state is the first flight's, carried back to the release; where the track
    starts with a run without vertical motion (``rest``), the fit may release the ball from
    that run instead (:meth:`released_from_rest`, where a surface holds it).
    """

    e: float
    mu_t: float
    vx0: float
    vz0: float
    x0: float
    z0: float
    flights: tuple[Flight, ...] = field(default=())
    bounces: tuple[float, ...] = field(default=())  # times where consecutive flights meet
    noise: float = float("nan")  # robust noise estimate of the heights (m)
    y0: float | None = None
    vy0: float | None = None
    direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    mu: float = float("nan")  # the friction law's coefficient (FRICTION_DEFAULT without a bounce)
    spin: tuple[float | None, float | None, float | None] = (None, None, None)  # rad/s (spin_start)
    rest: Rest | None = None  # a run without vertical motion before the first flight (the release state above is the flight's)

    def released_from_rest(self, height: float) -> Initial:
        """The same start released from its ``rest`` at ``height`` (the centre's on the
        surface it rests on; ``estim.fitting._fit``)."""
        (x0, y0, _), (vx0, vy0, _) = self.rest.position, self.rest.velocity
        return dataclasses.replace(self, x0=x0, y0=y0, z0=float(height), vx0=vx0, vy0=vy0, vz0=0.0)

    @property
    def position(self) -> tuple[float, float | None, float]:
        """The release position (x0, y0, z0) read from the data (m)."""
        return (self.x0, self.y0, self.z0)

    @property
    def velocity(self) -> tuple[float, float | None, float]:
        """The release velocity (vx0, vy0, vz0) read from the data (m/s)."""
        return (self.vx0, self.vy0, self.vz0)


# Where a start for e or mu_t is clipped to (a median of one or two noisy bounces can fall
# outside), and the value taken without a resolved bounce.
E_RANGE, MU_RANGE, FRICTION_RANGE = (0.05, 0.99), (0.5, 1.0), (0.02, 0.8)
# FRICTION_DEFAULT: a table-tennis ball on a table (Nakashima et al. 2010 measure 0.25).
E_DEFAULT, MU_DEFAULT, FRICTION_DEFAULT = 0.7, 0.95, 0.25
# Residuals about the flights (x and z) from which their spread is the noise level; with
# fewer, the larger of that and the second-difference estimate.
TRUSTED_RESIDUALS = 60


def initial_guess(t, x, z, g, *, release_time=0.0, e_default=E_DEFAULT, mu_default=MU_DEFAULT):
    """Starting values (e, mu_t, vx0, vz0, x0, z0) for one track, from its flights.

    e and mu_t are the medians over the resolved bounces (clipped to ``E_RANGE`` and
    ``MU_RANGE``); without a resolved bounce they take the defaults, and the fit reports them
    as not identifiable from the data.
    """
    flights, sigma = split_flights(np.asarray(t, float), np.asarray(x, float), np.asarray(z, float), g)
    if not flights:
        raise ValueError("no flight could be resolved in this track (too few valid samples?)")
    f0 = flights[0]
    t0 = release_time
    rest = _still_start(np.asarray(t, float), np.asarray(x, float), np.asarray(z, float), t0, f0.start, sigma)
    es, mus, frictions, bounces = [], [], [], []
    for a, b in zip(flights[:-1], flights[1:], strict=True):
        # The parabolas meet where their lines of w meet.
        dv = b.w[1] - a.w[1]
        if dv <= 0:
            continue
        tb = (a.w[0] - b.w[0]) / dv
        if not (a.start < tb < b.stop):
            continue
        before, after = a.vz(tb, g), b.vz(tb, g)
        if before < -0.3 and after > 0:  # a bounce resolved by the frame rate
            es.append(-after / before)
            bounces.append(tb)
            if abs(a.x[1]) > 1e-3:
                mus.append(b.x[1] / a.x[1])
            frictions.append(abs(b.x[1] - a.x[1]) / (after - before))
    # The noise level: robust spread of the samples about their flight's line of w
    # (second differences, used to split the flights, also see the curvature across
    # missing frames and rests, and overestimate it).
    tt, xx, zz = (np.asarray(a, float) for a in (t, x, z))
    ok = np.isfinite(tt) & np.isfinite(zz)
    res = []
    for f in flights:
        inside = ok & (tt >= f.start) & (tt <= f.stop) & np.isfinite(xx)
        res.append(zz[inside] + 0.5 * g * tt[inside] ** 2 - (f.w[0] + f.w[1] * tt[inside]))
        res.append(xx[inside] - (f.x[0] + f.x[1] * tt[inside]))
    res = np.concatenate(res) if res else np.zeros(0)
    if res.size > 4 * len(flights) + 4:
        mad = robust_std(res)
        from_flights = float(mad * np.sqrt(res.size / (res.size - 4 * len(flights))))
        # Few samples in flights (a ball that soon rests): do not trust a small estimate.
        sigma = from_flights if res.size >= TRUSTED_RESIDUALS or not np.isfinite(sigma) else max(from_flights, sigma)
    e = float(np.clip(np.median(es), *E_RANGE)) if es else e_default
    mu = float(np.clip(np.median(mus), *MU_RANGE)) if mus else mu_default
    return Initial(
        e=e,
        mu_t=mu,
        mu=float(np.clip(np.median(frictions), *FRICTION_RANGE)) if frictions else FRICTION_DEFAULT,
        vx0=float(f0.x[1]),
        vz0=float(f0.vz(t0, g)),
        x0=float(f0.x[0] + f0.x[1] * t0),
        z0=float(f0.z(t0, g)),
        flights=tuple(flights),
        bounces=tuple(bounces),
        noise=sigma,
        rest=rest,
    )


# The fewest samples of a still run at a track's start (``_still_start``).
STILL_SAMPLES = 3


def _still_start(t, x, z, t0, first_flight, sigma) -> Rest | None:
    """The run at a track's start without vertical motion, if there is one: the valid
    samples from the release ``t0`` to the first flight, at least ``STILL_SAMPLES`` of
    them, whose heights stay within ``still_range(sigma)``. ``split_flights`` skips such a
    run (no flight), and the first flight's parabola carried back over it to ``t0`` misses
    every sample of it where the ball lay on a surface: one that slid off a tread 1 s after
    the release read as thrown up at 10 m/s from 5 m under it. The fit decides whether a
    surface holds the run (``estim.fitting._fit``): a ball held still in the air is
    better started from the flight's parabola, which at least meets the flight."""
    run = np.isfinite(t) & np.isfinite(x) & np.isfinite(z) & (t >= t0) & (t < first_flight)
    if run.sum() < STILL_SAMPLES or np.ptp(z[run]) >= still_range(sigma):
        return None
    x0, vx0 = np.polynomial.polynomial.polyfit(t[run] - t0, x[run], 1)
    return Rest(float(t[run][0]), float(t[run][-1]), (float(x0), None, float(np.mean(z[run]))), (float(vx0), None, 0.0))


def release_start(t, position, gravity, *, release_time=0.0, e_default=E_DEFAULT, mu_default=MU_DEFAULT,
                  curved=False):
    """Starting values for one track in the ball's plane of travel, in the scene's coordinates.

    Gravity ``g`` (a vector, m/s^2) sets the vertical ``up = -g / |g|``; a sample ``p`` has
    the height ``h = p . up`` and the horizontal part ``p_h = p - h up``. The direction of
    travel ``u`` is the horizontal direction along which the samples spread most (the first
    principal axis of ``p_h``, oriented so that the ball moves along +u as time goes on), and
    ``w = up x u`` the lateral direction. In the vertical plane of travel the track is
    ``(s, h) = (p_h . u, p . up)``: :func:`initial_guess` splits it into flights and reads
    e, mu_t (from the speed along u, which an impact scales by mu_t), the speed along u and
    the release point in that plane; a straight line through the lateral coordinate
    ``l = p_h . w`` of the first flight gives the lateral release point and speed. Then

        position = s0 u + l0 w + h0 up,    velocity = v_s u + v_l w + v_h up.

    The friction law's mu comes from the velocity jump at each bounce (``_jump_at``), and
    so does e where the flights are ``curved`` (a scene with air: drag and the Magnus force
    bend a flight away from its parabola, and the flights' lines of w misread the jump).
    There the release state comes from the first samples alone (``_release_at``), and the
    noise level from third differences of each coordinate
    (``robust_noise``: blind to a flight's curvature, which the spread about the flights'
    lines of w would count as noise), the root mean square over the coordinates.

    A ball thrown along y gets the same starts as one thrown along x (the projection on x
    would read no horizontal speed, and so no mu_t). A track without y (a side view) is
    read in the x-z plane as it is: ``initial_guess(t, x, z, |g|)``, which needs gravity
    along -z.

    Args:
        t: ``(n,)`` sample times (s).
        position: ``(n, 3)`` positions (m), NaN where a coordinate was not measured.
        gravity: the gravity vector (m/s^2), e.g. ``(0, 0, -9.81)``.
        release_time: the model's t = 0 on the data's clock (s).
        curved: the flights are not parabolas (air): e from the velocities at the bounces.

    Raises:
        ValueError: a zero or non-finite gravity; a track without y under a gravity that
            does not point along -z; no flight resolved in the track.
    """
    t = np.asarray(t, dtype=np.float64)
    pos = np.asarray(position, dtype=np.float64)
    gravity = np.asarray(gravity, dtype=np.float64)
    g = float(np.linalg.norm(gravity))
    if not (math.isfinite(g) and g > 0):
        raise ValueError(f"gravity must be a finite non-zero vector, got {gravity.tolist()}")
    up = -gravity / g
    options = dict(release_time=release_time, e_default=e_default, mu_default=mu_default)
    if not np.isfinite(pos[:, 1]).any():
        if not np.array_equal(up, (0.0, 0.0, 1.0)):
            raise ValueError(f"a track without y (a side view in the x-z plane) needs gravity along -z, "
                             f"got {gravity.tolist()}")
        return initial_guess(t, pos[:, 0], pos[:, 2], g, **options)
    h = pos @ up
    horizontal = pos - h[:, None] * up
    u = _direction_of_travel(t, horizontal, up)
    w = np.cross(up, u)
    init = initial_guess(t, horizontal @ u, h, g, **options)
    f0 = init.flights[0]
    lateral = horizontal @ w
    t0 = release_time
    l0, vl = _line_between(t, lateral, f0.start, f0.stop)
    release = init.x0 * u + (l0 + vl * t0) * w + init.z0 * up
    speed = init.vx0 * u + vl * w + init.vz0 * up
    if init.rest is not None:  # in the scene's coordinates too, its lateral line through the first flight
        (s0, _, h0), (vs, _, _) = init.rest.position, init.rest.velocity
        l0, vl = _line_between(t, lateral, init.rest.start, f0.stop)
        on = s0 * u + (l0 + vl * t0) * w + h0 * up
        init = dataclasses.replace(init, rest=init.rest._replace(
            position=tuple(float(c) for c in on), velocity=tuple(float(c) for c in vs * u + vl * w)))
    edges = (-np.inf, *init.bounces, np.inf)
    jumps = [j for k, tb in enumerate(init.bounces) if (j := _jump_at(t, pos, tb, up, edges[k], edges[k + 2])) is not None]
    e, noise = init.e, init.noise
    if curved:
        release, speed = _release_at(t, pos, release_time, edges[1], release, speed)
        if jumps:
            e = float(np.clip(np.median([j[0] for j in jumps]), *E_RANGE))
        finite = np.isfinite(pos)
        levels = [robust_noise(pos[finite[:, k], k], order=3, t=t[finite[:, k]]) for k in range(3)]
        levels = [s for s in levels if np.isfinite(s)]
        noise = float(np.sqrt(np.mean(np.square(levels)))) if levels else noise
    return dataclasses.replace(
        init, x0=float(release[0]), y0=float(release[1]), z0=float(release[2]),
        vx0=float(speed[0]), vy0=float(speed[1]), vz0=float(speed[2]), direction=tuple(float(c) for c in u),
        e=e, noise=noise, mu=float(np.clip(np.median([j[1] for j in jumps]), *FRICTION_RANGE)) if jumps else init.mu,
    )


def _line_between(t, y, start, stop) -> tuple[float, float]:
    """The least-squares line ``y = c0 + c1 t`` through the samples from ``start`` to
    ``stop``; with fewer than two, the median of ``y`` and no slope."""
    inside = np.isfinite(t) & np.isfinite(y) & (t >= start) & (t <= stop)
    if inside.sum() < 2:
        return float(np.nanmedian(y)), 0.0
    design = np.stack([np.ones(int(inside.sum())), t[inside]], axis=1)
    c0, c1 = np.linalg.lstsq(design, y[inside], rcond=None)[0]
    return float(c0), float(c1)


# Half-width (s) of the windows on either side of a bounce whose samples give the velocities
# just before and after it, and the samples each window needs.
BOUNCE_WINDOW, BOUNCE_SAMPLES = 0.1, 6


def _release_at(t, pos, t0, bounce, position, velocity):
    """The release state at ``t0`` from a quadratic in time per coordinate over the samples
    of the first ``BOUNCE_WINDOW`` seconds (before the first bounce): in air, a straight line
    through a whole flight reads its mean velocity, which drag has already slowed. A
    coordinate with too few samples keeps ``position`` and ``velocity``."""
    position, velocity = np.array(position, dtype=np.float64), np.array(velocity, dtype=np.float64)
    for k in range(3):
        ok = np.isfinite(t) & np.isfinite(pos[:, k]) & (t < bounce)
        near = ok & (t <= t[ok].min() + BOUNCE_WINDOW) if ok.any() else ok
        if near.sum() < BOUNCE_SAMPLES:
            continue
        dt = t[near] - t0
        c = np.linalg.lstsq(np.stack([np.ones(dt.size), dt, dt**2], axis=1), pos[near, k], rcond=None)[0]
        position[k], velocity[k] = c[0], c[1]
    return position, velocity


def _jump_at(t, pos, tb, up, before, after) -> tuple[float, float] | None:
    """e and the friction law's mu at the bounce at ``tb``, from the velocities just before
    and after it: a quadratic in time per coordinate over the samples within
    ``BOUNCE_WINDOW`` on each side, and between the neighbouring bounces at ``before`` and
    ``after`` (in air a flight's line of w, or its straight line in x, would mix the drag's
    deceleration and the Magnus force into the jump). ``e = -v_n+ / v_n-``; an impact that
    slides throughout changes the tangential velocity by mu times the change of the normal
    one, ``mu = |dv_t| / dv_n``; where the ball grips it changes less, so that start is a
    lower bound, on the side where the loss still depends on mu. ``None`` where a window
    has too few samples or the normal velocity does not turn."""
    velocities = []
    for side in (-1, 1):
        near = (side * (t - tb) > 0) & (np.abs(t - tb) <= BOUNCE_WINDOW) & (t > before) & (t < after) \
            & np.all(np.isfinite(pos), axis=1)
        if near.sum() < BOUNCE_SAMPLES:
            return None
        dt = t[near] - tb
        design = np.stack([np.ones(dt.size), dt, dt**2], axis=1)
        velocities.append(np.linalg.lstsq(design, pos[near], rcond=None)[0][1])
    v_in, v_out = float(velocities[0] @ up), float(velocities[1] @ up)
    if not (v_in < 0 < v_out):
        return None
    jump = velocities[1] - velocities[0]
    normal = v_out - v_in
    return -v_out / v_in, float(np.linalg.norm(jump - normal * up) / normal)


def _direction_of_travel(t, horizontal, up):
    """Unit horizontal vector along which the samples spread most (first principal axis of
    their horizontal parts), pointing the way the ball moves; the first horizontal axis of
    the scene where the samples do not move horizontally at all."""
    ok = np.isfinite(t) & np.all(np.isfinite(horizontal), axis=1)
    d = horizontal[ok] - horizontal[ok].mean(axis=0) if ok.sum() >= 2 else np.zeros((0, 3))
    if not np.any(d):
        axes = np.eye(3) - np.outer(up, up)  # the scene's axes projected on the horizontal plane
        u = axes[np.argmax(np.linalg.norm(axes, axis=1))]
        return u / np.linalg.norm(u)
    u = np.linalg.svd(d, full_matrices=False)[2][0]
    u = u - (u @ up) * up
    u = u / np.linalg.norm(u)
    return -u if np.sum((d @ u) * (t[ok] - t[ok].mean())) < 0 else u


# Samples a flight needs for its curvature to give a spin start.
CURVATURE_SAMPLES = 8


def spin_start(init: Initial, t, position, gravity, air: Air, radius: float, mass: float,
               lift_factor: float = 1.0) -> tuple[float, float, float]:
    """The release spin (rad/s) read off the curvature of the flight before the first
    resolved bounce: a quadratic in time per coordinate gives the mean velocity v and
    acceleration a over it; what gravity leaves, ``a - g``, is drag (along -v) and the
    Magnus force (across v), and the part across v inverts the lift law
    (``estim.model._air.spin_for_lift``). The spin along v does nothing in flight and
    starts at 0; so does the spin of a flight too short to curve measurably
    (fewer than ``CURVATURE_SAMPLES`` samples). A coordinate the track lacks (y in a side
    view) counts as not moving."""
    t = np.asarray(t, dtype=np.float64)
    pos = np.asarray(position, dtype=np.float64)
    end = init.bounces[0] if init.bounces else np.inf
    inside = (t < end) & np.all(np.isfinite(pos[:, [0, 2]]), axis=1)
    if inside.sum() < CURVATURE_SAMPLES:
        return (0.0, 0.0, 0.0)
    tm = float(np.mean(t[inside]))
    design = np.stack([np.ones(int(inside.sum())), t[inside] - tm, 0.5 * (t[inside] - tm) ** 2], axis=1)
    velocity, acceleration = np.zeros(3), np.zeros(3)
    for k in range(3):
        ok = np.isfinite(pos[inside, k])
        if ok.sum() >= CURVATURE_SAMPLES:
            coef = np.linalg.lstsq(design[ok], pos[inside, k][ok], rcond=None)[0]
            velocity[k], acceleration[k] = coef[1], coef[2]
    if not np.isfinite(pos[:, 1]).any():
        acceleration[1] = -np.asarray(gravity, dtype=np.float64)[1]  # no lift read along y
    spin = spin_for_lift(air, radius, mass, velocity, acceleration - np.asarray(gravity, dtype=np.float64), lift_factor)
    return tuple(float(w) for w in spin)
