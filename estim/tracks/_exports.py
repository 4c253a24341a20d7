"""Readers for the text exports of the two common free video trackers, Tracker and Kinovea.

:func:`read_tracker` reads Tracker's (Open Source Physics, physlets.org/tracker) "Export
Data" text files; :func:`read_kinovea` reads Kinovea's "Export to spreadsheet" trajectory
text files. Both give :class:`~estim.tracks._csv.Tracks` (``units="m"``, a calibrated
export) or :class:`~estim.tracks._image.ImageTracks` seen by one camera (``units="px"``).
The file does not say reliably which of the two it holds, so the caller says; a column
header that states a unit (``x (m)``, ``t [ms]``) must agree with it.

What the formats are based on (the writers' own source code, read in the public
repositories OpenSourcePhysics/tracker, OpenSourcePhysics/osp and Kinovea/Kinovea, and the
tools' help pages):

**Tracker**, ``ExportDataDialog`` and ``TrackerIO``:

- Tracker 6 (``ExportDataDialog.getDataString``, one or more tracks): a line ``#multi:``
  when several tracks are exported; a track-name row that leaves the time column's cell
  empty and puts each track's name over the first of its group of columns (the name as
  Tracker shows it, spaces kept), then a delimiter per column (so the row ends with one);
  the column-name row, ``t`` then each track's group of columns, every group with the same
  names, TeX subscripts removed (``v_{x}`` -> ``vx``, ``pixel_{x}`` -> ``pixelx``), ending
  with a delimiter too; then one row per video frame from the first frame any track marked
  to the last, the time of the frame (seconds: the video's frame time in ms over 1000),
  and each track's values, a blank cell where that track has no value at that frame.
- Tracker 5 and earlier (``ExportDataDialog`` saving ``TrackerIO.getData`` of one track's
  datatable): the track's name alone on the first line with its spaces replaced by ``_``
  (``mass_A``), then the datatable's column names (``t`` first), then its rows; empty
  cells where a value does not exist. The datatable's "Copy Data" gives the same without
  the name line, and is read as one unnamed track (pass ``ball`` as a string).
- Delimiters (``TrackerIO.delimiters``): tab (the default), space, comma, semicolon; a
  custom delimiter is refused. Numbers: "formatted" as the table shows them or
  "unformatted" ``0.000000E0``-style, both with the decimal separator of the locale or of
  Tracker's preference (``OSPRuntime.getDecimalFormatSymbols``): a decimal comma goes with
  a tab, space or semicolon delimiter. A comma delimiter with decimal commas cannot be
  split and is refused (the rows have more fields than the header).
- Positions: ``x`` and ``y`` are world coordinates (``ImageCoordSystem``: image position =
  origin + scale * rotation(angle) * (x, -y), so y is up); in metres once the video is
  calibrated in metres, in pixels while the scale is Tracker's default 1. The other
  columns (``r``, ``vx``, ``ax``, ``step``, ``frame``, ``pixelx``, text columns, ...) are
  read and not used; only columns named exactly ``x`` and ``y`` are positions.

**Kinovea** (``ExporterCSVTrajectory``, ``ExporterTXTTrajectory``, ``CSVHelper``,
``Metadata.GetNumericalTime``, ``CalibrationHelper``, ``CalibratorPlane``; and the kva2txt
stylesheet of Kinovea 0.8):

- CSV (Kinovea 2023/0.9.6 "Export to spreadsheet > CSV"): one table indexed by time; the
  header ``"Time"`` then ``"<object>/<point>/X"``, ``"<object>/<point>/Y"`` per tracked
  point (a trajectory's single point is ``0``: ``"ball/0/X"``); every cell quoted; a blank
  (unquoted) cell where a trajectory has no point at that time. The list separator is the
  system's (``,``, or ``;`` when the decimal separator is a comma); the decimal separator
  is the system's or the preference's.
- Gnuplot text ("Export to spreadsheet > Gnuplot"): ``#Kinovea Trajectory data export``,
  ``#T X Y``, then per trajectory a line ``# <name>`` and its rows ``t x y`` separated by
  spaces, a blank line after each. Kinovea 0.8's stylesheet wrote the same two header
  lines and the rows of each trajectory without a name line, trajectories separated by
  blank lines: read as trajectories ``"1"``, ``"2"``, ... in the file's order.
- Time: a number in the unit of Kinovea's time format preference (seconds for the
  classic timecode, or milliseconds, frames, ...); the file does not say which, so pass
  ``time_unit="s"`` or ``"ms"`` unless the header states it. Timecodes such as
  ``0:00:01:12`` (Kinovea 0.8's ``UserTime``) are refused: their last field may be
  hundredths or frames.
- Positions: world coordinates of Kinovea's coordinate system (x right, y up, origin at
  the coordinate system object; uncalibrated: pixels from the image centre, y up), or
  image coordinates (top-left, y down) when the export preference is image space.
- Refused: the kinematics dialogs' CSV (``"Time (ms)"`` then one column per trajectory
  of a single quantity, times rounded to whole milliseconds); the ODS, XLSX, HTML and
  JSON exports.

Conversions. Metres: the tracker's x is estim's x and the tracker's y is estim's z (up);
estim's y is NaN (``has_y=False``); times in seconds (``ms`` divided by 1000). Pixels:
the export's (x, y) become OpenCV pixels (u right, v down, pixel (0, 0) the centre of the
top-left pixel) through the caller's frame, which the files do not record::

    Y = y if y_up else -y
    u = u0 + cos(a) x - sin(a) Y
    v = v0 - (sin(a) x + cos(a) Y)

``origin=(u0, v0)`` is the export's origin in OpenCV pixels, ``y_up`` whether the export's
y grows upward in the image, ``angle_deg`` (a, default 0: both tools' default axes) the
angle of the export's x axis counter-clockwise from the image's rightward direction. For
Tracker, whose image space counts from the top-left *corner* of the video (pixel centres
at half-integers, ``ImageCoordSystem``), the axes' origin shown as ``(x0, y0)`` in
Tracker's axes toolbar is ``origin=(x0 - 0.5, y0 - 0.5)``, ``y_up=True``, ``angle_deg`` =
the axes' angle; Tracker's default origin is the image centre, ``((w - 1) / 2, (h - 1) /
2)``. For Kinovea's world space, ``y_up=True`` and the coordinate system's origin; the
default is the image centre. For Kinovea's image space, ``origin=(0, 0)`` and
``y_up=False``. A Kinovea lens-distortion calibration makes its world coordinates
undistorted ones, which the camera's distortion does not model: leave it off.

Lost samples (blank cells, ``NaN``) stay as NaN rows; nothing the file holds is dropped,
reordered or rescaled silently. Every problem raises
:class:`~estim.tracks._csv.TracksError` naming the file, the line and the problem.
"""

