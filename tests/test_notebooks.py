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
import math
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest
from conftest import CACHE_DIR

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
REALDATA = ROOT.parent / "shared" / "realdata" / "pingpong_drop_nicofighter45"
ACCURACY_JSON = ROOT / "docs" / "pages" / "accuracy.json"  # the committed full study, if any


def run_notebook(name: str, out: pathlib.Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, ESTIM_NOTEBOOK_OUT=str(out), ESTIM_NOTEBOOK_FAST="1")
    env.setdefault("MUJOCO_GL", "egl")  # offscreen rendering without a display
    env.pop("DISPLAY", None)  # headless, as in CI: nothing may open a window
    # The notebooks switch JAX's persistent cache on, as for a user (conftest turns it off
    # for the suite's own processes), here in the run's cache: they load what the suite's
    # tests compiled before them (the same study, fits and derivatives) instead of
    # compiling it again.
    env.pop("ESTIM_NO_CACHE", None)
    env["ESTIM_CACHE_DIR"] = str(CACHE_DIR)
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
    assert names[:7] == ["01_three_balls.py", "02_fit_video_tracks.py", "03_gradient_sanity.py",
                         "04_accuracy_cost.py", "05_effects.py", "06_table_tennis.py", "07_cameras.py"]
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
@pytest.mark.slow
def test_03_gradient_sanity(tmp_path):
    proc = run_notebook("03_gradient_sanity.py", tmp_path)
    assert_files(tmp_path, ["03_dz_de.png", "03_grazing.png", "03_gradient_sanity.json"])
    s = summary(proc, tmp_path, "03_gradient_sanity")
    assert s["d_xfinal_d_e_mu_vx0"] == pytest.approx([0.19213914, 6.81524982, 2.17816532], abs=5e-8)
    assert s["event_times_autodiff_vs_implicit"] < 1e-12
    assert s["frozen_dxfinal_de_error"] == pytest.approx(-0.19213914, abs=1e-7)
    assert s["grazing_slope"] == pytest.approx(-0.5, abs=1e-3)


@pytest.mark.slow
def test_04_accuracy_cost(tmp_path):
    proc = run_notebook("04_accuracy_cost.py", tmp_path)
    committed = ACCURACY_JSON.is_file()
    expected = ["04_accuracy_live.png", "04_steps_error.png", "04_accuracy_live.json", "04_accuracy_cost.json"]
    expected += ["04_accuracy_committed.png"] if committed else []
    assert_files(tmp_path, expected)
    s = summary(proc, tmp_path, "04_accuracy_cost")
    assert s["committed"]["present"] == committed
    if committed:
        assert "error" not in s["committed"], s["committed"]
    else:
        assert "Committed study not found" in proc.stdout
    # (a) Vacuum: the closed form's seed numbers (9 / 6 / 4 events, the seed gradient of
    # notebook 3), and the ODE path agrees with it to rounding (its cost is shown, not
    # asserted: timings belong to benchmarks).
    assert s["vacuum_events"] == [9, 6, 4]
    assert s["closed_form_gradient"] == pytest.approx([0.19213914, 6.81524982, 2.17816532], abs=5e-8)
    assert s["vacuum_max_error"] < 1e-9
    # (b) Still air: the default is within 1e-9 m of the tight reference, with its events;
    # tight tolerances take more steps, and at loose ones the steps around the contacts
    # are all that is left (the count stops falling).
    default, ref = s["air_default"], s["air_reference"]
    assert default["final_position_error"] < 1e-9 and default["event_time_error"] < 1e-9
    assert default["events"] == ref["events"] and ref["complete"]
    steps = s["tsit5_steps_by_rtol"]  # loosest first
    assert steps["1e-11"] > 2 * steps["1e-03"]
    assert 1e-9 <= s["steps_plateau_rtol"] <= 1e-4
    slack_steps = list(s["slack_steps"].values())  # loosest slack first
    assert slack_steps == sorted(slack_steps) and slack_steps[0] < slack_steps[-1]


