"""``estim bench accuracy`` (the work-precision study of docs/pages/accuracy.md), in its
quick mode: Tsit5 at rtol 1e-4 and 1e-8 on the seed scene without air (against the closed
form) and in still air (against Tsit5 at rtol 1e-12).

The truths: without air every Runge-Kutta method integrates the parabolas exactly, so the
ODE path must reproduce the closed form's event times, final positions and gradient to
rounding; in air, the default setting must agree with the tight reference to far below the
contact slack. The committed docs table is checked for what it claims (every row of the
full study present, the reference converged, the default within its slack).
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

from estim.app._bench import ACCURACY_RTOLS, ACCURACY_SOLVERS, TABLE_END, TABLE_START
from estim.app._cli import main

PAGES = Path(__file__).resolve().parent.parent / "docs" / "pages"
pytestmark = pytest.mark.slow  # compiles four ODE programs (about a minute on 2 cores)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """``estim bench accuracy --quick --repeats 1 --json`` into a folder whose accuracy.md
    holds the table markers (so the command must splice its table in)."""
    out = tmp_path_factory.mktemp("accuracy")
    (out / "accuracy.md").write_text(f"# page\n\nbefore\n\n{TABLE_START}\nold table\n{TABLE_END}\n\nafter\n")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["bench", "accuracy", "--quick", "--repeats", "1", "--out", str(out), "--json"]) == 0
    return json.loads(buf.getvalue()), out


def test_vacuum_ode_path_reproduces_the_closed_form(quick):
    r, _ = quick
    rows = r["vacuum"]["rows"]
    assert [(x["solver"], x["rtol"]) for x in rows] == [("closed form", None), ("Tsit5", 1e-4), ("Tsit5", 1e-8)]
    exact = np.array(r["vacuum"]["closed_form_gradient"])
    assert np.all(np.isfinite(exact)) and np.all(exact != 0)
    for x in rows[1:]:
        assert x["events_match"] and x["complete"], x
        assert x["event_time_error"] < 1e-12 and x["final_position_error"] < 1e-12, x
        np.testing.assert_allclose(x["gradient"], exact, rtol=1e-10, atol=1e-12)
        assert x["forward_ms"] > 0 and x["gradient_ms"] > 0 and x["steps"] > 0


def test_air_default_agrees_with_the_reference(quick):
    r, _ = quick
    air = r["air"]
    assert air["reference"]["complete"] and air["reference"]["steps"] > 0
    default = next(x for x in air["rows"] if x["rtol"] == 1e-8)
    assert default["events_match"] and default["complete"]
    # The ball may leave its parabola by contact_slack = 1e-6 m per step; the default's
    # errors must be far below that (event times in s, positions in m).
    assert default["event_time_error"] < 1e-7 and default["final_position_error"] < 1e-7, default
    assert default["gradient_error"] < 1e-5 * np.max(np.abs(air["reference"]["gradient"]))
    # Air changes the answer: the reference differs from the vacuum run by far more.
    vac = np.array(r["vacuum"]["closed_form_gradient"])
    assert np.max(np.abs(np.array(air["reference"]["gradient"]) - vac)) > 1e3 * default["gradient_error"]


def test_files_written_and_table_spliced_into_the_page(quick):
    r, out = quick
    for name in ("accuracy_table.md", "accuracy.png", "accuracy.json"):
        assert (out / name).stat().st_size > 0, name
    assert (out / "accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = (out / "accuracy_table.md").read_text()
    page = (out / "accuracy.md").read_text()
    assert "old table" not in page and page.startswith("# page\n\nbefore\n") and page.endswith("after\n")
    assert table.strip() in page
    assert json.loads((out / "accuracy.json").read_text())["vacuum"]["rows"][0]["solver"] == "closed form"


def test_committed_study_is_complete_and_consistent():
    """docs/pages/accuracy.json is the full study the docs table shows: every solver at
    every rtol on both scenes, its reference converged, the table on the page generated
    from it."""
    r = json.loads((PAGES / "accuracy.json").read_text())
    assert not r["quick"]
    for scene in ("vacuum", "air"):
        pairs = {(x["solver"], x["rtol"]) for x in r[scene]["rows"]}
        assert {(s, t) for s in ACCURACY_SOLVERS for t in ACCURACY_RTOLS} <= pairs, scene
    for x in r["vacuum"]["rows"]:
        assert x["final_position_error"] < 1e-11, x
    chk = r["air"]["reference_check"]
    assert chk["events_match"] and chk["final_position_error"] < 1e-9, chk
    from estim.app._bench import format_accuracy

    assert format_accuracy(r).strip() in (PAGES / "accuracy.md").read_text()
