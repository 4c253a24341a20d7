"""``estim bench accuracy`` (the work-precision study of docs/pages/accuracy.md), in its
quick mode: Tsit5 at rtol 1e-4 and 1e-9 (the default) on the seed scene without air (against the closed
form), in still air and for a spinning table-tennis shot (against Tsit5 at rtol 1e-12).

The truths: without air every Runge-Kutta method integrates the parabolas exactly, so the
ODE path must reproduce the closed form's event times, final positions and gradient to
rounding; in air, the default setting must agree with the tight reference to far below the
contact slack. The committed docs table is checked for what it claims (every row of the
full study present, the reference converged, the default within its slack). The command
writes files only into --out, never into docs/; the page is written by
docs/scripts/accuracy.py, whose splicing is checked here on a copy.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
from pathlib import Path

import numpy as np
import pytest

from estim.app._bench import ACCURACY_RTOLS, ACCURACY_SOLVERS, format_accuracy
from estim.app._cli import build_parser, main

ROOT = Path(__file__).resolve().parent.parent
PAGES = ROOT / "docs" / "pages"
pytestmark = pytest.mark.slow  # compiles four ODE programs (about a minute on 2 cores)


def _docs_script():
    """docs/scripts/accuracy.py, imported as a module (it is not part of the package)."""
    spec = importlib.util.spec_from_file_location("docs_accuracy", ROOT / "docs" / "scripts" / "accuracy.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _docs_state():
    return {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted(PAGES.glob("accuracy*"))}


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """``estim bench accuracy --quick --repeats 1 --json --out DIR``, with the docs pages
    snapshotted before and after."""
    out = tmp_path_factory.mktemp("accuracy")
    before = _docs_state()
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["bench", "accuracy", "--quick", "--repeats", "1", "--out", str(out), "--json"]) == 0
    return json.loads(buf.getvalue()), out, (before, _docs_state())


def test_vacuum_ode_path_reproduces_the_closed_form(quick):
    r, _, _ = quick
    rows = r["vacuum"]["rows"]
    assert [(x["solver"], x["rtol"]) for x in rows] == [("closed form", None), ("Tsit5", 1e-4), ("Tsit5", 1e-9)]
    exact = np.array(r["vacuum"]["closed_form_gradient"])
    assert np.all(np.isfinite(exact)) and np.all(exact != 0)
    for x in rows[1:]:
        assert x["events_match"] and x["complete"], x
        assert x["event_time_error"] < 1e-12 and x["final_position_error"] < 1e-12, x
        np.testing.assert_allclose(x["gradient"], exact, rtol=1e-10, atol=1e-12)
        assert x["forward_ms"] > 0 and x["gradient_ms"] > 0 and x["steps"] > 0


def test_air_default_agrees_with_the_reference(quick):
    r, _, _ = quick
    air = r["air"]
    assert air["reference"]["complete"] and air["reference"]["steps"] > 0
    default = next(x for x in air["rows"] if x["rtol"] == 1e-9)
    assert default["events_match"] and default["complete"]
    # The default is chosen to meet 1e-9 m on this scene (docs/pages/accuracy.md).
    assert default["event_time_error"] < 1e-9 and default["final_position_error"] < 1e-9, default
    assert default["gradient_error"] < 1e-5 * np.max(np.abs(air["reference"]["gradient"]))
    # Air changes the answer: the reference differs from the vacuum run by far more.
    vac = np.array(r["vacuum"]["closed_form_gradient"])
    assert np.max(np.abs(np.array(air["reference"]["gradient"]) - vac)) > 1e3 * default["gradient_error"]


def test_shot_default_agrees_with_the_reference(quick):
    """The spinning table-tennis shot in air: at the default setting, and in the plain
    diffrax loop, the same single bounce as the tight reference, within 1e-9 m of it, and
    the same gradient."""
    r, _, _ = quick
    shot = r["shot"]
    assert shot["reference"]["events"] == [1]
    default = next(x for x in shot["rows"] if x["rtol"] == 1e-9)
    assert default["events_match"] and default["complete"]
    assert default["event_time_error"] < 1e-9 and default["final_position_error"] < 1e-9, default
    assert default["gradient_error"] < 1e-5 * np.max(np.abs(shot["reference"]["gradient"]))
    loop = shot["event_loop"]
    assert loop["events_match"] and loop["final_position_error"] < 1e-9, loop


def test_files_written_into_out_and_nothing_into_docs(quick):
    r, out, (before, after) = quick
    assert sorted(p.name for p in out.iterdir()) == ["accuracy.json", "accuracy.png", "accuracy_table.md"]
    assert (out / "accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "accuracy_table.md").read_text().strip() == format_accuracy(r).strip()
    assert json.loads((out / "accuracy.json").read_text()) == r
    assert before == after and "accuracy.md" in before  # docs/pages untouched
    assert build_parser().parse_args(["bench", "accuracy"]).out is None  # no default folder


def test_docs_script_writes_the_page(quick, tmp_path):
    """docs/scripts/accuracy.py splices the study's table between the page's markers,
    keeps the text around them and writes the plot and the values beside it; a page
    without the markers is refused before anything is written."""
    r, _, _ = quick
    script = _docs_script()
    assert script.TABLE_START in (PAGES / "accuracy.md").read_text()  # the committed page has them
    (tmp_path / "accuracy.md").write_text(
        f"# page\n\nbefore\n\n{script.TABLE_START}\nold table\n{script.TABLE_END}\n\nafter\n")
    paths = script.write_page(r, tmp_path)
    assert sorted(p.name for p in paths) == ["accuracy.json", "accuracy.md", "accuracy.png"]
    page = (tmp_path / "accuracy.md").read_text()
    assert "old table" not in page and page.startswith("# page\n\nbefore\n") and page.endswith("after\n")
    assert format_accuracy(r).strip() in page
    assert (tmp_path / "accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "accuracy.json").read_text()) == r
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "accuracy.md").write_text("# a page without markers\n")
    with pytest.raises(ValueError, match="table markers"):
        script.write_page(r, bare)
    assert sorted(p.name for p in bare.iterdir()) == ["accuracy.md"]


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
    assert format_accuracy(r).strip() in (PAGES / "accuracy.md").read_text()
