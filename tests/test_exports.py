"""Readers of Tracker's and Kinovea's text exports (``estim.tracks._exports``).

The fixtures under ``tests/data/exports/`` were written from known numbers in the layouts
the tools' own writers produce (module docstring of ``estim.tracks._exports``):

- ``tracker5_*``: Tracker 5's ``ExportDataDialog`` (the track name alone with ``_`` for
  spaces, then ``TrackerIO.getData``: column names, rows, empty cells where no value);
- ``tracker6_*``: Tracker 6's ``ExportDataDialog.getDataString`` (``#multi:`` for several
  tracks, a name row over each track's group of columns, rows ending without a delimiter,
  the name and column rows ending with one, a row per frame with blank cells);
- ``kinovea_*.csv``: Kinovea's ``ExporterCSVTrajectory`` with ``CSVHelper`` (quoted cells,
  ``"Time"``, ``"<name>/0/X"``, blank unquoted cells, ``;`` with decimal commas);
- ``kinovea_gnuplot.txt``: ``ExporterTXTTrajectory``; ``kinovea08_*``: Kinovea 0.8's
  kva2txt stylesheet (no names, a trailing space, timecodes in ``UserTime``).

Balls: A at x = 0.1 + 0.8 t, z = 1.2 - g t^2 / 2 and B at x = -0.2 + 0.5 t,
z = 0.9 + t - g t^2 / 2, sampled at 30 fps. The pixel fixtures hold the projection of A
through ``CAMERA`` (``Camera.project``), expressed in each tool's frame.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import estim
from estim.app._cli import main
from estim.tracks._camera import Camera
from estim.tracks._csv import Tracks, TracksError
from estim.tracks._exports import read_kinovea, read_tracker
from estim.tracks._image import ImageTracks

DATA = Path(__file__).resolve().parent / "data" / "exports"
G = 9.81
FPS = 30.0
N = 12


def ball_a(t):
    return 0.1 + 0.8 * t, 1.2 - G * t * t / 2


def ball_b(t):
    return -0.2 + 0.5 * t, 0.9 + 1.0 * t - G * t * t / 2


def _frames(first=0, n=N):
    return np.arange(first, first + n) / FPS


def _f(v) -> str:
    """A number written exactly (shortest round-trip repr)."""
    return repr(float(v))


@pytest.fixture(scope="module")
def camera():
    """The camera of the pixel fixtures: 640 x 480, 3 m from the ball's plane y = 0."""
    return Camera.from_opencv([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]], (0.02, 0, 0, 0, 0),
                              (math.pi / 2, 0, 0), (0.0, 0.8, 3.0), name="side", size=(640, 480))


@pytest.fixture(scope="module")
def pixels_a(camera):
    """OpenCV pixels of ball A at the 12 frames."""
    t = _frames()
    x, z = ball_a(t)
    return np.asarray(camera.project(np.stack([x, np.zeros(N), z], axis=1)))


def _assert_ball(tracks: Tracks, name, t, f, *, lost=(), atol=1e-12, rtol=0.0):
    """``tracks``' ball ``name`` is ``f`` sampled at ``t`` (x -> x, y -> z), NaN at ``lost``."""
    x, z = f(t)
    x, z = np.array(x, dtype=float), np.array(z, dtype=float)
    x[list(lost)] = np.nan
    z[list(lost)] = np.nan
    np.testing.assert_allclose(tracks.t[name], t, rtol=rtol, atol=atol)
    p = tracks.position[name]
    np.testing.assert_allclose(p[:, 0], x, rtol=rtol, atol=atol)
    np.testing.assert_allclose(p[:, 2], z, rtol=rtol, atol=atol)
    assert np.all(np.isnan(p[:, 1]))


# ------------------------------------------------------------------------------ Tracker, metres


def test_tracker5_tab_one_track_with_blank_cells():
    tr = read_tracker(DATA / "tracker5_tab.txt", units="m")
    assert isinstance(tr, Tracks) and tr.balls == ("mass_A",) and not tr.has_y
    _assert_ball(tr, "mass_A", _frames(), ball_a, lost=[5])  # the unmarked frame stays, as NaN
    assert tr.n_obs("mass_A") == N - 1