from __future__ import annotations

import csv
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ._camera import Camera
from ._csv import MAX_ABS_POSITION, MAX_ABS_TIME, MIN_SAMPLES, Tracks, TracksError, _where
from ._image import MAX_ABS_PIXEL, MIN_ROWS, ImageTracks

__all__ = ["read_tracker", "read_kinovea"]

# TrackerIO.delimiters (tab is Tracker's default), tried in this order.
_TRACKER_DELIMITERS = ("\t", ";", ",", " ")
# CSVHelper.GetListSeparator: the system's list separator.
_KINOVEA_DELIMITERS = (",", ";", "\t")
_KINOVEA_TXT_TITLE = "#Kinovea Trajectory data export"
_KINOVEA_TXT_COLUMNS = "#T X Y"
_LENGTH_UNITS = {"m": "m", "px": "px", "pix": "px", "pixel": "px", "pixels": "px"}
_TIME_UNITS = {"s": 1.0, "ms": 1e-3}
_TIME_NAMES = ("t", "time")
# "name", "name (unit)", "name [unit]"
_HEADER = re.compile(r"^(?P<name>.*?)\s*(?:[(\[]\s*(?P<unit>[^)\]]*?)\s*[)\]])?$")
_KINOVEA_POINT = re.compile(r"^(?P<object>.*)/(?P<point>[^/]*)/(?P<axis>[XY])$")
_MINUS = "\u2212"  # the minus sign of some locales' number formats


@dataclass
class _RawTrack:
    """One track's cells as text, before the decimal mark is known."""

    name: str | None  # None: the file does not name it
    line: int  # the line that names it (or the header's)
    rows: list[tuple[int, str, str, str]] = field(default_factory=list)  # (line, t, x, y)


@dataclass
class _Table:
    """What a format parser found: the tracks, and what the header says of the units."""

    tracks: list[_RawTrack]
    delimiter: str  # " " for whitespace-separated text
    time_scale: float | None  # from the time column's header; None when it does not say
    position_unit: str | None  # from the position columns' headers
    header_line: int


# ------------------------------------------------------------------------------ public API


