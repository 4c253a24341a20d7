"""The notebooks (issue 7) run headless from a clean checkout and tell their story with the
right numbers.

Each notebook runs as a subprocess, ``python notebooks/NAME.py``, exactly as a user would
run it, with ``ESTIM_NOTEBOOK_OUT`` pointing at a temporary folder and
``ESTIM_NOTEBOOK_FAST=1`` (smaller GIFs). The notebooks assert their key numbers
themselves (bounces 9 / 6 / 4, the seed gradient, e of the real drops against the published
value, ...), so a broken notebook exits non-zero; the test also checks the files each one
writes and the numbers in its summary JSON.

Speed: most of a run is JAX compiling estim's programs (the fits and the derivatives take
one to three minutes on a 2-core machine when nothing is cached; JAX's persistent cache,
which the notebooks switch on, makes later runs faster).
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
REALDATA = ROOT.parent / "shared" / "realdata" / "pingpong_drop_nicofighter45"


def run_notebook(name: str, out: pathlib.Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, ESTIM_NOTEBOOK_OUT=str(out), ESTIM_NOTEBOOK_FAST="1")
    env.setdefault("MUJOCO_GL", "egl")  # offscreen rendering without a display
    env.pop("DISPLAY", None)  # headless, as in CI: nothing may open a window
    proc = subprocess.run([sys.executable, str(NOTEBOOKS / name)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, f"{name} failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-8000:]}"
    return proc


def assert_files(out: pathlib.Path, names) -> None:
    missing = [n for n in names if not (out / n).is_file() or (out / n).stat().st_size == 0]
    assert not missing, f"missing or empty outputs: {missing}; present: {sorted(p.name for p in out.iterdir())}"


def summary(proc: subprocess.CompletedProcess, out: pathlib.Path, name: str) -> dict:
    data = json.loads((out / f"{name}.json").read_text())
    assert f"{name}:" in proc.stdout  # the headless run prints its summary line
    return data


def test_notebooks_are_marimo_apps():
    """Every notebook is a valid marimo app (``marimo check --strict``: parseable cells,
    no variable defined in two cells, no cycles), openable with ``marimo edit``."""
    names = sorted(p.name for p in NOTEBOOKS.glob("[0-9][0-9]_*.py"))
    assert names[:3] == ["01_three_balls.py", "02_fit_video_tracks.py", "03_gradient_sanity.py"]
    proc = subprocess.run([sys.executable, "-m", "marimo", "check", "--strict", *names],
                          cwd=NOTEBOOKS, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for name in names:
        text = (NOTEBOOKS / name).read_text()
        assert "app = marimo.App(" in text and 'if __name__ == "__main__":\n    app.run()' in text


def test_01_three_balls(tmp_path):
    proc = run_notebook("01_three_balls.py", tmp_path)
    rendered = "MuJoCo GIF skipped" not in proc.stdout
    assert_files(tmp_path, ["01_heights.png", "01_energy.png", "01_sideview.gif", "01_three_balls.json"]
                 + (["01_mujoco.gif"] if rendered else []))
    s = summary(proc, tmp_path, "01_three_balls")
    assert s["bounces"] == {"bocce": 9, "golf": 6, "pingpong": 4}
    assert s["final_x"]["golf"] == pytest.approx(2.3048901184, abs=1e-9)


@pytest.mark.slow
def test_02_fit_video_tracks(tmp_path):
    proc = run_notebook("02_fit_video_tracks.py", tmp_path)
    have_real = (REALDATA / "table").is_dir()
    rendered = "MuJoCo replay skipped" not in proc.stdout
    expected = ["02_stairs_fit.png", "02_stairs_residuals.png", "02_sideview.gif", "02_fit_video_tracks.json"]
    expected += ["02_replay.gif"] if rendered else []
    expected += ["02_real_track.png", "02_real_e.png", "02_real_fit.png"] if have_real else []
    assert_files(tmp_path, expected)
    s = summary(proc, tmp_path, "02_fit_video_tracks")
    assert s["stairs"]["pingpong"]["e"] == pytest.approx(0.805, abs=0.002)
    if have_real:
        real = s["real"]
        assert real["e_whole_track"] < real["e_after_bounce_1"]
        assert abs(real["e_after_bounce_1"] - real["e_authors"]) < 0.02
    else:
        assert "Real data not found" in proc.stdout


@pytest.mark.slow
def test_03_gradient_sanity(tmp_path):
    proc = run_notebook("03_gradient_sanity.py", tmp_path)
    assert_files(tmp_path, ["03_dz_de.png", "03_grazing.png", "03_gradient_sanity.json"])
    s = summary(proc, tmp_path, "03_gradient_sanity")
    assert s["d_xfinal_d_e_mu_vx0"] == pytest.approx([0.19213914, 6.81524982, 2.17816532], abs=5e-8)
    assert s["event_times_autodiff_vs_implicit"] < 1e-12
    assert s["frozen_dxfinal_de_error"] == pytest.approx(-0.19213914, abs=1e-7)
    assert s["grazing_slope"] == pytest.approx(-0.5, abs=1e-3)
