"""Notebook 7 (cameras), in a module of its own: a few minutes of compiling, run beside the
other long modules (tests/conftest.py, LONG_MODULES)."""

from test_notebooks import assert_files, run_notebook, summary


def test_07_cameras(tmp_path):
    """The notebook asserts its path errors and the two-camera e and spin itself; here, what
    it reports: two cameras fix the path better than one, the clock offset is none (the
    cameras share their clock), the replay has its frames."""
    proc = run_notebook("07_cameras.py", tmp_path)
    assert_files(tmp_path, ["side.yaml", "behind.json", "07_shot.csv", "07_pixels.png", "07_path_one_camera.png",
                            "07_replay.gif", "07_cameras.json"])
    s = summary(proc, tmp_path, "07_cameras")
    one, two = s["one_camera"], s["two_cameras"]
    assert two["path_error_cm"] < one["path_error_cm"] and two["depth_cm"] < one["depth_cm"]
    assert abs(s["dt_camera2"]) < 1e-3
    assert abs(one["rms_px"] - 1.0) < 0.15 and abs(two["rms_px"] - 1.0) < 0.15  # 1 px of noise
    assert s["replay_frames"] > 10