def read_tracker(path: str | os.PathLike, *, units: str, ball: str | Mapping[str, str | None] | None = None,
                 camera: Camera | None = None, origin: Sequence[float] | None = None, y_up: bool | None = None,
                 angle_deg: float | None = None, min_samples: int | None = None) -> Tracks | ImageTracks:
    """Read a Tracker "Export Data" text file (module docstring).

    Args:
        path: the exported text file (one or several tracks, any of Tracker's delimiters).
        units: ``"m"`` (calibrated in metres: gives :class:`Tracks`) or ``"px"`` (Tracker's
            default scale of one unit per pixel: gives :class:`ImageTracks`).
        ball: the scene's ball name of each track: a string for a file of one track, a
            mapping from every track name of the file to a ball name (or to None to leave
            that track out), or None to keep the tracks' own names.
        camera: the :class:`~estim.tracks._camera.Camera` that filmed the video; required
            for ``"px"``, refused for ``"m"``.
        origin: ``(u0, v0)``, the OpenCV pixel of the export's origin (``"px"`` only,
            required): Tracker's axes origin ``(x0, y0)`` minus half a pixel.
        y_up: whether the export's y grows upward in the image (``"px"`` only, required;
            True for Tracker's axes).
        angle_deg: the angle of Tracker's axes (``"px"`` only; default 0, Tracker's).
        min_samples: each track kept needs at least this many rows with both x and y (default:
            what the fit of such a track needs, ``MIN_SAMPLES`` in metres, ``MIN_ROWS`` in pixels).

    Raises:
        FileNotFoundError: no such file.
        TracksError: anything wrong with the arguments or the contents, naming the file, the
            line and the problem.
    """
    path, frame = _arguments(path, units, camera, origin, y_up, angle_deg)
    table = _parse_tracker(path, _lines(path))
    time_scale = 1.0 if table.time_scale is None else table.time_scale  # Tracker's t is in seconds
    return _finish(path, table, time_scale, units, ball, camera, frame, min_samples)


def read_kinovea(path: str | os.PathLike, *, units: str, ball: str | Mapping[str, str | None] | None = None,
                 time_unit: str | None = None, camera: Camera | None = None, origin: Sequence[float] | None = None,
                 y_up: bool | None = None, angle_deg: float | None = None,
                 min_samples: int | None = None) -> Tracks | ImageTracks:
    """Read a Kinovea trajectory export, CSV or Gnuplot text (module docstring).

    Args:
        path: the exported file.
        units: ``"m"`` (calibrated in metres) or ``"px"`` (uncalibrated, or image space).
        ball: as :func:`read_tracker`; a trajectory is named by its object (``ball`` for
            the CSV column ``ball/0/X``; ``object/point`` for a point other than ``0``).
        time_unit: ``"s"`` or ``"ms"``, the unit of Kinovea's time format when the export
            was made; required unless the time column's header states it.
        camera, origin, y_up, angle_deg: as :func:`read_tracker` (``y_up=True`` for
            Kinovea's world space, False for its image space).
        min_samples: each trajectory kept needs at least this many rows with both x and y
            (default as :func:`read_tracker`).

    Raises:
        FileNotFoundError: no such file.
        TracksError: anything wrong with the arguments or the contents, naming the file, the
            line and the problem.
    """
    path, frame = _arguments(path, units, camera, origin, y_up, angle_deg)
    if time_unit is not None and time_unit not in _TIME_UNITS:
        raise TracksError(f"{path}: time_unit={time_unit!r}; it is 's' or 'ms' (Kinovea's time format when "
                          "the file was exported)")
    table = _parse_kinovea(path, _lines(path))
    time_scale = _kinovea_time_scale(path, table, time_unit)
    return _finish(path, table, time_scale, units, ball, camera, frame, min_samples)


# ------------------------------------------------------------------------------ arguments


def _arguments(path, units, camera, origin, y_up, angle_deg) -> tuple[str, tuple[float, float, bool, float] | None]:
    """Check the arguments; return the path and, for pixels, the frame (u0, v0, y_up, a)."""
    path = os.fspath(path)
    if units not in ("m", "px"):
        raise TracksError(f"{path}: units={units!r}; it is 'm' (a calibrated export in metres) or 'px' (pixels)")
    given = [k for k, v in (("camera", camera), ("origin", origin), ("y_up", y_up), ("angle_deg", angle_deg))
             if v is not None]
    if units == "m":
        if given:
            raise TracksError(f"{path}: {given} given with units='m': a camera and a pixel frame are for pixel "
                              "exports (units='px') only")
        frame = None
    else:
        frame = _pixel_frame(path, camera, origin, y_up, angle_deg)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"track file not found: {path}")
    return path, frame


