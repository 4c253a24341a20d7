"""Tracked positions in metres: the track CSV, read, written and checked, in plain numpy.

A **track CSV** (:func:`read_tracks_csv`, :func:`write_tracks_csv`) has a header naming the
columns ``t,ball,x,z`` and optionally ``y`` (any order), then one row per ball per frame,
in seconds and metres. A frame that was not tracked is simply absent; an empty field or
``nan`` marks a lost detection of that coordinate (kept as NaN and masked when fitting).
Every problem raises :class:`TracksError` naming the file, the line and the problem;
nothing is dropped, reordered or rescaled silently. Values that cannot be metres or
seconds (a position beyond 100 m, a time beyond 10^4 s) are reported as a unit problem,
and so, when the scene is given, is a ball that falls between bounces with an
acceleration far from the scene's gravity (:func:`check_units`: millimetres, centimetres,
pixels, milliseconds or frame numbers read as metres and seconds).

Pixel tracks of a video tracker are read by ``estim.tracks._pixels``; the flights that
:func:`check_units` measures are cut by ``estim.tracks._flights``.
"""

from __future__ import annotations

import csv
import functools
import math
import os
from dataclasses import dataclass, field

import numpy as np

from ..model._scene import Scene
from ._flights import fit_flights

__all__ = [
    "TracksError",
    "Tracks",
    "read_tracks_csv",
    "write_tracks_csv",
    "check_units",
    "MAX_ABS_POSITION",
    "MAX_ABS_TIME",
]

REQUIRED_COLUMNS = ("t", "ball", "x", "z")
OPTIONAL_COLUMNS = ("y",)
# Beyond these a value cannot be metres / seconds of a tabletop experiment.
MAX_ABS_POSITION = 100.0
# Valid samples a ball of a track in metres needs (the fit, estim.fit, asks the same).
MIN_SAMPLES = 8
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
                    min_samples: int = MIN_SAMPLES) -> Tracks:
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
# Units
# ---------------------------------------------------------------------------------------

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


@functools.lru_cache(maxsize=1024)
def _fall_acceleration(t: bytes, z: bytes) -> float | None:
    """The median acceleration of the flights of ``z(t)`` (float64 bytes) that end at a
    bounce, None without any. Cached: a track read from a file is checked there and again
    by the fit."""
    bounces, flights = fit_flights(np.frombuffer(t), -np.frombuffer(z))
    # Flights that end at a bounce (not the open end of the track, where the ball may rest)
    # and whose curvature is known to 5%: a segment with an unresolved bounce inside is a
    # poor parabola (10-20% errors, too flat) and is left out.
    acc = [2.0 * f.curvature for f in flights
           if f.stop in bounces and f.curvature > 0 and f.curvature_stderr < 0.05 * f.curvature]
    return float(np.median(acc)) if acc else None


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
    a = _fall_acceleration(t.tobytes(), z.tobytes())
    if a is None:
        return None
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
