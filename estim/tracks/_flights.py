"""Flights of a tracked ball: where they start and end, what they fit, how noisy the data is.

A ball between two bounces is in free flight: its height is a parabola in time. Everything
that reads a track's physics before a model is fitted (the fit's starting values, the unit
check of a track file, the pixel scale, the contact row and the flight-time restitution of
a pixel track) starts by cutting the track into flights. This module is that step, in plain
numpy; the readers (``_csv``, ``_pixels``) and the fit's starts (``estim.fitting._initial``)
call it.

**One noise estimator**, :func:`robust_noise`: a signal that is a polynomial of degree
``k - 1`` between a few rare breaks has k-th differences that are pure noise away from the
breaks; for white noise of standard deviation sigma the k-th difference has standard
deviation ``sqrt(C(2k, k)) sigma`` (sqrt 6 for k = 2, sqrt 20 for k = 3), so

    sigma = 1.4826 MAD(Delta^k y) / sqrt(C(2k, k)),

robust to the breaks (bounces) and to outliers through the median absolute deviation
(:func:`robust_std`, 1.4826 MAD: the standard deviation of Gaussian data). Where a sample
is missing, the windows across the gap are divided differences scaled alike (the
callers pass the times). Known gravity
makes ``w = z + g t^2 / 2`` a line in flight (k = 2); unknown gravity leaves a parabola
(k = 3).

**Two splitters, because they assume different things** (both here, both using the
estimator above):

- :func:`split_flights` knows gravity in the data's units: ``w = z + g t^2 / 2`` is a
  straight line within a flight and bends upward at every bounce, so flights are the
  maximal runs on which w is a line to within the noise. The fit's starting values
  (``estim.fitting._initial``) and the release frame of a pixel fit use it.
- :func:`fit_flights` does not know gravity in the data's units, because what it serves
  measures it: the pixel scale (gravity in px/s^2 gives metres per pixel), the unit check
  of a track file (an acceleration 1000 g means millimetres) and the contact row. Its
  flights are the runs between sharp local maxima of a downward coordinate, each fitted
  by a robust parabola of free curvature.

They stay two: a splitter that assumes g cannot measure g, and one that does not cannot
use g where it is known. Their flight boundaries differ (``fit_flights`` leaves the
bounce samples out of both flights and starts the first flight where the ball clearly
falls; ``split_flights`` keeps every sample that lies on a line and skips a run without
vertical motion), and the fit's starting values, hence every fitted number, and the pixel
scale, hence every pixel fit, depend on those boundaries bit for bit. What they share is
here once: the noise level and the robust spread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

__all__ = [
    "robust_std",
    "robust_noise",
    "Flight",
    "still_range",
    "split_flights",
    "FlightFit",
    "fit_flights",
    "flight_contacts",
]

# 1 / Phi^-1(3/4): the standard deviation of Gaussian data over its median absolute deviation.
MAD_TO_STD = 1.4826


# ---------------------------------------------------------------------------------------
# The noise level
# ---------------------------------------------------------------------------------------


def robust_std(r) -> float:
    """Robust standard deviation of a sample: ``1.4826 median(|r - median(r)|)``.

    Equal to the standard deviation for Gaussian data; a minority of outliers (up to half
    the sample) does not move it far.
    """
    r = np.asarray(r)
    return MAD_TO_STD * np.median(np.abs(r - np.median(r)))


def robust_noise(y, *, order: int, t=None) -> float:
    """Noise level of ``y`` from its ``order``-th differences (see the module docstring).

    ``sigma = robust_std(Delta^k y) / sqrt(C(2k, k))`` with ``k = order``: exact for white
    noise on a signal that is a polynomial of degree below ``order`` between rare breaks.
    The differences are the binomial stencil ``sum_j (-1)^j C(k, j) y[i + k - j]``,
    accumulated from ``j = 0``, for evenly spaced samples. With the sample times ``t``, a
    window of ``k + 1`` samples whose steps differ (a frame missing, a lost detection)
    gives instead its k-th divided difference over its standard deviation in units of
    sigma: ``sum_j w_j y_j / sqrt(sum_j w_j^2)`` with ``w_j = 1 / prod_{m != j} (t_j -
    t_m)``, which vanishes on any polynomial of degree below k at any spacing and on even
    spacing is the stencil's over ``sqrt(C(2k, k))`` (Newton's divided differences; the
    variance of a linear form of white noise). Without ``t`` the samples are taken as
    evenly spaced: the stencil across a gap would read the signal's own curvature as
    noise (three frames missing of 15 read 2 px of noise as 6 to 8 px).

    Returns NaN when ``y`` has fewer than ``order + 3`` samples, or fewer than three
    differences are finite (a median of fewer than three is no estimate).
    """
    y = np.asarray(y, dtype=np.float64)
    n = y.shape[0]
    if n < order + 3:
        return float("nan")
    d = y[order:]
    for j in range(1, order + 1):
        c = math.comb(order, j) * y[order - j: n - j]
        d = d - c if j % 2 else d + c
    scale = math.sqrt(math.comb(2 * order, order))
    if t is not None:
        t = np.asarray(t, dtype=np.float64)
        steps = np.lib.stride_tricks.sliding_window_view(np.diff(t), order)
        even = np.all(np.abs(steps - steps[:, :1]) <= 1e-9 * np.abs(steps[:, :1]), axis=1) & (steps[:, 0] > 0)
        if not even.all():
            d = np.where(even, d / scale, _divided(y, t, order))
            d = d[np.isfinite(d)]
            return float(robust_std(d)) if d.size >= 3 else float("nan")
    return float(robust_std(d) / scale)


def _divided(y, t, order: int) -> np.ndarray:
    """Every window's ``order``-th divided difference of ``y`` at the times ``t`` over its
    standard deviation per unit of white noise (:func:`robust_noise`); NaN where two
    times of a window coincide."""
    tw = np.lib.stride_tricks.sliding_window_view(t, order + 1)
    gaps = tw[:, :, None] - tw[:, None, :]
    gaps[:, np.arange(order + 1), np.arange(order + 1)] = 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        w = 1.0 / np.prod(gaps, axis=2)
        return np.sum(w * np.lib.stride_tricks.sliding_window_view(y, order + 1), axis=1) / np.sqrt(np.sum(w * w, axis=1))


# ---------------------------------------------------------------------------------------
# Flights with gravity known: lines of w = z + g t^2 / 2
# ---------------------------------------------------------------------------------------


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


def _line(t, y):
    """The least-squares line ``y = c0 + c1 t``, in closed form about the mean time (a
    slope of 0 where every t is the same)."""
    tm, ym = t.mean(), y.mean()
    dt = t - tm
    ss = dt @ dt
    c1 = (dt @ (y - ym)) / ss if ss > 0 else 0.0
    return np.array([ym - c1 * tm, c1])


def still_range(sigma: float) -> float:
    """The height range (m) below which a run of samples has no vertical motion at the
    noise level ``sigma`` (2 mm where that is NaN): ``max(8 sigma, 3 mm)`` (the range of
    pure noise over a hundred samples is about 5 sigma)."""
    return max(8.0 * (sigma if np.isfinite(sigma) else 0.002), 3e-3)


def split_flights(t, x, z, g, *, noise=None, min_points=4):
    """Greedy segmentation of a track into flights, with gravity ``g`` known.

    Within a flight ``w = z + g t^2 / 2`` is a straight line; at a bounce it bends upward
    (the vertical velocity jumps up by ``(1 + e) |v|``). A run grows while the next sample
    lies on the run's line of w to within ``max(6 sigma, 1 mm)``; a sample off the line is
    an outlier if the one after it is back on the line, and a bounce if the next
    ``min_points - 1`` samples also leave it upward. Runs shorter than ``min_points``, or
    without vertical motion beyond the noise (a height range below 8 sigma, at least 3 mm:
    the unresolved tail of a Zeno series, or a ball at rest), end the segmentation. (The
    range of pure noise over a hundred samples is about 5 sigma; the bound used to be 3
    times the line tolerance, 18 sigma, which in 3 mm noise ended the segmentation at the
    first flight lower than 5 cm.)

    Args:
        t, x, z: sample times (s), horizontal and vertical positions (m); rows with a NaN
            are left out.
        g: gravity (m/s^2), pointing along -z.
        noise: the noise level sigma of z (m); default :func:`robust_noise` of w
            (second differences), 2 mm where that has too few samples.
        min_points: the fewest samples of a flight.

    Returns:
        ``(flights, sigma)``: the :class:`Flight` list in time order, and the noise level
        used (NaN when it could not be estimated).
    """
    ok = np.isfinite(t) & np.isfinite(x) & np.isfinite(z)
    t, x, z = t[ok], x[ok], z[ok]
    w = z + 0.5 * g * t * t
    sigma = robust_noise(w, order=2, t=t) if noise is None else noise
    level = sigma if np.isfinite(sigma) else 0.002
    tol = max(6.0 * level, 1e-3)
    still = still_range(sigma)
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


# ---------------------------------------------------------------------------------------
# Flights with gravity unknown: parabolas of a coordinate that grows downward
# ---------------------------------------------------------------------------------------


class FlightFit(NamedTuple):
    """A robust parabola fit ``b(t) = b0 + v (t - t_ref) + c (t - t_ref)^2`` of one flight.

    ``b`` grows downward (pixels, or ``-z``), so ``c = g / (2 s)`` with s the scale.
    A fit with air drag has a fourth coefficient k: ``b'' = 2c - k b'|b'|`` (k in 1/px);
    ``t_vertex`` and calling the fit then use the parabola part only.
    """

    start: int  # first sample index of the flight (inclusive)
    stop: int  # last sample index + 1
    used: np.ndarray  # bool (stop - start,): samples kept by the robust fit
    t_ref: float
    coef: np.ndarray  # (b0, v, c)
    cov: np.ndarray  # 3x3 covariance of coef
    sigma: float  # robust residual scale of the kept samples

    @property
    def n(self) -> int:
        return int(np.sum(self.used))

    @property
    def n_outliers(self) -> int:
        return int(self.used.size - np.sum(self.used))

    @property
    def curvature(self) -> float:
        return float(self.coef[2])

    @property
    def curvature_stderr(self) -> float:
        return float(math.sqrt(max(self.cov[2, 2], 0.0)))

    @property
    def t_vertex(self) -> float:
        """Time of the apex (the vertex of the parabola)."""
        return float(self.t_ref - self.coef[1] / (2.0 * self.coef[2]))

    def __call__(self, t):
        dt = np.asarray(t) - self.t_ref
        return self.coef[0] + self.coef[1] * dt + self.coef[2] * dt**2  # parabola part


def _drag_column(x, v):
    """Double time integral of ``-v|v|`` over the sample times ``x`` (trapezoid rule)."""
    w = -v * np.abs(v)
    first = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(x))])
    second = np.concatenate([[0.0], np.cumsum(0.5 * (first[1:] + first[:-1]) * np.diff(x))])
    return first, second


def _model_velocity(x, coef, first):
    v = coef[1] + 2.0 * coef[2] * x
    if coef.size > 3:
        v = v + coef[3] * first
    return v


def _robust_parabola(t, b, *, cut: float = 5.0, max_iter: int = 20, floor: float = 0.0,
                     drag: bool = False):
    """Least squares parabola, dropping samples with |residual| > cut * (1.4826 MAD).

    With ``drag``, a fourth column ``D(t)``, the double integral of ``-v|v|`` along the
    fitted motion, models quadratic air drag ``b'' = 2c - k b'|b'|`` (``coef[3] = k`` in
    1/px); the column is refreshed from the current fit at every iteration.
    """
    t_ref = float(np.mean(t))
    x = t - t_ref
    A = np.stack([np.ones_like(x), x, x * x], axis=1)
    used = np.ones(t.size, dtype=bool)
    coef, *_ = np.linalg.lstsq(A, b, rcond=None)
    first = np.zeros_like(x)

    def refresh(coef, first):
        if not drag:
            return A, first
        first, second = _drag_column(x, _model_velocity(x, coef, first))
        return np.concatenate([A[:, :3], second[:, None]], axis=1), first

    if drag:
        for _ in range(6):
            A, first = refresh(coef, first)
            coef, *_ = np.linalg.lstsq(A[used], b[used], rcond=None)
    for _ in range(max_iter):
        A, first = refresh(coef, first)
        coef, *_ = np.linalg.lstsq(A[used], b[used], rcond=None)
        r = b - A @ coef
        scale = max(robust_std(r[used]), floor, 1e-12)
        new = np.abs(r) <= cut * scale
        if new.sum() < 4 or np.array_equal(new, used):
            break
        used = new
    coef, *_ = np.linalg.lstsq(A[used], b[used], rcond=None)
    r = b[used] - A[used] @ coef
    dof = max(int(used.sum()) - A.shape[1], 1)
    s2 = float(r @ r) / dof
    cov = s2 * np.linalg.inv(A[used].T @ A[used])
    return t_ref, coef, cov, used, math.sqrt(s2)


def _bounces(b: np.ndarray, noise: float, *, window: int = 3) -> list[int]:
    """Indices of bounces: sharp local maxima of ``b`` (downward coordinate)."""
    n = b.size
    # A bounce reverses a speed far above the noise; require a clear rise and fall.
    thr = max(10.0 * noise, 1e-9)
    out = []
    for i in range(1, n - 1):
        lo, hi = max(0, i - window), min(n, i + window + 1)
        if b[i] < np.max(b[lo:hi]) or (out and i - out[-1] <= window):
            continue
        if i - window < 0 or i + window >= n:
            continue
        # the neighbours must lie on the falling and rising slopes too, so that a single
        # outlier sample (a spike in b) is not taken for a bounce
        if (b[i] - b[i - window] > thr and b[i] - b[i + window] > thr
                and b[i - 1] - b[i - window] > 0.5 * thr and b[i + 1] - b[i + window] > 0.5 * thr):
            out.append(i)
    return out


def _release(b: np.ndarray, stop: int, noise: float) -> int:
    """Start of the flight ending at ``stop``: walk back while the ball clearly falls."""
    v = np.diff(b[:stop])  # downward speed per frame
    thr = max(5.0 * noise, 1e-9)
    j = stop - 2
    while j >= 0 and v[j] > thr:
        j -= 1
    return j + 1


def fit_flights(t, b, *, min_points: int = 8, cut: float = 5.0,
                drag: bool = False) -> tuple[list[int], list[FlightFit]]:
    """Split a downward-growing vertical coordinate into flights and fit each robustly.

    Gravity is not assumed (see the module docstring): bounces are sharp local maxima of
    ``b``, with a rise and fall beyond 10 times the noise level (:func:`robust_noise`
    of order 3: b is a parabola in flight). The first flight starts where the ball
    clearly starts to fall (samples of a hand holding the ball before release are left
    out), then grows backwards while earlier samples still lie on its parabola. The
    bounce samples themselves are left out of both adjacent flights. Each flight is
    fitted by least squares, iteratively dropping samples whose residual exceeds
    ``cut`` robust standard deviations (1.4826 MAD). With ``drag`` the model has a
    quadratic air-drag term besides the parabola (see :class:`FlightFit`).

    Returns ``(bounce indices, flights)``; flight k ends at bounce k (if any).
    """
    t = np.asarray(t, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    # Below 8 samples (the fewest a flight is fitted on by default) there is no noise
    # level to read, and the thresholds fall to their floors.
    noise = robust_noise(b, order=3, t=t) if b.size >= 8 else 0.0
    bounces = _bounces(b, noise)
    edges = [None] + bounces + [None]
    flights = []
    for k in range(len(edges) - 1):
        lo = 0 if edges[k] is None else edges[k] + 1
        hi = b.size if edges[k + 1] is None else edges[k + 1]
        if k == 0 and edges[1] is not None:
            lo = _release(b, hi, noise)
        elif k == 0:
            continue  # no bounce at all: no well-defined flight
        if hi - lo < min_points:
            continue
        fit = _robust_parabola(t[lo:hi], b[lo:hi], cut=cut, floor=noise, drag=drag)
        if k == 0:
            # Grow backwards while earlier samples lie on the parabola.
            t_ref, coef, _, _, sig = fit
            tol = cut * max(sig, noise)
            while lo > 0:
                dt = t[lo - 1] - t_ref
                pred = coef[0] + coef[1] * dt + coef[2] * dt * dt
                if abs(b[lo - 1] - pred) > tol:
                    break
                lo -= 1
            fit = _robust_parabola(t[lo:hi], b[lo:hi], cut=cut, floor=noise, drag=drag)
        t_ref, coef, cov, used, sig = fit
        if coef[2] <= 0:
            continue  # not a downward-accelerated flight
        flights.append(FlightFit(lo, hi, used, t_ref, coef, cov, sig))
    return bounces, flights


def _meet(f1: FlightFit, f2: FlightFit, t_guess: float) -> float:
    """Time where two flight parabolas meet, nearest ``t_guess``."""
    # Both as polynomials in absolute t: c t^2 + (v - 2 c tr) t + (b0 - v tr + c tr^2).
    def poly(f):
        b0, v, c = f.coef
        tr = f.t_ref
        return np.array([c, v - 2 * c * tr, b0 - v * tr + c * tr * tr])

    d = poly(f1) - poly(f2)
    if abs(d[0]) < 1e-12 * max(abs(d[1]), 1e-300):
        roots = np.array([-d[2] / d[1]])
    else:
        roots = np.roots(d)
        roots = roots[np.abs(roots.imag) < 1e-9].real if np.iscomplexobj(roots) else roots
    if roots.size == 0:
        return float(t_guess)
    return float(roots[np.argmin(np.abs(roots - t_guess))])


def flight_contacts(t, b):
    """The bounces of :func:`fit_flights` with a fitted flight on both sides.

    At such a bounce the parabolas before and after are extrapolated to the time where
    they meet: the free flights meet where the ball first touches.

    Returns ``(bounces, flights, contacts)``: the two lists of :func:`fit_flights`, and
    per such bounce ``(bounce index, contact time, b at contact, flight before, flight
    after)``.
    """
    bounces, flights = fit_flights(t, b)
    out = []
    for i in bounces:
        before = [f for f in flights if f.stop == i]
        after = [f for f in flights if f.start == i + 1]
        if before and after:
            tc = _meet(before[0], after[0], t[i])
            out.append((i, tc, float(before[0](tc)), before[0], after[0]))
    return bounces, flights, out