def _pixel_frame(path, camera, origin, y_up, angle_deg) -> tuple[float, float, bool, float]:
    if not isinstance(camera, Camera):
        raise TracksError(f"{path}: units='px' needs camera=<the Camera that filmed the video>, got {camera!r}")
    try:
        u0, v0 = (float(c) for c in origin)
    except (TypeError, ValueError):
        raise TracksError(f"{path}: units='px' needs origin=(u0, v0), the OpenCV pixel of the export's origin "
                          f"(the files do not record it), got {origin!r}") from None
    if not (math.isfinite(u0) and math.isfinite(v0)):
        raise TracksError(f"{path}: origin={origin!r} is not finite")
    if not isinstance(y_up, bool):
        raise TracksError(f"{path}: units='px' needs y_up=True or False (whether the export's y grows upward in "
                          f"the image; the files do not record it), got {y_up!r}")
    a = 0.0 if angle_deg is None else float(angle_deg)
    if not math.isfinite(a):
        raise TracksError(f"{path}: angle_deg={angle_deg!r} is not finite")
    return u0, v0, y_up, math.radians(a)


def _lines(path: str) -> list[str]:
    """The file's lines (utf-8; a byte-order mark is an encoding mark, not text)."""
    with open(path, encoding="utf-8-sig", newline="") as f:
        text = f.read()
    lines = [s[:-1] if s.endswith("\r") else s for s in text.split("\n")]
    if not any(s.strip() for s in lines):
        raise TracksError(f"{_where(path, 1)}: the file is empty")
    return lines


# ------------------------------------------------------------------------------ headers


def _split_header_cell(path, line: int, cell: str) -> tuple[str, str | None]:
    """``name`` and ``unit`` of a header cell ``name (unit)``; TeX subscripts removed."""
    m = _HEADER.match(cell.strip())
    name = re.sub(r"_\{([^}]*)\}", r"\1", m.group("name")).replace("_", "")
    unit = m.group("unit")
    if unit is not None and not unit:
        raise TracksError(f"{_where(path, line)}: column {cell.strip()!r} has empty unit brackets")
    return name, unit


def _time_scale(path, line: int, cell: str) -> float | None:
    """Seconds per unit of the time column from its header; None when it states no unit."""
    name, unit = _split_header_cell(path, line, cell)
    if unit is None:
        return None
    if unit not in _TIME_UNITS:
        raise TracksError(f"{_where(path, line)}: the time column {cell.strip()!r} is in {unit!r}; estim reads "
                          "seconds or milliseconds (s, ms)")
    return _TIME_UNITS[unit]


def _is_time_name(path, line: int, cell: str) -> bool:
    return _split_header_cell(path, line, cell)[0].lower() in _TIME_NAMES


def _position_unit(path, line: int, cells: Sequence[str]) -> str | None:
    """The unit the position columns' headers state (all the same), or None."""
    found: dict[str, str] = {}
    for cell in cells:
        unit = _split_header_cell(path, line, cell)[1]
        if unit is None:
            continue
        if unit not in _LENGTH_UNITS:
            raise TracksError(f"{_where(path, line)}: column {cell.strip()!r} is in {unit!r}; estim reads "
                              "positions in metres (units='m') or pixels (units='px'): convert the export")
        found[cell.strip()] = _LENGTH_UNITS[unit]
    if len(set(found.values())) > 1:
        raise TracksError(f"{_where(path, line)}: the position columns state different units: {found}")
    return next(iter(found.values()), None)


# ------------------------------------------------------------------------------ Tracker


def _tracker_header(path, line: int, text: str) -> tuple[str, list[str]] | None:
    """``(delimiter, cells)`` when ``text`` is a column-name row (``t`` first), else None."""
    for d in _TRACKER_DELIMITERS:
        if d in text:
            cells = text.split(d)
            return (d, cells) if len(cells) >= 2 and _is_time_name(path, line, cells[0]) else None
    return None


def _require_tracker_header(path, line: int, text: str) -> tuple[str, list[str]]:
    found = _tracker_header(path, line, text)
    if found is not None:
        return found
    present = [d for d in _TRACKER_DELIMITERS if d in text]
    if not present:
        raise TracksError(f"{_where(path, line)}: unknown delimiter in the column names {text!r}: Tracker "
                          "separates columns with a tab, a semicolon, a comma or a space")
    first = text.split(present[0])[0].strip()
    raise TracksError(f"{_where(path, line)}: no time column: the column names {text!r} start with {first!r}; "
                      "Tracker's exports start with t")