def test_tracker5_semicolon_decimal_comma_unformatted():
    tr = read_tracker(DATA / "tracker5_semicolon_comma.txt", units="m", ball="pingpong")
    assert tr.balls == ("pingpong",)
    # "0.000000E0": 7 significant digits
    _assert_ball(tr, "pingpong", _frames(), ball_a, rtol=5e-7, atol=1e-15)


def test_tracker6_two_tracks_side_by_side():
    tr = read_tracker(DATA / "tracker6_two_tracks_tab.txt", units="m", ball={"mass A": "golf", "mass B": "bocce"})
    assert tr.balls == ("golf", "bocce")
    t = _frames(0, N + 2)  # one row per frame, from A's first to B's last
    _assert_ball(tr, "golf", t, ball_a, lost=[N, N + 1])
    _assert_ball(tr, "bocce", t, ball_b, lost=[0, 1])
    assert tr.n_obs("golf") == tr.n_obs("bocce") == N


def test_tracker6_comma_and_decimal_comma():
    tr = read_tracker(DATA / "tracker6_comma.txt", units="m")
    assert tr.balls == ("mass A",)
    _assert_ball(tr, "mass A", _frames(), ball_a)
    tr = read_tracker(DATA / "tracker6_tab_decimal_comma.txt", units="m")
    _assert_ball(tr, "mass A", _frames(), ball_a, atol=5.0001e-5)  # formatted with 4 decimals


def test_tracker_space_delimiter(tmp_path):
    t = _frames()
    x, z = ball_a(t)
    rows = [f"{_f(t[k])} {_f(x[k])} {_f(z[k])} " if k != 3 else f"{_f(t[k])}   " for k in range(N)]
    p = tmp_path / "space.txt"
    p.write_text("mass_A\nt x y vx\n" + "\n".join(rows) + "\n")
    _assert_ball(read_tracker(p, units="m"), "mass_A", t, ball_a, lost=[3])


def test_tracker_copy_data_has_no_name(tmp_path):
    t = _frames()
    x, z = ball_a(t)
    p = tmp_path / "copy.txt"
    p.write_text("t\tx\ty\n" + "".join(f"{_f(t[k])}\t{_f(x[k])}\t{_f(z[k])}\n" for k in range(N)))
    _assert_ball(read_tracker(p, units="m", ball="golf"), "golf", t, ball_a)
    with pytest.raises(TracksError, match="does not name its track"):
        read_tracker(p, units="m")
    with pytest.raises(TracksError, match="does not name its track, so ball cannot map"):
        read_tracker(p, units="m", ball={"mass A": "golf"})


def test_tracker_ms_header_and_none_leaves_a_track_out(tmp_path):
    t = _frames()
    x, z = ball_a(t)
    p = tmp_path / "ms.txt"
    p.write_text("\tA\t\tB\t\nt (ms)\tx (m)\ty (m)\tx (m)\ty (m)\n"
                 + "".join(f"{_f(1000 * t[k])}\t{_f(x[k])}\t{_f(z[k])}\t\t\n" for k in range(N)))
    tr = read_tracker(p, units="m", ball={"A": "golf", "B": None})
    assert tr.balls == ("golf",)
    _assert_ball(tr, "golf", t, ball_a)


# ------------------------------------------------------------------------------ Kinovea, metres


