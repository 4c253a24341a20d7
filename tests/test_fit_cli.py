"""``estim fit`` (``estim.app._cli.main`` in-process): the bundled demo tracks against their
truth, outputs, bad input (exit 2 with a message) and pixel mode on a real table drop."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from estim.app._cli import main, progress

ROOT = Path(__file__).resolve().parents[1]
SCENE = str(ROOT / "data" / "scenes" / "stairs.xml")
DROP = str(ROOT / "data" / "scenes" / "drop.xml")
DEMO_CSV = str(ROOT / "data" / "tracks" / "stairs_demo.csv")
DEMO_TRUTH = ROOT / "data" / "tracks" / "stairs_demo_truth.json"
REALDATA = ROOT.parent / "shared" / "realdata" / "pingpong_drop_nicofighter45"
PNG = b"\x89PNG\r\n\x1a\n"


def test_fit_demo_csv(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["fit", DEMO_CSV, "--scene", SCENE, "--out", str(out), "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    payload = json.loads(captured.out)
    truth = json.loads(DEMO_TRUTH.read_text())["balls"]
    assert set(payload["balls"]) == {"bocce", "golf", "pingpong"}
    for ball, fitted in payload["balls"].items():
        assert abs(fitted["e"] - truth[ball]["e"]) < 0.01, (ball, fitted["e"])
        assert abs(fitted["mu_t"] - truth[ball]["mu_t"]) < 0.01, (ball, fitted["mu_t"])
        assert abs(fitted["vx0"] - truth[ball]["vx0"]) < 0.01, (ball, fitted["vx0"])
        assert {"e", "mu_t", "vx0"} <= set(fitted["stderr"])
        assert all(fitted["stderr"][k] is not None and fitted["stderr"][k] > 0 for k in ("e", "mu_t", "vx0"))
        assert fitted["converged"] is True
        assert 0.0015 < fitted["rms_m"] < 0.0025  # the demo's noise is 2 mm
        assert fitted["n_obs"] > 100
    assert json.loads((out / "fit.json").read_text()) == payload
    for name in ("fit.png", "residuals.png", "loss.png"):
        data = (out / name).read_bytes()
        assert len(data) > 1000 and data.startswith(PNG), name


def test_a_video_clock_is_released_at_its_first_sample(tmp_path, capsys):
    """The bundled tracks on a video's clock (every time 12.34 s later): `estim fit` takes
    each ball's release at its first sample, says so, and fits what it fits on the
    release's own clock (the same values to rounding). `estim.fit` itself keeps t0 = 0
    (tests/test_fit.py::test_late_clock_is_pointed_out)."""
    lines = Path(DEMO_CSV).read_text().splitlines()
    shifted = [lines[0]] + [f"{float(a) + 12.34!r},{rest}" for a, rest in (row.split(",", 1) for row in lines[1:])]
    (tmp_path / "late.csv").write_text("\n".join(shifted) + "\n")
    fits = []
    for path in (DEMO_CSV, str(tmp_path / "late.csv")):
        assert main(["fit", path, "--scene", SCENE, "--json"]) == 0
        fits.append(json.loads(capsys.readouterr().out)["balls"])
    for ball, late in fits[1].items():
        assert "the track's clock starts at t = 12.340 s" in late["notes"][0]
        assert late["release"]["t"] == pytest.approx(12.34, abs=1e-9)
        for name in ("e", "mu_t", "vx0", "x0", "z0"):
            assert late[name] == pytest.approx(fits[0][ball][name], abs=1e-6), (ball, name)


def _fails(argv, capsys, *words):
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, (argv, err)
    assert err.strip(), argv
    for w in words:
        assert w.lower() in err.lower(), (w, err)
    return err


def test_fit_missing_file(tmp_path, capsys):
    missing = str(tmp_path / "nope.csv")
    _fails(["fit", missing, "--scene", SCENE], capsys, "nope.csv", "not found")


def test_fit_unknown_ball(tmp_path, capsys):
    p = tmp_path / "tennis.csv"
    p.write_text("t,ball,x,z\n" + "".join(f"{i / 60},tennis,{0.01 * i},{1.0 - 0.001 * i}\n" for i in range(12)))
    _fails(["fit", str(p), "--scene", SCENE], capsys, "tennis")


def test_fit_non_monotonic_time(tmp_path, capsys):
    times = [i / 60 for i in range(12)]
    times[5], times[6] = times[6], times[5]
    p = tmp_path / "order.csv"
    p.write_text("t,ball,x,z\n" + "".join(f"{t!r},golf,{0.01 * i},{1.0 - 0.001 * i}\n" for i, t in enumerate(times)))
    err = _fails(["fit", str(p), "--scene", SCENE], capsys, "order.csv")
    assert "line" in err


def test_fit_text_in_number_column(tmp_path, capsys):
    p = tmp_path / "text.csv"
    rows = [f"{i / 60!r},golf,{0.01 * i},{1.0 - 0.001 * i}\n" for i in range(12)]
    rows[3] = f"{3 / 60!r},golf,abc,0.99\n"
    p.write_text("t,ball,x,z\n" + "".join(rows))
    _fails(["fit", str(p), "--scene", SCENE], capsys, "text.csv", "abc", "not a number")


def test_fit_pixels_without_frame_interval(tmp_path, capsys):
    p = tmp_path / "px.txt"
    p.write_text("".join(f"{700 + i};{600 + i * i};\n" for i in range(20)))
    _fails(["fit", str(p), "--pixels", "--scene", DROP, "--ball", "pingpong"], capsys, "--frame-interval")


def test_fit_also_names_from_the_registry(capsys):
    """--also takes the registry's names (a vector's name for its components): the air's
    parameters in a scene without air are refused before any fit, naming them; a name the
    registry does not have is an argparse error."""
    err = _fails(["fit", DEMO_CSV, "--scene", SCENE, "--also", "spin"], capsys, "acts only in a scene with air")
    assert "spin_x" in err and "spin_z" in err
    _fails(["fit", DEMO_CSV, "--scene", SCENE, "--also", "drag_coefficient"], capsys, "acts only in a scene with air")
    with pytest.raises(SystemExit) as info:
        main(["fit", DEMO_CSV, "--scene", SCENE, "--also", "omega"])
    assert info.value.code == 2 and "invalid choice: 'omega'" in capsys.readouterr().err


def test_fit_frame_interval_without_pixels(capsys):
    _fails(["fit", DEMO_CSV, "--scene", SCENE, "--frame-interval", "0.01"], capsys, "--pixels")


def test_fit_pixels_real_table(capsys):
    f = REALDATA / "table" / "tracked-0.txt"
    if not f.is_file():
        pytest.skip(f"real data not found at {f}")
    code = main(["fit", str(f), "--pixels", "--frame-interval", "0.01", "--scene", DROP,
                 "--ball", "pingpong", "--json"])
    captured = capsys.readouterr()
    assert code in (0, 1), captured.err
    payload = json.loads(captured.out)
    assert payload["metres_per_pixel"] > 0
    assert 0.6 < payload["balls"]["pingpong"]["e"] < 0.95


def test_fit_progress_follows_sys_stderr(capsys):
    say = progress()
    say("hello from the progress reporter")
    assert "hello from the progress reporter" in capsys.readouterr().err