def _tracker_groups(path, name_line: int | None, name_text: str | None, d: str,
                    width: int) -> list[tuple[str | None, int, int]]:
    """``(track name, first column, end column)`` of each track's group of columns."""
    if name_text is None:  # "Copy Data": no name row
        return [(None, 1, width)]
    if d not in name_text:  # Tracker 5: the name alone
        return [(name_text.strip(), 1, width)]
    cells = name_text.split(d)
    while cells and not cells[-1].strip():
        cells.pop()
    if cells and cells[0].strip():
        raise TracksError(f"{_where(path, name_line)}: the track-name row {name_text!r} has {cells[0].strip()!r} "
                          "over the time column; Tracker leaves it empty and names each track over its columns")
    starts = [k for k, c in enumerate(cells) if c.strip()]
    if not starts:
        raise TracksError(f"{_where(path, name_line)}: the track-name row names no track")
    if len(cells) > width or starts[0] != 1:
        raise TracksError(f"{_where(path, name_line)}: the track names {[cells[k].strip() for k in starts]} do not "
                          "stand over the column groups of the next line")
    if d == " " and any(b == a + 1 for a, b in zip(starts, starts[1:], strict=False)):
        raise TracksError(f"{_where(path, name_line)}: a space-delimited export whose track names hold spaces "
                          f"({name_text.strip()!r}) cannot be split; export with tab, semicolon or comma")
    ends = starts[1:] + [width]
    return [(cells[a].strip(), a, b) for a, b in zip(starts, ends, strict=True)]


def _xy_columns(path, line: int, header: list[str], name: str | None, start: int, end: int) -> tuple[int, int]:
    """The columns named exactly x and y in ``header[start:end]``."""
    names = [_split_header_cell(path, line, header[k])[0] for k in range(start, end)]
    found = []
    for axis in ("x", "y"):
        at = [start + k for k, n in enumerate(names) if n.lower() == axis]
        what = "the track" if name is None else f"track {name!r}"
        if len(at) != 1:
            problem = "no" if not at else f"{len(at)}"
            raise TracksError(f"{_where(path, line)}: {what} has {problem} {axis} column(s) (its columns are "
                              f"{[header[k].strip() for k in range(start, end)]}); Tracker's positions are x and y")
        found.append(at[0])
    return found[0], found[1]


def _parse_tracker(path: str, lines: list[str]) -> _Table:
    i = next(k for k, s in enumerate(lines) if s.strip())
    if lines[i].strip() == "#multi:":
        i += 1
        while i < len(lines) and not lines[i].strip():
            i += 1
        if i == len(lines):
            raise TracksError(f"{_where(path, i)}: nothing after '#multi:'")
    if _tracker_header(path, i + 1, lines[i]) is not None:
        name_line, name_text, h = None, None, i
    else:
        name_line, name_text, h = i + 1, lines[i], i + 1
        if h >= len(lines) or not lines[h].strip():
            raise TracksError(f"{_where(path, h + 1)}: no column names after the track name {lines[i].strip()!r}")
    d, header = _require_tracker_header(path, h + 1, lines[h])
    while header and not header[-1].strip():
        header.pop()  # Tracker 6 ends the row with a delimiter
    empty = [k + 1 for k, c in enumerate(header) if not c.strip()]
    if empty:
        raise TracksError(f"{_where(path, h + 1)}: column(s) {empty} of {lines[h]!r} have no name")
    groups = _tracker_groups(path, name_line, name_text, d, len(header))
    names = [g[0] for g in groups]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise TracksError(f"{_where(path, name_line)}: track name(s) {dup} appear more than once")
    columns = [_xy_columns(path, h + 1, header, n, a, b) for n, a, b in groups]
    unit = _position_unit(path, h + 1, [header[k] for xy in columns for k in xy])
    tracks = [_RawTrack(n, name_line or h + 1) for n, _, _ in groups]
    for k in range(h + 1, len(lines)):
        if not lines[k].strip():
            continue
        cells = _row_cells(path, k + 1, lines[k].split(d), len(header), header)
        for track, (cx, cy) in zip(tracks, columns, strict=True):
            track.rows.append((k + 1, cells[0], cells[cx], cells[cy]))
    return _Table(tracks, d, _time_scale(path, h + 1, header[0]), unit, h + 1)


def _row_cells(path, line: int, cells: list[str], width: int, header: list[str]) -> list[str]:
    """The row's cells, checked against the header's width (extra cells must be empty)."""
    if len(cells) < width or any(c.strip() for c in cells[width:]):
        raise TracksError(f"{_where(path, line)}: {len(cells)} fields, expected {width} "
                          f"({[c.strip() for c in header]}); a decimal comma with a comma delimiter cannot be "
                          "split: export with a tab or semicolon delimiter")
    return cells[:width]


