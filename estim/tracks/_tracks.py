"""Tracked ball positions: reading, writing and checking them, in plain numpy.

Two input formats:

- **Track CSV** (:func:`read_tracks_csv`, :func:`write_tracks_csv`): a header naming the
  columns ``t,ball,x,z`` and optionally ``y`` (any order), then one row per ball per frame,
  in seconds and metres. A frame that was not tracked is simply absent; an empty field or
  ``nan`` marks a lost detection of that coordinate (kept as NaN and masked when fitting).
  Every problem raises :class:`TracksError` naming the file, the line and the problem;
  nothing is dropped, reordered or rescaled silently. Values that cannot be metres or
  seconds (a position beyond 100 m, a time beyond 10^4 s) are reported as a unit problem,
  and so, when the scene is given, is a ball that falls between bounces with an
  acceleration far from the scene's gravity (:func:`check_units`: millimetres, centimetres,
  pixels, milliseconds or frame numbers read as metres and seconds).

- **Pixel tracks** (:func:`read_pixel_track`): the ``a;b;`` files of a video colour tracker
  (one line per frame, ball-centre pixel coordinates, ``a`` horizontal, ``b`` vertical with
  image rows growing *downward*; no header, no time column). With a known frame interval,
  gravity fixes the pixel scale (:func:`estimate_pixel_scale`), parabolas meeting at the
  bounces fix the contact row (:func:`estimate_surface_row`), and ratios of successive
  flight times give the restitution without any scale
  (:func:`restitution_from_flight_times`).
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..model._scene import Scene

__all__ = [
    "TracksError",
    "Tracks",
    "read_tracks_csv",
    "write_tracks_csv",
    "PixelTrack",
    "read_pixel_track",
    "FlightFit",
    "PixelScale",
    "SurfaceRow",
    "FlightTimeRestitution",
    "fit_flights",
    "estimate_pixel_scale",
    "estimate_surface_row",
    "restitution_from_flight_times",
    "check_units",
]

REQUIRED_COLUMNS = ("t", "ball", "x", "z")
OPTIONAL_COLUMNS = ("y",)
# Beyond these a value cannot be metres / seconds of a tabletop experiment.
MAX_ABS_POSITION = 100.0
MAX_ABS_TIME = 1.0e4
DEFAULT_UNITS = {"t": "s", "position": "m"}


class TracksError(ValueError):
    """A track file is malformed; the message names the file, the line and the problem."""


def _where(path, line: int | None = None) -> str:
    return f"{path}: line {line}" if line is not None else f"{path}"


# ---------------------------------------------------------------------------------------
# Tracks in metres
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Tracks:
    """Tracked centre positions of one or more balls.

    Attributes:
        source: where the data came from (a file path, or a description).
        balls: ball names, in order of first appearance.
        t: ``ball -> (n,)`` frame times (s), strictly increasing.
        position: ``ball -> (n, 3)`` centre positions (m); NaN where a coordinate is
            missing (a lost detection, or ``y`` of every row when ``has_y`` is False).
        has_y: whether the data has a ``y`` column.
        units: the units of the arrays (always seconds and metres).
    """

    source: str
    balls: tuple[str, ...]
    t: dict[str, np.ndarray]
    position: dict[str, np.ndarray]
    has_y: bool
    units: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_UNITS))

    def __post_init__(self):
        for b in self.balls:
            t, p = self.t[b], self.position[b]
            if t.ndim != 1 or p.shape != (t.shape[0], 3):
                raise ValueError(f"ball {b!r}: t must be (n,) and position (n, 3), got "
                                 f"{t.shape} and {p.shape}")

    @property
    def observed_axes(self) -> tuple[int, ...]:
        """The coordinate axes the data has: (0, 2), or (0, 1, 2) with y."""
        return (0, 1, 2) if self.has_y else (0, 2)

    def valid(self, ball: str) -> np.ndarray:
        """``(n,)`` bool: rows of ``ball`` whose observed coordinates are all present."""
        p = self.position[ball][:, self.observed_axes]
        return np.all(np.isfinite(p), axis=1)

    def n_obs(self, ball: str) -> int:
        """Number of valid samples of ``ball`` (rows with every observed coordinate)."""
        return int(np.sum(self.valid(ball)))

    def n_frames(self, ball: str) -> int:
        """Number of rows of ``ball`` (including rows with lost coordinates)."""
        return int(self.t[ball].shape[0])

    def padded(self, balls=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pad every ball to the same number of rows, for batched fitting.

        Returns ``(t, obs, mask)`` of shapes ``(B, N)``, ``(B, N, 3)``, ``(B, N, 3)``.
        Padding rows repeat the ball's last time; ``mask`` is False on padding, on lost
        coordinates and on ``y`` when the data has none. ``obs`` is 0 wherever ``mask``
        is False (never NaN, so masked residuals cannot poison gradients).
        """
        balls = tuple(self.balls if balls is None else balls)
        for b in balls:
            if b not in self.t:
                raise KeyError(f"unknown ball {b!r}: these tracks have {list(self.balls)}")
        n = max((self.t[b].shape[0] for b in balls), default=0)
        t = np.zeros((len(balls), n))
        obs = np.zeros((len(balls), n, 3))
        mask = np.zeros((len(balls), n, 3), dtype=bool)
        for i, b in enumerate(balls):
            k = self.t[b].shape[0]
            t[i, :k] = self.t[b]
            t[i, k:] = self.t[b][-1] if k else 0.0
            p = self.position[b]
            m = np.isfinite(p)
            if not self.has_y:
                m[:, 1] = False
            mask[i, :k] = m
            obs[i, :k] = np.where(m, p, 0.0)
        return t, obs, mask

    def select(self, balls) -> Tracks:
        """The same tracks restricted to ``balls``."""
        balls = tuple(balls)
        return Tracks(self.source, balls, {b: self.t[b] for b in balls},
                      {b: self.position[b] for b in balls}, self.has_y, dict(self.units))


