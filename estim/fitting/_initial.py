"""Starting values from the data itself: split a track into flights, fit each flight.

The loss of a bouncing ball is rough in its parameters (a bounce that moves onto the next
tread changes the whole rest of the trajectory), so a fit must start close to the answer.
Flights are easy to read off the data: with gravity known, the height in flight k is

    z(t) = z_k + v_k (t - t_k) - g (t - t_k)^2 / 2,

so ``w(t) = z(t) + g t^2 / 2`` is a straight line within a flight and bends upward at every
bounce (the vertical velocity jumps up by (1 + e) |v|). Flights are the maximal runs on which
w is a line to within the noise. Two consecutive flights meet at the bounce, where the
parabolas intersect; there ``e = -v_after / v_before`` and ``mu_t = u_after / u_before``
(u the horizontal speed, a straight-line fit of x(t) per flight). The flights and the
noise level come from ``estim.tracks._flights`` (:func:`split_flights`, ``robust_noise``),
which the track readers' flight analysis shares.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ..tracks._flights import Flight, robust_std, split_flights


@dataclass(frozen=True)
class Initial:
    """Starting values read from the flights of one track.

    The release state is in the scene's coordinates. ``y0`` and ``vy0`` are ``None`` where
    the data does not say (a track without y: the fit then takes the ball's y in the
    scene and no lateral speed). ``flights`` are fitted in the ball's plane of travel: their
    ``x`` lines are the horizontal coordinate along ``direction`` (the unit horizontal
    vector of the motion; ``(1, 0, 0)`` for a track without y), their ``w`` lines the height.
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
E_RANGE, MU_RANGE = (0.05, 0.99), (0.5, 1.0)
E_DEFAULT, MU_DEFAULT = 0.7, 0.95
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
    es, mus, bounces = [], [], []
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
        vx0=float(f0.x[1]),
        vz0=float(f0.vz(t0, g)),
        x0=float(f0.x[0] + f0.x[1] * t0),
        z0=float(f0.z(t0, g)),
        flights=tuple(flights),
        bounces=tuple(bounces),
        noise=sigma,
    )


def release_start(t, position, gravity, *, release_time=0.0, e_default=E_DEFAULT, mu_default=MU_DEFAULT):
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

    A ball thrown along y gets the same starts as one thrown along x (the projection on x
    would read no horizontal speed, and so no mu_t). A track without y (a side view) is
    read in the x-z plane as it is: ``initial_guess(t, x, z, |g|)``, which needs gravity
    along -z.

    Args:
        t: ``(n,)`` sample times (s).
        position: ``(n, 3)`` positions (m), NaN where a coordinate was not measured.
        gravity: the gravity vector (m/s^2), e.g. ``(0, 0, -9.81)``.
        release_time: the model's t = 0 on the data's clock (s).

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
    inside = np.isfinite(t) & np.isfinite(lateral) & (t >= f0.start) & (t <= f0.stop)
    if inside.sum() >= 2:
        design = np.stack([np.ones(int(inside.sum())), t[inside]], axis=1)
        l0, vl = np.linalg.lstsq(design, lateral[inside], rcond=None)[0]
    else:  # no lateral sample in the first flight: no lateral speed to read
        l0, vl = float(np.nanmedian(lateral)), 0.0
    t0 = release_time
    release = init.x0 * u + (l0 + vl * t0) * w + init.z0 * up
    speed = init.vx0 * u + vl * w + init.vz0 * up
    return dataclasses.replace(
        init, x0=float(release[0]), y0=float(release[1]), z0=float(release[2]),
        vx0=float(speed[0]), vy0=float(speed[1]), vz0=float(speed[2]), direction=tuple(float(c) for c in u),
    )


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