# ------------------------------------------------------------------------------ Kinovea


def _parse_kinovea(path: str, lines: list[str]) -> _Table:
    i = next(k for k, s in enumerate(lines) if s.strip())
    if lines[i].strip() == _KINOVEA_TXT_TITLE:
        return _parse_kinovea_txt(path, lines, i)
    for d in _KINOVEA_DELIMITERS:
        header = next(csv.reader([lines[i]], delimiter=d))
        if len(header) >= 2 and _is_time_name(path, i + 1, header[0]):
            return _parse_kinovea_csv(path, lines, i, d, header)
    raise TracksError(f"{_where(path, i + 1)}: not a Kinovea trajectory export: {lines[i].strip()!r}; expected the "
                      f"CSV header \"Time\",\"<name>/0/X\",\"<name>/0/Y\" or the Gnuplot text's "
                      f"{_KINOVEA_TXT_TITLE!r} (Export to spreadsheet > CSV or Gnuplot)")


def _parse_kinovea_csv(path: str, lines: list[str], i: int, d: str, header: list[str]) -> _Table:
    points = [_KINOVEA_POINT.match(c.strip()) for c in header[1:]]
    if not any(points):
        raise TracksError(f"{_where(path, i + 1)}: the columns {[c.strip() for c in header]} are not Kinovea "
                          "trajectories (<name>/<point>/X and /Y): a kinematics dialog's export holds one quantity "
                          "per file with times rounded to whole milliseconds and is not read; use Export to "
                          "spreadsheet > CSV")
    where: dict[str, dict[str, int]] = {}
    for k, m in enumerate(points, start=1):
        if m is None:
            raise TracksError(f"{_where(path, i + 1)}: column {header[k].strip()!r} is not <name>/<point>/X or /Y")
        name = m["object"] if m["point"] == "0" else f"{m['object']}/{m['point']}"
        axes = where.setdefault(name, {})
        if m["axis"] in axes:
            raise TracksError(f"{_where(path, i + 1)}: column {header[k].strip()!r} appears more than once")
        axes[m["axis"]] = k
    for name, axes in where.items():
        if set(axes) != {"X", "Y"}:
            raise TracksError(f"{_where(path, i + 1)}: trajectory {name!r} has only its {sorted(axes)} column")
    tracks = [_RawTrack(name, i + 1) for name in where]
    for k in range(i + 1, len(lines)):
        if not lines[k].strip():
            continue
        cells = _row_cells(path, k + 1, next(csv.reader([lines[k]], delimiter=d)), len(header), header)
        for track in tracks:
            axes = where[track.name]
            track.rows.append((k + 1, cells[0], cells[axes["X"]], cells[axes["Y"]]))
    return _Table(tracks, d, _time_scale(path, i + 1, header[0]), None, i + 1)


def _parse_kinovea_txt(path: str, lines: list[str], i: int) -> _Table:
    if i + 1 >= len(lines) or lines[i + 1].strip() != _KINOVEA_TXT_COLUMNS:
        raise TracksError(f"{_where(path, i + 2)}: expected {_KINOVEA_TXT_COLUMNS!r} after {_KINOVEA_TXT_TITLE!r}")
    tracks: list[_RawTrack] = []
    current: _RawTrack | None = None
    for k in range(i + 2, len(lines)):
        text, line = lines[k].strip(), k + 1
        if not text:
            current = None  # a blank line ends a trajectory
        elif text.startswith("#"):
            current = _RawTrack(text[1:].strip(), line)
            tracks.append(current)
        else:
            if current is None:
                current = _RawTrack(None, line)
                tracks.append(current)
            current.rows.append((line, *_kinovea_txt_row(path, line, text)))
    named = [t.name is not None for t in tracks]
    if any(named) and not all(named):
        at = tracks[named.index(False)].line
        raise TracksError(f"{_where(path, at)}: rows without a '# <name>' line before them, in a file that names "
                          "its other trajectories")
    for n, track in enumerate(tracks, start=1):
        track.name = str(n) if track.name is None else track.name  # Kinovea 0.8: unnamed, in order
    return _Table(tracks, " ", None, None, i + 2)


def _kinovea_txt_row(path, line: int, text: str) -> tuple[str, str, str]:
    cells = text.split()
    if len(cells) != 3:
        raise TracksError(f"{_where(path, line)}: {len(cells)} fields, expected 3 (t x y); an object with several "
                          "points is not a trajectory")
    return cells[0], cells[1], cells[2]