def _parse_number(text: str, column: str, path, line: int, *, allow_missing: bool) -> float:
    s = text.strip()
    if s == "" or s.lower() == "nan":
        if allow_missing:
            return math.nan
        raise TracksError(f"{_where(path, line)}: {column} is missing ({text!r}); every row "
                          f"needs a {column}")
    try:
        v = float(s)
    except ValueError:
        raise TracksError(f"{_where(path, line)}: {column} = {text!r} is not a number") from None
    if math.isnan(v):  # e.g. '+nan'
        if allow_missing:
            return math.nan
        raise TracksError(f"{_where(path, line)}: {column} is missing ({text!r})")
    if not math.isfinite(v):
        raise TracksError(f"{_where(path, line)}: {column} = {text!r} is infinite; use an "
                          "empty field or nan for a lost detection")
    return v


def read_tracks_csv(path: str | os.PathLike, *, scene: Scene | None = None,
                    min_samples: int = 8) -> Tracks:
    """Read tracked positions from a CSV file (see the module docstring).

    Args:
        path: the CSV file: header ``t,ball,x,z`` plus optional ``y``, any column order;
            metres and seconds.
        scene: if given, every ball must be one of the scene's balls, and its vertical
            acceleration in flight must match the scene's gravity (:func:`check_units`).
        min_samples: each ball needs at least this many valid samples (rows with every
            observed coordinate present).

    Raises:
        FileNotFoundError: no such file.
        TracksError: anything wrong with the contents; the message names the file, the
            line number and the problem.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"track file not found: {path}")
    known_balls = None if scene is None else [b.name for b in scene.balls]
    # utf-8-sig: a byte-order mark (spreadsheets save one) is an encoding mark, not text.
    with open(path, newline="", encoding="utf-8-sig") as f:
        rows = list(csv.reader(f))
    header_line = next((i for i, r in enumerate(rows) if any(c.strip() for c in r)), None)
    if header_line is None:
        raise TracksError(f"{_where(path, 1)}: the file is empty; expected a header "
                          f"{','.join(REQUIRED_COLUMNS)} (and optionally y)")
    header = [c.strip() for c in rows[header_line]]
    hl = header_line + 1
    unknown = [c for c in header if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    if unknown:
        raise TracksError(
            f"{_where(path, hl)}: unknown column(s) {unknown} in the header; the columns are "
            f"{list(REQUIRED_COLUMNS)} plus optionally {list(OPTIONAL_COLUMNS)}"
        )
    dup = sorted({c for c in header if header.count(c) > 1})
    if dup:
        raise TracksError(f"{_where(path, hl)}: column(s) {dup} appear more than once in the header")
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise TracksError(f"{_where(path, hl)}: header {header} lacks the column(s) {missing}; "
                          f"required are {list(REQUIRED_COLUMNS)}")
    has_y = "y" in header
    col = {c: header.index(c) for c in header}
    axes = ("x", "y", "z")

    times: dict[str, list[float]] = {}
    pos: dict[str, list[list[float]]] = {}
    last: dict[str, tuple[float, int]] = {}
    first_line: dict[str, int] = {}
    for i in range(header_line + 1, len(rows)):
        r, line = rows[i], i + 1
        if not any(c.strip() for c in r):
            continue  # blank line: no data
        if len(r) != len(header):
            raise TracksError(f"{_where(path, line)}: {len(r)} fields, expected {len(header)} "
                              f"({','.join(header)})")
        ball = r[col["ball"]].strip()
        if not ball:
            raise TracksError(f"{_where(path, line)}: the ball name is empty")
        if known_balls is not None and ball not in known_balls:
            raise TracksError(f"{_where(path, line)}: unknown ball {ball!r}; the scene's balls "
                              f"are {known_balls}")
        t = _parse_number(r[col["t"]], "t", path, line, allow_missing=False)
        if abs(t) > MAX_ABS_TIME:
            raise TracksError(
                f"{_where(path, line)}: t = {t:g} is not a time in seconds (|t| > {MAX_ABS_TIME:g}); "
                "milliseconds or frame numbers? Convert to seconds (estim never rescales)"
            )
        p = [math.nan, math.nan, math.nan]
        for k, a in enumerate(axes):
            if a not in col:
                continue
            v = _parse_number(r[col[a]], a, path, line, allow_missing=True)
            if abs(v) > MAX_ABS_POSITION:
                raise TracksError(
                    f"{_where(path, line)}: {a} = {v:g} is not a position in metres "
                    f"(|{a}| > {MAX_ABS_POSITION:g}); millimetres or pixels? Convert to metres "
                    "(estim never rescales)"
                )
            p[k] = v
        if ball in last:
            t_prev, line_prev = last[ball]
            if not t > t_prev:
                what = "repeats" if t == t_prev else "goes back from"
                raise TracksError(
                    f"{_where(path, line)}: time of ball {ball!r} {what} t = {t_prev!r} "
                    f"(line {line_prev}) to t = {t!r}; times must increase strictly per ball"
                )
        else:
            first_line[ball] = line
            times[ball], pos[ball] = [], []
        last[ball] = (t, line)
        times[ball].append(t)
        pos[ball].append(p)
    if not times:
        raise TracksError(f"{_where(path, hl + 1)}: no data rows after the header")
    tracks = Tracks(
        source=path,
        balls=tuple(times),
        t={b: np.asarray(v, dtype=np.float64) for b, v in times.items()},
        position={b: np.asarray(v, dtype=np.float64).reshape(-1, 3) for b, v in pos.items()},
        has_y=has_y,
    )
    for b in tracks.balls:
        n = tracks.n_obs(b)
        if n < min_samples:
            cols = "x, y and z" if has_y else "x and z"
            raise TracksError(
                f"{_where(path, first_line[b])}: ball {b!r} (first row on this line) has only "
                f"{n} valid samples ({cols} present); at least min_samples = {min_samples} "
                "are needed"
            )
    if scene is not None:
        for b in tracks.balls:
            check_units(tracks.t[b], tracks.position[b][:, 2], float(scene.gravity),
                        where=f"{_where(path, first_line[b])}: ball {b!r} (first row on this line)")
    return tracks


def _fmt(v: float, digits: int | None) -> str:
    if not math.isfinite(v):
        return ""
    if digits is None:
        return repr(float(v))
    s = f"{v:.{digits}f}"
    return "0.0" if float(s) == 0 else s


def write_tracks_csv(path, tracks: Tracks, *, digits: int | None = None) -> None:
    """Write ``tracks`` as a track CSV that :func:`read_tracks_csv` reads back.

    Rows are ordered by time, then by ball. Lost coordinates are written as empty fields.
    ``digits=None`` writes every number exactly (shortest round-trip repr); an integer
    rounds positions to that many decimals (times are always exact).
    """
    cols = ["t", "ball", "x", "y", "z"] if tracks.has_y else ["t", "ball", "x", "z"]
    rows = []
    for bi, b in enumerate(tracks.balls):
        for t, p in zip(tracks.t[b], tracks.position[b], strict=True):
            rows.append((float(t), bi, b, p))
    rows.sort(key=lambda r: (r[0], r[1]))
    with open(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(cols)
        for t, _, b, p in rows:
            fields = {"t": repr(t), "ball": b, "x": _fmt(p[0], digits),
                      "y": _fmt(p[1], digits), "z": _fmt(p[2], digits)}
            w.writerow([fields[c] for c in cols])


# ---------------------------------------------------------------------------------------
# Pixel tracks
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PixelTrack:
    """One ball tracked in a video, in pixels.

    Attributes:
        source: the file read.
        ball: the ball's name (for :meth:`to_metres`).
        frame: ``(n,)`` frame indices 0, 1, ... (one per line).
        t: ``(n,)`` times ``frame * frame_interval`` (s).
        a: ``(n,)`` horizontal pixel coordinate of the ball centre.
        b: ``(n,)`` vertical pixel coordinate (image row, growing DOWNWARD).
        frame_interval: seconds per frame (an assumption of the reader, not in the file).
        metres_per_pixel: the scale if known (else None).
    """

    source: str
    ball: str
    frame: np.ndarray
    t: np.ndarray
    a: np.ndarray
    b: np.ndarray
    frame_interval: float
    metres_per_pixel: float | None = None

    def to_metres(self, metres_per_pixel: float | None = None, surface_row: float = 0.0) -> Tracks:
        """Tracks in metres: ``x = (a - a[0]) * s`` and ``z = (surface_row - b) * s``.

        ``z`` is the height above ``surface_row`` (upward positive). Pass the row of the
        surface (e.g. ``estimate_surface_row(...).surface_row``) to get the centre height
        above the surface, which is one radius at contact; pass the contact row of the
        centre (``.centre_row``) to get heights above the centre's contact height.
        """
        s = self.metres_per_pixel if metres_per_pixel is None else metres_per_pixel
        if s is None or not (math.isfinite(s) and s > 0):
            raise ValueError(f"{self.source}: to_metres needs a scale metres_per_pixel > 0, got {s!r}")
        p = np.full((self.t.shape[0], 3), np.nan)
        p[:, 0] = (self.a - self.a[0]) * s
        p[:, 2] = (surface_row - self.b) * s
        return Tracks(self.source, (self.ball,), {self.ball: self.t.copy()}, {self.ball: p}, False)


def read_pixel_track(path, *, frame_interval: float, metres_per_pixel: float | None = None,
                     ball: str = "pingpong") -> PixelTrack:
    """Read an ``a;b;`` pixel track (one line per frame; see :class:`PixelTrack`).

    Each line holds two numbers separated by ``;`` (a trailing ``;`` is optional). Blank
    lines at the end are ignored; a blank line followed by more data, a line without exactly
    two numbers, or a non-finite number raises :class:`TracksError` with file and line.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"pixel track file not found: {path}")
    if not (math.isfinite(frame_interval) and frame_interval > 0):
        raise ValueError(f"frame_interval must be a time > 0 (s), got {frame_interval!r}")
    with open(path, encoding="utf-8-sig") as f:
        lines = f.read().splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    vals = []
    for i, raw in enumerate(lines):
        line = i + 1
        s = raw.strip()
        if not s:
            raise TracksError(f"{_where(path, line)}: blank line inside the data (every frame "
                              "needs a line 'a;b;')")
        parts = s.split(";")
        if parts and parts[-1].strip() == "":
            parts = parts[:-1]
        if len(parts) != 2:
            raise TracksError(f"{_where(path, line)}: expected 'a;b;' (two numbers), got {raw!r}")
        ab = []
        for name, p in zip(("a", "b"), parts, strict=True):
            try:
                v = float(p)
            except ValueError:
                raise TracksError(f"{_where(path, line)}: {name} = {p!r} is not a number") from None
            if not math.isfinite(v):
                raise TracksError(f"{_where(path, line)}: {name} = {p!r} is not finite")
            ab.append(v)
        vals.append(ab)
    if not vals:
        raise TracksError(f"{_where(path, 1)}: the file has no data lines")
    v = np.asarray(vals, dtype=np.float64)
    frame = np.arange(v.shape[0])
    return PixelTrack(path, ball, frame, frame * float(frame_interval), v[:, 0], v[:, 1],
                      float(frame_interval), metres_per_pixel)