def test_kinovea_csv_two_trajectories_seconds():
    tr = read_kinovea(DATA / "kinovea_two_trajectories.csv", units="m", time_unit="s")
    assert tr.balls == ("ball", "ball 2")
    t = np.round(1000 * _frames(0, N + 3)) / 1000  # classic time: whole milliseconds
    np.testing.assert_allclose(tr.t["ball"], t, rtol=0, atol=1e-15)
    for name, f, first in (("ball", ball_a, 0), ("ball 2", ball_b, 3)):
        x, z = f(_frames(0, N + 3))  # the positions are those of the frames' exact times
        lost = [k for k in range(N + 3) if not first <= k < first + N]
        x[lost] = z[lost] = np.nan
        np.testing.assert_allclose(tr.position[name][:, 0], x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(tr.position[name][:, 2], z, rtol=0, atol=1e-12)


def test_kinovea_csv_semicolon_decimal_comma_milliseconds():
    tr = read_kinovea(DATA / "kinovea_semicolon_ms.csv", units="m", time_unit="ms", ball="pingpong")
    _assert_ball(tr, "pingpong", _frames(), ball_a, atol=1e-12)


def test_kinovea_gnuplot_text():
    tr = read_kinovea(DATA / "kinovea_gnuplot.txt", units="m", time_unit="s")
    assert tr.balls == ("ball", "ball 2")
    _assert_ball(tr, "ball", _frames(), ball_a, lost=[7])  # "NaN NaN"
    _assert_ball(tr, "ball 2", _frames(), ball_b)


def test_kinovea08_gnuplot_without_names():
    tr = read_kinovea(DATA / "kinovea08_gnuplot.txt", units="m", time_unit="s", ball={"1": "golf", "2": "bocce"})
    _assert_ball(tr, "golf", _frames(), ball_a)
    _assert_ball(tr, "bocce", _frames(), ball_b)


# ------------------------------------------------------------------------------ pixels


def test_tracker_pixels_y_up_origin_at_the_centre(camera, pixels_a):
    # Tracker shows the axes origin at (320, 240) from the video's top-left corner.
    it = read_tracker(DATA / "tracker6_pixels_yup.txt", units="px", camera=camera, origin=(319.5, 239.5), y_up=True)
    assert isinstance(it, ImageTracks) and it.balls == ("mass A",) and it.cameras == (camera,)
    uv = it.uv["mass A"]
    keep = np.arange(N) != 4
    np.testing.assert_allclose(uv[keep], pixels_a[keep], rtol=0, atol=1e-9)
    assert np.all(np.isnan(uv[4]))  # the blank sample
    np.testing.assert_allclose(it.t["mass A"], _frames(), rtol=0, atol=1e-15)
    assert np.all(it.view["mass A"] == 0) and it.n_obs("mass A") == N - 1


def test_tracker_pixels_rotated_axes(tmp_path, camera, pixels_a):
    # Tracker's ImageCoordSystem: image = origin + R(angle) (x, -y) (image y down); the file
    # holds the inverse of that map of the projected pixels (+ 0.5: pixel corners).
    x0, y0, a = 300.25, 260.5, math.radians(12.0)
    du, dv = pixels_a[:, 0] + 0.5 - x0, pixels_a[:, 1] + 0.5 - y0
    x = math.cos(a) * du - math.sin(a) * dv
    y = -(math.sin(a) * du + math.cos(a) * dv)
    p = tmp_path / "rotated.txt"
    p.write_text("mass_A\nt\tx\ty\n" + "".join(f"{_f(k / FPS)}\t{_f(x[k])}\t{_f(y[k])}\n" for k in range(N)))
    it = read_tracker(p, units="px", camera=camera, origin=(x0 - 0.5, y0 - 0.5), y_up=True, angle_deg=12.0)
    np.testing.assert_allclose(it.uv["mass_A"], pixels_a, rtol=0, atol=1e-9)


def test_kinovea_image_space_pixels(camera, pixels_a):
    it = read_kinovea(DATA / "kinovea_image_pixels.csv", units="px", time_unit="s", camera=camera, origin=(0, 0),
                      y_up=False)
    np.testing.assert_allclose(it.uv["ball"], pixels_a, rtol=0, atol=1e-9)


def test_kinovea_world_space_pixels_y_up(tmp_path, camera, pixels_a):
    # Uncalibrated world space: pixels from the image centre, y up.
    u0, v0 = 319.5, 239.5
    p = tmp_path / "world.txt"
    p.write_text("#Kinovea Trajectory data export\n#T X Y\n\n# ball\n"
                 + "".join(f"{_f(k / FPS)} {_f(pixels_a[k, 0] - u0)} {_f(v0 - pixels_a[k, 1])}\n" for k in range(N)))
    it = read_kinovea(p, units="px", time_unit="s", camera=camera, origin=(u0, v0), y_up=True)
    np.testing.assert_allclose(it.uv["ball"], pixels_a, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------ errors


def _tracker_text(rows=N, name="mass_A", header="t\tx\ty", row=None):
    t = _frames(0, rows)
    x, z = ball_a(t)
    row = row or (lambda k: f"{_f(t[k])}\t{_f(x[k])}\t{_f(z[k])}")
    return f"{name}\n{header}\n" + "".join(row(k) + "\n" for k in range(rows))


GOOD = _tracker_text()
TWO = "\tA\t\tB\t\nt\tx\ty\tx\ty\t\n" + "".join(f"{k / FPS!r}\t0.1\t1.0\t0.2\t0.9\n" for k in range(N))


@pytest.mark.parametrize("text, kwargs, line, message", [
    ("", {}, 1, "the file is empty"),
    ("\n  \n", {}, 1, "the file is empty"),
    (_tracker_text(header="x\ty"), {}, 2, "no time column"),
    (_tracker_text(header="t|x|y"), {}, 2, "unknown delimiter"),
    (_tracker_text(row=lambda k: f"{k / FPS!r}\tabc\t1.0"), {}, 3, "x = 'abc' is not a number"),
    (_tracker_text(row=lambda k: f"{k / FPS!r}\t0.1\tinf"), {}, 3, "y = 'inf' is not a finite number"),
    (_tracker_text(row=lambda k: f"{0.1 * (k % 5)!r}\t0.1\t1.0"), {}, 8, "times must increase strictly"),
    (_tracker_text(row=lambda k: f"{0.1 * min(k, 3)!r}\t0.1\t1.0"), {}, 7,
     "repeats t = 0.30000000000000004 s (line 6)"),
    (_tracker_text(row=lambda k: ("\t0.1\t1.0" if k == 2 else f"{k / FPS!r}\t0.1\t1.0")), {}, 5, "t is missing"),
    (_tracker_text(rows=5), {}, 1, "has only 5 valid samples"),
    (_tracker_text(row=lambda k: f"{k / FPS!r}\t0.1\t" + ("1.0" if k < 4 else "")), {}, 1,
     "has only 4 valid samples"),
    (GOOD, {"ball": {"mass_A": "golf", "mass C": "bocce"}}, None, "unknown track name(s) ['mass C']"),
    (TWO, {"ball": {"A": "golf"}}, None, "track(s) ['B'] of the file are not in ball"),
    (TWO, {"ball": "golf"}, None, "names one ball but the file holds 2 tracks ['A', 'B']"),
    (TWO, {"ball": {"A": "golf", "B": "golf"}}, None, "must be distinct"),
    (_tracker_text(row=lambda k: f"{k / FPS!r}\t0.1\t{1.0 if k != 6 else 250.0}"), {}, 9,
     "(x, y) = (0.1, 250) of track 'mass_A' is not a position in metres"),
    (_tracker_text(row=lambda k: f"{2e4 + k!r}\t0.1\t1.0"), {}, 3, "is not a time in seconds"),
    (_tracker_text(header="t\tx (px)\ty (px)"), {}, 2, "the position columns state 'px' but units='m'"),
    (_tracker_text(header="t\tx (cm)\ty (cm)"), {}, 2, "column 'x (cm)' is in 'cm'"),
    (_tracker_text(header="t (min)\tx\ty"), {}, 2, "the time column 't (min)' is in 'min'"),
    (_tracker_text(header="t\tpixelx\tpixely\tvx"), {}, 2, "has no x column(s)"),
    (_tracker_text(header="t\tx\tx\ty"), {}, 2, "has 2 x column(s)"),
    (_tracker_text(header="t,x,y", row=lambda k: f"{k / FPS:.3f},0,1,1,2".replace(".", ",")), {}, 3,
     "6 fields, expected 3"),
    (_tracker_text(row=lambda k: f"{k / FPS!r}\t0,1\t1.0"), {}, 3, "mix decimal points (first on line 3)"),
    ("mass_A\n", {}, 2, "no column names after the track name 'mass_A'"),
    ("mass_A\nt\t\ty\n0\t1\t2\n", {}, 2, "column(s) [2] of 't\\t\\ty' have no name"),
    (" mass A  \nt x y \n" + "".join(f"{k} 1 2\n" for k in range(N)), {}, 1, "cannot be split"),
    ("x\tA\t\nt\tx\ty\n", {}, 1, "has 'x' over the time column"),
])
def test_tracker_errors(tmp_path, text, kwargs, line, message):
    p = tmp_path / "export.txt"
    p.write_text(text)
    with pytest.raises(TracksError) as err:
        read_tracker(p, units="m", **kwargs)
    where = f"{p}: line {line}: " if line is not None else f"{p}: "
    assert str(err.value).startswith(where), str(err.value)
    assert message in str(err.value), str(err.value)


def test_argument_errors(tmp_path, camera):
    p = tmp_path / "export.txt"
    p.write_text(GOOD)
    cases = [
        (dict(units="cm"), "units='cm'"),
        (dict(units="px"), "needs camera="),
        (dict(units="px", camera=camera), "needs origin=(u0, v0)"),
        (dict(units="px", camera=camera, origin=(1.0, 2.0, 3.0)), "needs origin=(u0, v0)"),
        (dict(units="px", camera=camera, origin=(1.0, math.nan)), "is not finite"),
        (dict(units="px", camera=camera, origin=(1.0, 2.0)), "needs y_up=True or False"),
        (dict(units="px", camera=camera, origin=(1.0, 2.0), y_up=1), "needs y_up=True or False"),
        (dict(units="m", camera=camera), "['camera'] given with units='m'"),
        (dict(units="m", origin=(0, 0), y_up=True), "['origin', 'y_up'] given with units='m'"),
        (dict(units="m", ball=3), "ball=3; it is a ball name"),
        (dict(units="m", ball=""), "ball='' is not a ball name"),
        (dict(units="m", ball={"mass_A": None}), "nothing to read"),
    ]
    for kwargs, message in cases:
        with pytest.raises(TracksError) as err:
            read_tracker(p, **kwargs)
        assert str(err.value).startswith(f"{p}: ") and message in str(err.value), (kwargs, str(err.value))
    with pytest.raises(FileNotFoundError):
        read_tracker(tmp_path / "missing.txt", units="m")
    with pytest.raises(TracksError, match="time_unit='min'"):
        read_kinovea(p, units="m", time_unit="min")


def test_pixels_beyond_an_image(tmp_path, camera):
    p = tmp_path / "export.txt"
    p.write_text(_tracker_text(row=lambda k: f"{k / FPS!r}\t{3e5 if k == 3 else 10.0}\t20.0"))
    with pytest.raises(TracksError, match=rf"^{p}: line 6: \(u, v\) = \(300000, 20\) of track 'mass_A' is not a pixel"):
        read_tracker(p, units="px", camera=camera, origin=(0, 0), y_up=False)


KINOVEA_CSV = '"Time","ball/0/X","ball/0/Y"\n' + "".join(f'"{k / FPS!r}","0.1","1.0"\n' for k in range(N))


@pytest.mark.parametrize("text, kwargs, line, message", [
    (KINOVEA_CSV, {}, 1, "pass time_unit='s' or 'ms'"),
    (KINOVEA_CSV.replace('"Time"', '"Time (ms)"'), {"time_unit": "s"}, 1, "states ms but time_unit='s'"),
    ("t;x;y\n0;1;2\n", {"time_unit": "s"}, 1, "are not Kinovea trajectories"),
    ("Frame,X,Y\n0,1,2\n", {"time_unit": "s"}, 1, "not a Kinovea trajectory export"),
    ('"Time","ball/0/X","ball/0/Z"\n', {"time_unit": "s"}, 1, "is not <name>/<point>/X or /Y"),
    ('"Time","ball/0/X","ball 2/0/Y"\n', {"time_unit": "s"}, 1, "trajectory 'ball' has only its ['X'] column"),
    ('"Time","ball/0/X","ball/0/Y"\n"0.0","0.1"\n', {"time_unit": "s"}, 2, "2 fields, expected 3"),
    ("#Kinovea Trajectory data export\n#T X Y Z\n", {"time_unit": "s"}, 2, "expected '#T X Y'"),
    ("#Kinovea Trajectory data export\n#T X Y\n\n# ball\n0.0 1.0 2.0 3.0 4.0\n", {"time_unit": "s"}, 5,
     "5 fields, expected 3 (t x y)"),
    ("#Kinovea Trajectory data export\n#T X Y\n\n# ball\n0.0 1.0 2.0\n\n1.0 2.0 3.0\n", {"time_unit": "s"}, 7,
     "rows without a '# <name>' line"),
    (KINOVEA_CSV, {"time_unit": "s", "ball": {"ball 2": "golf"}}, None, "unknown track name(s) ['ball 2']"),
])
def test_kinovea_errors(tmp_path, text, kwargs, line, message):
    p = tmp_path / "export.csv"
    p.write_text(text)
    with pytest.raises(TracksError) as err:
        read_kinovea(p, units="m", **kwargs)
    where = f"{p}: line {line}: " if line is not None else f"{p}: "
    assert str(err.value).startswith(where), str(err.value)
    assert message in str(err.value), str(err.value)


def test_kinovea_refuses_timecodes_and_kinematics_dialogs():
    p = DATA / "kinovea08_timecode.txt"
    with pytest.raises(TracksError, match=rf"^{p}: line 3: t = '0:00:00:00' is a timecode"):
        read_kinovea(p, units="m", time_unit="s")
    p = DATA / "kinovea_kinematics.csv"
    with pytest.raises(TracksError, match=rf"^{p}: line 1: .*kinematics dialog's export"):
        read_kinovea(p, units="m", time_unit="ms")


# ------------------------------------------------------------------- through `estim fit`


def test_estim_fit_reads_a_tracker_export(tmp_path, capsys):
    # The bundled demo's golf ball (made from known parameters, data/tracks/make_demo.py),
    # exported as Tracker 6 writes one track (tab-delimited, decimal commas, blank cells
    # where the demo lost a coordinate), fitted by `estim fit --format tracker --units m`.
    tracks = estim.read_tracks_csv("data/tracks/stairs_demo.csv")
    t, p = tracks.t["golf"], tracks.position["golf"]
    cell = lambda v: "" if not np.isfinite(v) else repr(float(v)).replace(".", ",")  # noqa: E731
    lines = ["\tmass A\t\t", "t\tx\ty\t"] + [f"{cell(a)}\t{cell(b)}\t{cell(c)}\t" for a, b, c in zip(t, p[:, 0], p[:, 2], strict=True)]
    path = tmp_path / "golf.txt"
    path.write_text("\n".join(lines) + "\n")
    code = main(["fit", str(path), "--format", "tracker", "--units", "m", "--ball", "golf",
                 "--scene", "data/scenes/stairs.xml", "--json"])
    out = json.loads(capsys.readouterr().out)["balls"]["golf"]
    assert code == 0
    assert abs(out["e"] - 0.725) < 3 * out["stderr"]["e"] and abs(out["vx0"] - 1.275) < 3 * out["stderr"]["vx0"]


def test_estim_fit_names_what_an_export_needs(tmp_path, capsys):
    path = tmp_path / "x.txt"
    path.write_text("mass_A\nt\tx\ty\n")
    assert main(["fit", str(path), "--format", "tracker", "--scene", "data/scenes/stairs.xml"]) == 2
    assert "needs --units m or px" in capsys.readouterr().err
    assert main(["fit", str(path), "--units", "m", "--scene", "data/scenes/stairs.xml"]) == 2
    assert "only applies with --format tracker|kinovea" in capsys.readouterr().err
