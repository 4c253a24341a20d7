"""Notebook 2 (``notebooks/02_fit_video_tracks.py``), the longest: a module of its own, so
that under pytest-xdist it runs beside the other notebooks (``tests/test_notebooks.py``)."""

from __future__ import annotations

import pytest
from test_notebooks import REALDATA, assert_files, run_notebook, summary


def test_02_fit_video_tracks(tmp_path):
    proc = run_notebook("02_fit_video_tracks.py", tmp_path)
    have_real = (REALDATA / "table").is_dir()
    rendered = "MuJoCo replay skipped" not in proc.stdout
    expected = ["02_stairs_fit.png", "02_stairs_residuals.png", "02_sideview.gif", "02_fit_video_tracks.json"]
    expected += ["02_replay.gif"] if rendered else []
    expected += ["02_real_track.png", "02_real_e.png", "02_real_fit.png", "02_forest.png"] if have_real else []
    assert_files(tmp_path, expected)
    s = summary(proc, tmp_path, "02_fit_video_tracks")
    assert s["stairs"]["pingpong"]["e"] == pytest.approx(0.805, abs=0.002)
    if have_real:
        real = s["real"]
        assert real["e_whole_track"] < real["e_after_bounce_1"]
        assert abs(real["e_after_bounce_1"] - real["e_authors"]) < 0.02
        # Together, in still air: one e above the drag-free whole-track one, with an error
        # that carries the clips' scatter (wider than any single drop's noise-only one).
        pooled = s["pooled"]
        assert real["e_whole_track"] < pooled["e"] < 1.0 and pooled["se_e"] > 1e-4
    else:
        assert "Real data not found" in proc.stdout