def _kinovea_time_scale(path, table: _Table, time_unit: str | None) -> float:
    stated = table.time_scale
    if stated is None and time_unit is None:
        raise TracksError(f"{_where(path, table.header_line)}: Kinovea's time column does not say its unit (it "
                          "follows the time format preference when exporting): pass time_unit='s' or 'ms'")
    if stated is not None and time_unit is not None and stated != _TIME_UNITS[time_unit]:
        raise TracksError(f"{_where(path, table.header_line)}: the time column states "
                          f"{'ms' if stated == 1e-3 else 's'} but time_unit={time_unit!r}")
    return stated if stated is not None else _TIME_UNITS[time_unit]


# ------------------------------------------------------------------------------ numbers


def _decimal_mark(path, table: _Table, tracks: list[_RawTrack]) -> str:
    """``","`` when the numbers use a decimal comma, else ``"."``; a file that mixes the two
    (or writes thousands separators) is refused."""
    if table.delimiter == ",":
        return "."
    first: dict[str, int] = {}
    for track in tracks:
        for line, *cells in track.rows:
            for c in cells:
                for mark in ",.":
                    if mark in c:
                        first.setdefault(mark, line)
    if len(first) == 2:
        raise TracksError(f"{_where(path, max(first.values()))}: the numbers mix decimal points (first on line "
                          f"{first['.']}) and decimal commas (first on line {first[',']}), or hold thousands "
                          "separators")
    return "," if "," in first else "."


def _number(path, line: int, column: str, text: str, mark: str) -> float:
    """A cell's number; NaN for an empty cell or ``NaN`` (a lost sample)."""
    s = text.strip().replace(_MINUS, "-")
    if mark == ",":
        s = s.replace(",", ".")
    if s == "" or s.lower() == "nan":
        return math.nan
    try:
        v = float(s)
    except ValueError:
        raise TracksError(f"{_where(path, line)}: {column} = {text.strip()!r} is not a number") from None
    if not math.isfinite(v):
        raise TracksError(f"{_where(path, line)}: {column} = {text.strip()!r} is not a finite number")
    return v


def _time(path, line: int, text: str, mark: str, scale: float) -> float:
    if ":" in text:
        raise TracksError(f"{_where(path, line)}: t = {text.strip()!r} is a timecode, which estim does not read "
                          "(its last field may be hundredths or frames): set the time format to seconds or "
                          "milliseconds and export again")
    t = _number(path, line, "t", text, mark)
    if math.isnan(t):
        raise TracksError(f"{_where(path, line)}: t is missing; every row needs a time")
    t *= scale
    if abs(t) > MAX_ABS_TIME:
        raise TracksError(f"{_where(path, line)}: t = {t:g} s is not a time in seconds (|t| > {MAX_ABS_TIME:g}); "
                          "frame numbers or microseconds? Export in seconds or milliseconds")
    return t


@dataclass
class _Track:
    name: str  # the ball's name in estim
    line: int
    t: np.ndarray
    xy: np.ndarray  # (n, 2): the export's x and y
    lines: np.ndarray


def _convert(path, raw: _RawTrack, name: str, mark: str, scale: float) -> _Track:
    what = "the track" if raw.name is None else f"track {raw.name!r}"
    t, xy = [], []
    for k, (line, tt, x, y) in enumerate(raw.rows):
        t.append(_time(path, line, tt, mark, scale))
        if k and not t[-1] > t[-2]:
            verb = "repeats" if t[-1] == t[-2] else "goes back from"
            raise TracksError(f"{_where(path, line)}: the time of {what} {verb} t = {t[-2]!r} s (line "
                              f"{raw.rows[k - 1][0]}) to t = {t[-1]!r} s; times must increase strictly")
        xy.append((_number(path, line, "x", x, mark), _number(path, line, "y", y, mark)))
    return _Track(name, raw.line, np.asarray(t, dtype=np.float64), np.asarray(xy, dtype=np.float64).reshape(-1, 2),
                  np.asarray([r[0] for r in raw.rows], dtype=np.int64))


# ------------------------------------------------------------------------------ assembly


