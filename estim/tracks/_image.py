"""Tracks in pixels of calibrated cameras: the image-track CSV.

An **image-track CSV** (:func:`read_image_tracks_csv`) has a header naming the columns
``t,ball,u,v`` and optionally ``camera`` (any order), then one row per ball per frame per
camera: the time (s) on that camera's clock, the ball, and the ball centre's pixel, ``u`` to
the right and ``v`` down (OpenCV's image coordinates; ``estim.tracks._camera``). An empty
field or ``nan`` in ``u`` or ``v`` marks a lost detection (kept as NaN, masked when
fitting). With several cameras the ``camera`` column says which camera saw the row: the
camera's name (its file's stem), or its position in the list of cameras given, counted
from 1 (``1, 2, ...``) or from 0 (``0, 1, ...``: a column that holds a 0). With one camera
the column may be left out.

Every problem raises :class:`~estim.tracks._csv.TracksError` naming the file, the line and
the problem; nothing is dropped or reordered silently (rows of one ball are kept in the
order of time, then camera; times must increase strictly per ball and camera).
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass

import numpy as np

from ._camera import Camera
from ._csv import MAX_ABS_TIME, TracksError, _parse_number, _where
from ._flights import robust_noise

__all__ = ["ImageTracks", "read_image_tracks_csv"]

REQUIRED_COLUMNS = ("t", "ball", "u", "v")
OPTIONAL_COLUMNS = ("camera",)
# Beyond this a value cannot be a pixel of a camera image.
MAX_ABS_PIXEL = 1.0e5
# Rows with both pixels a ball of an image track needs (the fit, estim.fit_image, asks the
# same): 12 coordinates for the 11 parameters of a fit from one camera (release position,
# velocity and spin, e, the friction coefficient; two of them also held by the scene's
# priors). A shot hit hard is short at 25 fps: 6 or 7 frames from hit to hit, its bounce
# among them (docs/pages/cameras.md, "Short tracks"). Fewer rows than parameters fix no path.
MIN_ROWS = 6


@dataclass(frozen=True, eq=False)
class ImageTracks:
    """Ball-centre pixels seen by one or more calibrated cameras.

    Attributes:
        source: where the data came from.
        balls: ball names, in order of first appearance.
        cameras: the cameras, in the order the ``view`` indices count.
        t: ``ball -> (n,)`` times (s), each on its camera's clock, non-decreasing.
        uv: ``ball -> (n, 2)`` pixels (u right, v down); NaN where lost.
        view: ``ball -> (n,)`` the index in ``cameras`` of the camera of each row.
    """

    source: str
    balls: tuple[str, ...]
    cameras: tuple[Camera, ...]
    t: dict[str, np.ndarray]
    uv: dict[str, np.ndarray]
    view: dict[str, np.ndarray]

    def __post_init__(self):
        for b in self.balls:
            n = self.t[b].shape[0]
            if self.uv[b].shape != (n, 2) or self.view[b].shape != (n,):
                raise ValueError(f"ball {b!r}: t must be (n,), uv (n, 2) and view (n,)")
            if n and (self.view[b].min() < 0 or self.view[b].max() >= len(self.cameras)):
                raise ValueError(f"ball {b!r}: a view index outside the {len(self.cameras)} camera(s)")

    def valid(self, ball: str) -> np.ndarray:
        """``(n,)`` bool: rows of ``ball`` with both pixel coordinates."""
        return np.all(np.isfinite(self.uv[ball]), axis=1)

    def n_obs(self, ball: str, camera: int | None = None) -> int:
        """Valid rows of ``ball`` (seen by ``camera`` where given)."""
        ok = self.valid(ball)
        return int(np.sum(ok if camera is None else ok & (self.view[ball] == camera)))

    def noise(self, ball: str) -> float:
        """The pixels' noise level (px) of ``ball``: per camera, the rms over u and v of
        :func:`~estim.tracks._flights.robust_noise` (third differences, blind to a flight's
        curvature), the median over the cameras with 8 rows or more; NaN without any."""
        levels = []
        for k in range(len(self.cameras)):
            at = self.valid(ball) & (self.view[ball] == k)
            if np.sum(at) >= 8:
                u, v = (robust_noise(self.uv[ball][at, i], order=3, t=self.t[ball][at]) for i in (0, 1))
                levels.append(float(np.sqrt((u * u + v * v) / 2.0)))
        return float(np.median(levels)) if levels else float("nan")

    def select(self, balls) -> ImageTracks:
        """The same tracks restricted to ``balls``."""
        balls = tuple(balls)
        return ImageTracks(self.source, balls, self.cameras, {b: self.t[b] for b in balls},
                           {b: self.uv[b] for b in balls}, {b: self.view[b] for b in balls})


def _camera_indices(labels: list[tuple[str, int]], cameras: tuple[Camera, ...], path) -> list[int]:
    """The camera index of each row's ``camera`` label (module docstring): a camera's name,
    or its number in the list, from 0 where some row says 0, else from 1."""
    names = [c.name for c in cameras]
    numbers = []
    for label, line in labels:
        if label not in names:
            try:
                numbers.append(int(label))
            except ValueError:
                raise TracksError(f"{_where(path, line)}: camera {label!r} is none of the cameras given {names} "
                                  "(name a camera by its file's stem, or by its number in that list)") from None
    base = 0 if not numbers or min(numbers) <= 0 else 1
    out = []
    for label, line in labels:
        if label in names:
            out.append(names.index(label))
            continue
        k = int(label) - base
        if not 0 <= k < len(cameras):
            raise TracksError(f"{_where(path, line)}: camera {label} is not one of the {len(cameras)} camera(s) "
                              f"given {names} (numbered from {base})")
        out.append(k)
    return out


def read_image_tracks_csv(path: str | os.PathLike, cameras, *, balls=None, min_samples: int = MIN_ROWS) -> ImageTracks:
    """Read an image-track CSV (module docstring) seen by ``cameras``.

    Args:
        path: the CSV file.
        cameras: the :class:`~estim.tracks._camera.Camera` of each camera, in the order
            the ``camera`` column counts them.
        balls: the names a ball may have (the scene's balls); default any.
        min_samples: each ball needs at least this many rows with both pixels.

    Raises:
        FileNotFoundError: no such file.
        TracksError: anything wrong with the contents, naming the file, line and problem.
    """
    path = os.fspath(path)
    cameras = tuple(cameras)
    if not cameras:
        raise ValueError("an image track needs at least one camera")
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ValueError(f"two cameras share a name: {names}")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"track file not found: {path}")
    with open(path, newline="", encoding="utf-8-sig") as f:
        rows = list(csv.reader(f))
    head = next((i for i, r in enumerate(rows) if any(c.strip() for c in r)), None)
    if head is None:
        raise TracksError(f"{_where(path, 1)}: the file is empty; expected a header t,ball,u,v (and camera)")
    header = [c.strip() for c in rows[head]]
    hl = head + 1
    unknown = [c for c in header if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    if unknown:
        hint = " (x, y, z are metres: a track CSV, read without --camera)" if set(unknown) & {"x", "y", "z"} else ""
        raise TracksError(f"{_where(path, hl)}: unknown column(s) {unknown} in the header; the columns are "
                          f"{list(REQUIRED_COLUMNS)} plus optionally {list(OPTIONAL_COLUMNS)}{hint}")
    dup = sorted({c for c in header if header.count(c) > 1})
    if dup:
        raise TracksError(f"{_where(path, hl)}: column(s) {dup} appear more than once in the header")
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise TracksError(f"{_where(path, hl)}: header {header} lacks the column(s) {missing}")
    if "camera" not in header and len(cameras) > 1:
        raise TracksError(f"{_where(path, hl)}: {len(cameras)} cameras given but no camera column says which "
                          "camera saw each row")
    col = {c: header.index(c) for c in header}
    data: dict[str, list] = {}
    first_line: dict[str, int] = {}
    labels: list[tuple[str, int]] = []
    for i in range(head + 1, len(rows)):
        r, line = rows[i], i + 1
        if not any(c.strip() for c in r):
            continue
        if len(r) != len(header):
            raise TracksError(f"{_where(path, line)}: {len(r)} fields, expected {len(header)} ({','.join(header)})")
        ball = r[col["ball"]].strip()
        if not ball:
            raise TracksError(f"{_where(path, line)}: the ball name is empty")
        if balls is not None and ball not in balls:
            raise TracksError(f"{_where(path, line)}: unknown ball {ball!r}; the scene's balls are {list(balls)}")
        t = _parse_number(r[col["t"]], "t", path, line, allow_missing=False)
        if abs(t) > MAX_ABS_TIME:
            raise TracksError(f"{_where(path, line)}: t = {t:g} is not a time in seconds (|t| > {MAX_ABS_TIME:g}); "
                              "milliseconds or frame numbers? Convert to seconds (estim never rescales)")
        uv = [_parse_number(r[col[a]], a, path, line, allow_missing=True) for a in ("u", "v")]
        for a, x in zip("uv", uv, strict=True):
            if abs(x) > MAX_ABS_PIXEL:
                raise TracksError(f"{_where(path, line)}: {a} = {x:g} is not a pixel of an image")
        labels.append((r[col["camera"]].strip() if "camera" in col else names[0], line))
        first_line.setdefault(ball, line)
        data.setdefault(ball, []).append((t, uv, len(labels) - 1, line))
    if not data:
        raise TracksError(f"{_where(path, hl + 1)}: no data rows after the header")
    views_of_rows = _camera_indices(labels, cameras, path)

    out_t, out_uv, out_view = {}, {}, {}
    for ball, entries in data.items():
        last: dict[int, tuple[float, int]] = {}
        views = []
        for t, _, row, line in entries:
            k = views_of_rows[row]
            if k in last and not t > last[k][0]:
                what = "repeats" if t == last[k][0] else "goes back from"
                raise TracksError(f"{_where(path, line)}: time of ball {ball!r} on camera {names[k]!r} {what} "
                                  f"t = {last[k][0]!r} (line {last[k][1]}) to t = {t!r}; times must increase "
                                  "strictly per ball and camera")
            last[k] = (t, line)
            views.append(k)
        t = np.array([e[0] for e in entries])
        order = np.lexsort((np.asarray(views), t))
        out_t[ball] = t[order]
        out_uv[ball] = np.array([e[1] for e in entries], dtype=np.float64).reshape(-1, 2)[order]
        out_view[ball] = np.asarray(views, dtype=np.int64)[order]
    tracks = ImageTracks(path, tuple(data), cameras, out_t, out_uv, out_view)
    for b in tracks.balls:
        n = tracks.n_obs(b)
        if n < min_samples:
            raise TracksError(f"{_where(path, first_line[b])}: ball {b!r} (first row on this line) has only {n} rows "
                              f"with both u and v; at least min_samples = {min_samples} are needed")
    return tracks
