"""Pixel tracks of a video tracker, and what gravity and the bounces tell about them.

A **pixel track** (:func:`read_pixel_track`) is the ``a;b;`` file of a video colour tracker:
one line per frame, ball-centre pixel coordinates, ``a`` horizontal, ``b`` vertical with
image rows growing *downward*; no header, no time column. With a known frame interval,
gravity fixes the pixel scale (:func:`estimate_pixel_scale`), parabolas meeting at the
bounces fix the contact row (:func:`estimate_surface_row`), and ratios of successive
flight times give the restitution without any scale
(:func:`restitution_from_flight_times`). The flights are those of
``estim.tracks._flights.fit_flights``, which does not assume gravity in pixels.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ._csv import Tracks, TracksError, _where
from ._flights import fit_flights, flight_contacts

__all__ = [
    "PixelTrack",
    "read_pixel_track",
    "PixelScale",
    "estimate_pixel_scale",
    "SurfaceRow",
    "estimate_surface_row",
    "FlightTimeRestitution",
    "restitution_from_flight_times",
]


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
# Scale, contact row and restitution from the flights
# ---------------------------------------------------------------------------------------


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
    _, _, contacts = flight_contacts(track.frame * dt, track.b)
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
    bounces, flights, contacts = flight_contacts(t, b)
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