def _select(path, tracks: list[_RawTrack], ball) -> list[tuple[_RawTrack, str]]:
    """Each track kept, with its ball name (``ball`` as in :func:`read_tracker`)."""
    names = [t.name for t in tracks]
    if ball is None:
        if None in names:
            raise TracksError(f"{path}: the file does not name its track (Tracker's Copy Data has no name line): "
                              "pass ball='<the ball>'")
        return [(t, t.name) for t in tracks]
    if isinstance(ball, str):
        if not ball:
            raise TracksError(f"{path}: ball='' is not a ball name")
        if len(tracks) != 1:
            raise TracksError(f"{path}: ball={ball!r} names one ball but the file holds {len(tracks)} tracks "
                              f"{names}: pass a mapping from each track name to a ball name")
        return [(tracks[0], ball)]
    if not isinstance(ball, Mapping):
        raise TracksError(f"{path}: ball={ball!r}; it is a ball name, a mapping from track names to ball names, "
                          "or None")
    if None in names:
        raise TracksError(f"{path}: the file does not name its track, so ball cannot map track names: pass "
                          "ball='<the ball>'")
    unknown = [k for k in ball if k not in names]
    if unknown:
        raise TracksError(f"{path}: unknown track name(s) {unknown} in ball; the file's tracks are {names}")
    missing = [n for n in names if n not in ball]
    if missing:
        raise TracksError(f"{path}: track(s) {missing} of the file are not in ball: map each track to a ball "
                          "name, or to None to leave it out")
    chosen = [(t, ball[t.name]) for t in tracks if ball[t.name] is not None]
    bad = [v for _, v in chosen if not isinstance(v, str) or not v]
    values = [v for _, v in chosen]
    if bad or len(set(values)) != len(values):
        raise TracksError(f"{path}: the ball names {values} must be distinct non-empty strings")
    if not chosen:
        raise TracksError(f"{path}: ball maps every track to None: nothing to read")
    return chosen


def _check_samples(path, track: _Track, min_samples: int) -> None:
    n = int(np.sum(np.all(np.isfinite(track.xy), axis=1)))
    if n < min_samples:
        raise TracksError(f"{_where(path, track.line)}: track {track.name!r} has only {n} valid samples (x and y "
                          f"present); at least min_samples = {min_samples} are needed")


def _check_range(path, track: _Track, values: np.ndarray, limit: float, names: str, what: str) -> None:
    bad = np.flatnonzero(np.any(np.abs(values) > limit, axis=1))
    if bad.size:
        k = int(bad[0])
        raise TracksError(f"{_where(path, int(track.lines[k]))}: {names} = ({values[k, 0]:g}, {values[k, 1]:g}) of "
                          f"track {track.name!r} is not a {what} (beyond {limit:g}); check the export's units "
                          "(estim never rescales)")


def _to_pixels(xy: np.ndarray, frame: tuple[float, float, bool, float]) -> np.ndarray:
    """The export's (x, y) as OpenCV pixels (module docstring); NaN if either is lost."""
    u0, v0, y_up, a = frame
    x = xy[:, 0]
    y = xy[:, 1] if y_up else -xy[:, 1]
    c, s = math.cos(a), math.sin(a)
    uv = np.stack([u0 + c * x - s * y, v0 - (s * x + c * y)], axis=1)
    uv[~np.all(np.isfinite(xy), axis=1)] = np.nan
    return uv


def _finish(path: str, table: _Table, time_scale: float, units: str, ball, camera, frame,
            min_samples: int) -> Tracks | ImageTracks:
    if table.position_unit is not None and table.position_unit != units:
        raise TracksError(f"{_where(path, table.header_line)}: the position columns state "
                          f"{table.position_unit!r} but units={units!r}")
    chosen = _select(path, table.tracks, ball)
    mark = _decimal_mark(path, table, [raw for raw, _ in chosen])
    tracks = [_convert(path, raw, name, mark, time_scale) for raw, name in chosen]
    if min_samples is None:
        min_samples = MIN_SAMPLES if units == "m" else MIN_ROWS
    for track in tracks:
        _check_samples(path, track, min_samples)
    balls = tuple(t.name for t in tracks)
    times = {t.name: t.t for t in tracks}
    if units == "m":
        position = {}
        for track in tracks:
            _check_range(path, track, track.xy, MAX_ABS_POSITION, "(x, y)", "position in metres")
            p = np.full((track.t.shape[0], 3), np.nan)
            p[:, 0], p[:, 2] = track.xy[:, 0], track.xy[:, 1]
            position[track.name] = p
        return Tracks(path, balls, times, position, has_y=False)
    uv = {}
    for track in tracks:
        uv[track.name] = _to_pixels(track.xy, frame)
        _check_range(path, track, uv[track.name], MAX_ABS_PIXEL, "(u, v)", "pixel of an image")
    view = {t.name: np.zeros(t.t.shape[0], dtype=np.int64) for t in tracks}
    return ImageTracks(path, balls, (camera,), times, uv, view)