# ---------------------------------------------------------------------------------------
# Flights of a vertical coordinate that grows downward
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


def _noise_scale(b: np.ndarray) -> float:
    """Robust per-sample noise of a piecewise-parabolic signal (third differences)."""
    if b.size < 8:
        return 0.0
    d3 = np.diff(b, 3)
    return float(1.4826 * np.median(np.abs(d3 - np.median(d3))) / math.sqrt(20.0))


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
        mad = 1.4826 * np.median(np.abs(r[used] - np.median(r[used])))
        scale = max(mad, floor, 1e-12)
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

    Bounces are sharp local maxima of ``b``. The first flight starts where the ball
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
    noise = _noise_scale(b)
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


# Ratios (acceleration measured in the file's units / gravity) of common unit mistakes.
_UNIT_MISTAKES = (
    (1e3, "positions in millimetres"),
    (1e2, "positions in centimetres"),
    (39.37, "positions in inches"),
    (3.281, "positions in feet"),
    (1e-6, "times in milliseconds"),
    (1e-3, "positions in millimetres and times in milliseconds"),
    (1.0 / 60.0**2, "times in frame numbers at 60 fps"),
    (1.0 / 30.0**2, "times in frame numbers at 30 fps"),
    (1.0 / 120.0**2, "times in frame numbers at 120 fps"),
    (1.0 / 240.0**2, "times in frame numbers at 240 fps"),
)
# A track in seconds and metres falls with an apparent acceleration within this factor of g
# (air drag and noise move it by tens of percent at most); every mistake above is outside.
UNIT_TOLERANCE = 3.0