@pytest.mark.slow
def test_05_effects(tmp_path):
    proc = run_notebook("05_effects.py", tmp_path)
    assert_files(tmp_path, ["05_drag_heights.png", "05_drop_delay.png", "05_magnus.png", "05_effects.json"])
    s = summary(proc, tmp_path, "05_effects")
    # The vacuum is the closed form: the seed's bounces; it never traced the ODE solver, and
    # every air run of the notebook shared one ODE program.
    assert s["vacuum_bounces"] == {"bocce": 9, "golf": 6, "pingpong": 4, "regulation pingpong": 4}
    assert s["ode_traces"] == {"after_vacuum": 0, "after_first_air": 1, "total": 1}
    # The vertical drop from rest through H with quadratic drag only, against the closed form
    # t = (v_t / g) arccosh(exp(g H / v_t^2)), v_t = sqrt(2 m g / (rho C_D pi r^2)).
    rho, cd, g, h = 1.204, 0.47, 9.81, s["drop_height"]
    balls = {"bocce": (0.08, 0.92), "golf": (0.05, 0.046), "pingpong": (0.04, 0.005),
             "regulation pingpong": (0.02, 0.0027)}
    for name, (r, m) in balls.items():
        vt = math.sqrt(2 * m * g / (rho * cd * math.pi * r**2))
        t = vt / g * math.acosh(math.exp(g * h / vt**2))
        assert s["drop_t"][name] == pytest.approx(t, rel=1e-7), name
        assert s["k_per_m"][name] == pytest.approx(g / vt**2, rel=1e-12)
    # Drag delays the ping-pong ball's first bounce on the stairs ~46 times as much as the
    # bocce ball's: the ratio of their drag constants k, to first order.
    k_ratio = s["k_per_m"]["pingpong"] / s["k_per_m"]["bocce"]
    assert k_ratio == pytest.approx(46.0, abs=0.1)
    assert s["stairs_delay_ratio_pingpong_bocce"] == pytest.approx(k_ratio, rel=0.1)
    assert s["stairs_bounce1_delay_ms"]["bocce"] > 0
    # Backspin lifts (a later first bounce), topspin dips.
    mag = s["magnus"]
    assert mag["pingpong backspin"]["bounce1_ms"] > 0 > mag["pingpong topspin"]["bounce1_ms"]
    assert mag["bocce backspin"]["bounce1_ms"] > 0 > mag["bocce topspin"]["bounce1_ms"]
    # Linear (Stokes) drag is far smaller than quadratic drag for every ball.
    effects = {e["effect"]: e["balls"] for e in s["effect_report"]["effects"]}
    for name in balls:
        assert 0 < effects["linear drag"][name]["bounce1_ms"] < 0.05 * effects["quadratic drag"][name]["bounce1_ms"]


def test_06_table_tennis(tmp_path):
    """The notebook checks its bounces against the friction law's closed forms and its edge
    ball against the geometry itself (it fails otherwise); here, what it reports."""
    proc = run_notebook("06_table_tennis.py", tmp_path)
    assert_files(tmp_path, ["06_spin.png", "06_fit.png", "06_table_tennis.json"])
    s = summary(proc, tmp_path, "06_table_tennis")
    # Magnus: topspin lands first, backspin last.
    t = s["bounce_t"]
    assert t["topspin"] < t["no spin"] < t["backspin"]
    # The edge ball touches the table's edge line (y = 1.37 m, z = 0) 1 cm beyond it: centre
    # at height sqrt(r^2 - d^2), the normal from the edge to the centre.
    r, d = 0.02, 0.01
    np.testing.assert_allclose(s["edge"]["position"], [0.0, 1.37 + d, math.sqrt(r * r - d * d)], atol=1e-9)
    np.testing.assert_allclose(s["edge"]["normal"], [0.0, d / r, math.sqrt(r * r - d * d) / r], atol=1e-9)
    # The fit of the synthetic 3D shot reads the truth (e 0.88, its spin; mu 0.3, unless the
    # topspin bounce grips and the scene's prior holds mu, which the notebook checks: the
    # true mu then moves the fitted path by less than a tenth of the noise).
    fit = s["fit"]
    assert abs(fit["e"] - 0.88) < 0.01 and fit["spin_error"] < 0.1
    assert abs(fit["mu"] - 0.3) < 0.03 or fit["mu_held_by_prior"], fit
    # The effects of the fitted model (estim.fit(effects=True)): drag, Magnus, the spin at the
    # bounce and the bounce's friction move the ball by many noise levels; the air's
    # viscosity (Stokes drag, 6 pi eta r v: 0.01 m/s^2 at 5 m/s for 2.7 g) by about a mm over
    # the track, below its noise.
    effects = s["effects"]
    assert list(effects) == ["quadratic drag", "linear drag", "Magnus", "spin at the bounce", "friction at the bounce"]
    assert all(effects[n]["noise_levels"] > 10 for n in effects if n != "linear drag"), effects
    assert effects["linear drag"]["verdict"] == "below the noise", effects

