"""Starting values from the data itself: split a track into flights, fit each flight.

The loss of a bouncing ball is rough in its parameters (a bounce that moves onto the next
tread changes the whole rest of the trajectory), so a fit must start close to the answer.
Flights are easy to read off the data: with gravity known, the height in flight k is

    z(t) = z_k + v_k (t - t_k) - g (t - t_k)^2 / 2,

so ``w(t) = z(t) + g t^2 / 2`` is a straight line within a flight and bends upward at every
bounce (the vertical velocity jumps up by (1 + e) |v|). Flights are the maximal runs on which
w is a line to within the noise. Two consecutive flights meet at the bounce, where the
parabolas intersect; there ``e = -v_after / v_before`` and ``mu_t = u_after / u_before``
(u the horizontal speed, a straight-line fit of x(t) per flight).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Flight:
    """A straight-line fit of w = z + g t^2/2 and of x over the samples of one flight."""

    start: float  # first and last sample time
    stop: float
    w: tuple[float, float]  # w(t) = w[0] + w[1] t
    x: tuple[float, float]  # x(t) = x[0] + x[1] t
    n: int

    def z(self, t, g):
        return self.w[0] + self.w[1] * t - 0.5 * g * t * t

    def vz(self, t, g):
        return self.w[1] - g * t


@dataclass(frozen=True)
class Initial:
    """Starting values read from the flights of one track."""

    e: float
    mu_t: float
    vx0: float
    vz0: float
    x0: float
    z0: float
    flights: tuple[Flight, ...] = field(default=())
    bounces: tuple[float, ...] = field(default=())  # times where consecutive flights meet
    noise: float = float("nan")  # robust noise estimate of the heights (m)


def robust_noise(t, z, g):
    """Noise level of z from second differences of w (robust: median absolute deviation).

    For evenly spaced samples inside a flight the second difference of w is pure noise
    with standard deviation sqrt(6) sigma."""
    w = z + 0.5 * g * t * t
    if len(w) < 5:
        return float("nan")
    d2 = w[2:] - 2 * w[1:-1] + w[:-2]
    mad = np.median(np.abs(d2 - np.median(d2)))
    return float(1.4826 * mad / np.sqrt(6.0))


def _line(t, y):
    A = np.stack([np.ones_like(t), t], axis=1)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return coef


def split_flights(t, x, z, g, *, noise=None, min_points=4):
    """Greedy segmentation of a track into flights (see the module docstring).

    A run grows while the next sample lies on the run's line of w to within
    ``max(6 sigma, 1 mm)``; a sample off the line is an outlier if the one after it is back on
    the line, and a bounce if the next ``min_points - 1`` samples also leave it upward. Runs
    shorter than ``min_points``, or without vertical motion beyond the noise (a height range
    below 8 sigma, at least 3 mm: the unresolved tail of a Zeno series, or a ball at rest),
    end the segmentation. (The range of pure noise over a hundred samples is about 5 sigma;
    the bound used to be 3 times the line tolerance, 18 sigma, which in 3 mm noise ended the
    segmentation at the first flight lower than 5 cm.)
    """
    ok = np.isfinite(t) & np.isfinite(x) & np.isfinite(z)
    t, x, z = t[ok], x[ok], z[ok]
    sigma = robust_noise(t, z, g) if noise is None else noise
    level = sigma if np.isfinite(sigma) else 0.002
    tol = max(6.0 * level, 1e-3)
    still = max(8.0 * level, 3e-3)  # a height range below this is no vertical motion
    w = z + 0.5 * g * t * t
    flights = []
    i, n = 0, len(t)
    while i + min_points <= n:
        members = list(range(i, i + min_points))
        coef = _line(t[members], w[members])
        if np.max(np.abs(w[members] - (coef[0] + coef[1] * t[members]))) > 4 * tol:
            i += 1  # the seed of a run straddles a bounce or an outlier: move on
            continue
        j = i + min_points
        while j < n:
            res = w[j] - (coef[0] + coef[1] * t[j])
            if abs(res) <= tol:
                members.append(j)
                coef = _line(t[members], w[members])
                j += 1
                continue
            ahead = range(j + 1, min(j + min_points, n))
            back = [k for k in ahead if abs(w[k] - (coef[0] + coef[1] * t[k])) <= tol]
            if back:  # an isolated outlier
                j += 1
                continue
            break
        if np.ptp(z[members]) < still:
            if not flights:  # still in the hand before the release: skip
                i = j
                continue
            break  # no vertical motion: the ball rests, or its bounces are no longer resolved
        xc = _line(t[members], x[members])
        flights.append(Flight(float(t[members[0]]), float(t[members[-1]]), tuple(coef), tuple(xc), len(members)))
        i = j
    return flights, sigma


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
        mad = 1.4826 * np.median(np.abs(res - np.median(res)))
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