def check_units(t, z, g: float, *, where: str = "track") -> float | None:
    """Check that a height track ``z(t)`` falls with gravity ``g`` between its bounces.

    Every flight between two bounces is fitted with a robust parabola
    (:func:`fit_flights` on ``-z``; samples with NaN are left out). If the median of their
    accelerations (flights whose curvature is known to 5% or better) is more than
    ``UNIT_TOLERANCE`` times larger or smaller than ``g``, the positions are not in metres
    or the times not in seconds: raises :class:`TracksError` naming the likely mistake (see
    ``_UNIT_MISTAKES``). Tracks without a resolved bounce pass (nothing to measure).

    Returns the measured acceleration (None when there was nothing to measure).
    """
    t = np.asarray(t, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    ok = np.isfinite(t) & np.isfinite(z)
    t, z = t[ok], z[ok]
    if t.size < 16:
        return None
    bounces, flights = fit_flights(t, -z)
    # Flights that end at a bounce (not the open end of the track, where the ball may rest)
    # and whose curvature is known to 5%: a segment with an unresolved bounce inside is a
    # poor parabola (10-20% errors, too flat) and is left out.
    acc = [2.0 * f.curvature for f in flights
           if f.stop in bounces and f.curvature > 0 and f.curvature_stderr < 0.05 * f.curvature]
    if not acc:
        return None
    a = float(np.median(acc))
    ratio = a / g
    if 1.0 / UNIT_TOLERANCE <= ratio <= UNIT_TOLERANCE:
        return a
    near = min(_UNIT_MISTAKES, key=lambda m: abs(math.log(ratio / m[0])))
    guess = (f"{near[1]} (which gives {near[0]:.3g})" if abs(math.log(ratio / near[0])) < math.log(1.5)
             else "positions in pixels or other units, or times not in seconds")
    raise TracksError(
        f"{where}: falls with an acceleration of {a:.4g} (file units) between bounces, "
        f"{ratio:.3g} times the scene's gravity {g:.4g} m/s^2: the units are not metres and "
        f"seconds; likely {guess}. Convert the file to metres and seconds (estim never "
        "rescales)"
    )


class PixelScale(NamedTuple):
    """What :func:`estimate_pixel_scale` returns (also unpacks as a 3-tuple)."""

    metres_per_pixel: float
    stderr: float
    flights: tuple  # per flight: (start, stop, n points, metres_per_pixel, stderr)


def estimate_pixel_scale(track: PixelTrack, frame_interval: float | None = None, *,
                         g: float = 9.81, drag: bool = False,
                         complete_only: bool = False) -> PixelScale:
    """Metres per pixel from gravity: every flight is ``b(t) = b0 + v t + (g / 2s) t^2``.

    Each flight gives ``s = g / (2 c)`` from its robust parabola fit (curvature ``c`` in
    px/s^2, with ``t = frame * frame_interval``); flights are combined weighted by their
    number of points. The standard error is the larger of the propagated fit errors and
    the scatter between flights. The scale scales with ``frame_interval**2``: it is only
    as right as the assumed frame interval.

    Air drag biases the plain parabola: a ball falling from release decelerates less than
    g (too small a curvature, too large a scale), a rising ball more. Over a whole
    bounce-to-bounce flight the drag is nearly odd in time and the bias mostly cancels.
    ``drag=True`` fits a quadratic drag term per flight as well (``b'' = 2c - k b'|b'|``),
    which removes most of the bias of the release and truncated flights.
    ``complete_only=True`` uses only flights observed from bounce to bounce (if any).
    Flights whose curvature has a relative error above 25% are left out (``flights`` lists
    the ones used); if none is left, raises ``ValueError``.
    """
    dt = track.frame_interval if frame_interval is None else float(frame_interval)
    t = track.frame * dt
    bounces, flights = fit_flights(t, track.b, drag=drag)
    if complete_only:
        complete = [f for f in flights if f.start - 1 in bounces and f.stop in bounces]
        flights = complete or flights
    if not flights:
        raise ValueError(f"{track.source}: no flight found to fit (needs a bounce and "
                         "at least 8 samples per flight)")
    per = []
    for f in flights:
        c, dc = f.curvature, f.curvature_stderr
        s = g / (2.0 * c)
        per.append((f.start, f.stop, f.n, s, s * dc / c))
    # A flight whose curvature is not resolved (relative error above 25%: a few samples of a
    # ball that is caught or comes to rest) says nothing about the scale, and weighted by its
    # number of points it would pull the mean anywhere (3x too large on a real racket drop).
    resolved = [p for p in per if p[4] <= 0.25 * p[3]]
    if not resolved:
        raise ValueError(f"{track.source}: no flight with a resolved curvature (every fit has "
                         "a relative error above 25%): the scale cannot be measured")
    per = resolved
    w = np.array([p[2] for p in per], dtype=np.float64)
    s_k = np.array([p[3] for p in per])
    e_k = np.array([p[4] for p in per])
    w = w / w.sum()
    s = float(np.sum(w * s_k))
    internal = float(math.sqrt(np.sum(w**2 * e_k**2)))
    if len(per) > 1:
        external = float(math.sqrt(np.sum(w**2 * (s_k - s) ** 2) * len(per) / (len(per) - 1)))
    else:
        external = 0.0
    return PixelScale(s, max(internal, external), tuple(per))


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


def _contacts(t, b):
    """(bounce time, centre row at contact) where consecutive flight parabolas meet."""
    bounces, flights = fit_flights(t, b)
    out = []
    for i in bounces:
        before = [f for f in flights if f.stop == i]
        after = [f for f in flights if f.start == i + 1]
        if before and after:
            tc = _meet(before[0], after[0], t[i])
            out.append((i, tc, float(before[0](tc)), before[0], after[0]))
    return bounces, flights, out


class SurfaceRow(NamedTuple):
    """What :func:`estimate_surface_row` returns.

    ``centre_row`` is the row of the ball CENTRE at contact (where the incoming and
    outgoing parabolas meet); ``surface_row`` is the row of the surface itself, one radius
    lower in the image (larger row): ``centre_row + radius / metres_per_pixel``.
    """

    centre_row: float
    surface_row: float
    stderr: float  # of centre_row (scatter between bounces; NaN with a single bounce)
    bounce_t: np.ndarray
    bounce_rows: np.ndarray


def estimate_surface_row(track: PixelTrack, frame_interval: float | None = None, *,
                         radius: float = 0.02, metres_per_pixel: float | None = None,
                         g: float = 9.81) -> SurfaceRow:
    """Row of the ball centre at contact and of the surface, from where flights meet.

    At each bounce the parabolas of the flights before and after are extrapolated to the
    time where they meet; the row there is the centre's row at contact (the free flights
    meet where the ball first touches, one radius above the surface). The surface row adds
    ``radius / metres_per_pixel`` (rows grow downward); the scale defaults to
    ``track.metres_per_pixel``, else :func:`estimate_pixel_scale`.
    """
    dt = track.frame_interval if frame_interval is None else float(frame_interval)
    _, _, contacts = _contacts(track.frame * dt, track.b)
    if not contacts:
        raise ValueError(f"{track.source}: no bounce with fitted flights on both sides")
    rows = np.array([c[2] for c in contacts])
    times = np.array([c[1] for c in contacts])
    s = metres_per_pixel if metres_per_pixel is not None else track.metres_per_pixel
    if s is None:
        s = estimate_pixel_scale(track, dt, g=g).metres_per_pixel
    centre = float(np.mean(rows))
    err = float(np.std(rows, ddof=1) / math.sqrt(rows.size)) if rows.size > 1 else math.nan
    return SurfaceRow(centre, centre + radius / s, err, times, rows)


class FlightTimeRestitution(NamedTuple):
    """What :func:`restitution_from_flight_times` returns (per bounce k = 0, 1, ...).

    ``e[k] = flight_time[k + 1] / flight_time[k]`` where flight k ends at bounce k.
    ``flight_time`` is measured bounce to bounce where both bounces are observed
    (``measured`` True); the first flight (from release) and a last flight cut off by the
    end of the data are the durations of their symmetric parabolas (twice the time between
    the apex and the observed bounce), which is what the flight would have lasted from and
    to the contact height.
    """

    e: np.ndarray
    t_bounce: np.ndarray
    flight_time: np.ndarray
    measured: np.ndarray


def restitution_from_flight_times(track: PixelTrack | Tracks, *,
                                  ball: str | None = None) -> FlightTimeRestitution:
    """Restitution from ratios of successive flight durations, ``T_{k+1} / T_k = e``.

    Scale-free: neither the pixel scale nor the frame interval matters (times only enter
    as ratios). Valid for bounces on one horizontal surface (a drop), not on stairs.

    Args:
        track: a :class:`PixelTrack`, or :class:`Tracks` with ``ball`` (uses ``-z``).
    """
    if isinstance(track, Tracks):
        ball = ball or track.balls[0]
        ok = np.isfinite(track.position[ball][:, 2])
        t, b = track.t[ball][ok], -track.position[ball][ok, 2]
        source = track.source
    else:
        t, b, source = track.t, track.b, track.source
    bounces, flights, contacts = _contacts(t, b)
    if not contacts:
        raise ValueError(f"{source}: no bounce with fitted flights on both sides")
    tb = np.array([c[1] for c in contacts])
    times, measured = [], []
    first = contacts[0][3]
    times.append(2.0 * (tb[0] - first.t_vertex))
    measured.append(False)
    for k in range(len(contacts) - 1):
        if contacts[k][4] is contacts[k + 1][3]:
            times.append(tb[k + 1] - tb[k])
            measured.append(True)
        else:  # a flight between the bounces could not be fitted
            times.append(math.nan)
            measured.append(False)
    last = contacts[-1][4]
    times.append(2.0 * (last.t_vertex - tb[-1]))
    measured.append(False)
    ft = np.array(times)
    e = ft[1:] / ft[:-1]
    return FlightTimeRestitution(e, tb, ft, np.array(measured))
