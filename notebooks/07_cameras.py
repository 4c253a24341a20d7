"""Through a camera: from a camera file and a pixel track to the 3-D path, e and spin, with
the replay from the camera's own viewpoint; one camera against two.

Run headless with ``python notebooks/07_cameras.py`` (figures go to
``$ESTIM_NOTEBOOK_OUT``, default ``notebooks/out/``), or open it with
``marimo edit notebooks/07_cameras.py``. The scene is ``data/scenes/table_tennis.xml``
(regulation table, net, still air, the friction law on the table).
"""

import marimo

__generated_with = "0.25.2"
app = marimo.App()


@app.cell
def _():
    import json
    import time

    import marimo as mo
    import numpy as np
    from _common import FAST, OUT, ROOT, md_table  # notebooks/_common.py

    import estim

    START = time.perf_counter()
    return FAST, OUT, ROOT, START, estim, json, md_table, mo, np, time


@app.cell
def _(mo):
    mo.md(r"""
    # Through a camera

    A video gives pixels, not metres: a camera looks at the table in perspective, and one
    camera alone sees each position only as a ray. estim fits the pixels directly: the
    model's 3-D path, seen by the calibrated camera, against the tracked pixels. The depth
    the rays leave open comes from the physics: gravity has a known size, and at the bounce
    the ball's centre is one radius above the table (the *Cameras* page of the docs).

    Here a table-tennis shot of known parameters (topspin, 60 frames per second) is seen by
    two cameras, one from the side and one from behind the server, with 1 px of noise.
    """)
    return


@app.cell
def _(OUT, ROOT, estim, json, np):
    scene = estim.load_scene(ROOT / "data" / "scenes" / "table_tennis.xml")
    TRUTH = {"e": 0.88, "mu": 0.3, "position": np.array([-0.2, -1.6, 0.25]),
             "velocity": np.array([0.4, 6.0, 1.8]), "spin": np.array([-110.0, 0.0, 30.0])}
    T = np.arange(0.0, 0.55, 1.0 / 60.0)
    _params = estim.Params.for_ball(scene, "pingpong", e=TRUTH["e"], mu_t=0.0, mu=TRUTH["mu"],
                                    position=TRUTH["position"], velocity=TRUTH["velocity"], spin=TRUTH["spin"])
    PATH = np.asarray(estim.simulate(scene, _params, float(T[-1]), ts=T).position)
    # Two cameras, written as a user would have them: the short form (a pose, a focal
    # length in pixels, an image size) for the side camera, OpenCV's FileStorage JSON for
    # the one behind.
    _side = estim.Camera.look_at((3.0, -0.4, 0.9), (0.0, 0.0, 0.1), focal=1400.0, size=(1280, 720), name="side")
    _behind = estim.Camera.look_at((0.4, -4.5, 1.5), (0.0, 0.0, 0.1), focal=1400.0, size=(1280, 720), name="behind")
    CAMERA_FILES = [OUT / "side.yaml", OUT / "behind.json"]
    CAMERA_FILES[0].write_text(f"rvec: {_side.rvec.tolist()}\ntvec: {np.asarray(_side.translation).tolist()}\n"
                               "f: 1400\nw: 1280\nh: 720\n")
    _matrix = lambda a, r, c: {"type_id": "opencv-matrix", "rows": r, "cols": c, "dt": "d",  # noqa: E731
                               "data": np.asarray(a).ravel().tolist()}
    CAMERA_FILES[1].write_text(json.dumps({
        "image_width": 1280, "image_height": 720, "camera_matrix": _matrix(_behind.matrix, 3, 3),
        "distortion_coefficients": _matrix(np.zeros(5), 1, 5), "rvec": _matrix(_behind.rvec, 3, 1),
        "tvec": _matrix(_behind.translation, 3, 1)}, indent=1))
    # The pixel tracks (1 px of Gaussian noise): t,ball,u,v,camera of both cameras, and the
    # side camera's rows alone (t,ball,u,v: one camera needs no camera column).
    _rng = np.random.default_rng(11)
    _rows = [(float(_t), _cam.name, *(np.asarray(_cam.project(_p)) + _rng.normal(0.0, 1.0, 2)))
             for _t, _p in zip(T, PATH, strict=True) for _cam in (_side, _behind)]
    TRACK, SIDE_TRACK = OUT / "07_shot.csv", OUT / "07_side.csv"
    TRACK.write_text("t,ball,u,v,camera\n" + "".join(f"{t!r},pingpong,{u:.3f},{v:.3f},{c}\n" for t, c, u, v in _rows))
    SIDE_TRACK.write_text("t,ball,u,v\n" + "".join(f"{t!r},pingpong,{u:.3f},{v:.3f}\n" for t, c, u, v in _rows
                                                    if c == "side"))
    return CAMERA_FILES, PATH, SIDE_TRACK, T, TRACK, TRUTH, scene


@app.cell
def _(CAMERA_FILES, TRACK, mo):
    mo.md(f"""
    ## The files

    The side camera's file, in the short form (`rvec`, `tvec` world-to-camera as OpenCV's
    `solvePnP` gives them; the focal length and image size in pixels):

    ```yaml
    {CAMERA_FILES[0].read_text().strip()}
    ```

    and the first rows of the pixel track (`u` right, `v` down):

    ```text
    {"".join(TRACK.read_text().splitlines(keepends=True)[:5]).strip()}
    ```
    """)
    return


@app.cell
def _(CAMERA_FILES, PATH, SIDE_TRACK, TRACK, TRUTH, estim, np, scene, time):
    def _fit(files, track):
        cams = [estim.read_camera(p) for p in files]
        tracks = estim.read_image_tracks_csv(track, cams)
        start = time.perf_counter()
        bf = estim.fit_image(scene, tracks).balls["pingpong"]
        seconds = time.perf_counter() - start
        true_path = PATH[np.rint(tracks.t["pingpong"] * 60).astype(int)]  # the truth at the rows' times
        spin = np.array([bf.values[f"spin_{c}"] for c in "xyz"])
        v = TRUTH["velocity"] / np.linalg.norm(TRUTH["velocity"])
        across = lambda w: w - np.dot(w, v) * v  # noqa: E731
        return tracks, bf, {
            "path_error_cm": float(np.mean(np.linalg.norm(bf.model_position - true_path, axis=1)) * 100),
            "e": bf.values["e"], "mu": bf.values["mu"],
            "spin_error": float(np.linalg.norm(across(spin) - across(TRUTH["spin"])) / np.linalg.norm(across(TRUTH["spin"]))),
            "rms_px": bf.rms_m, "depth_cm": bf.depth["along_axis_m"] * 100, "seconds": seconds}

    ONE_TRACKS, ONE, ONE_STATS = _fit(CAMERA_FILES[:1], SIDE_TRACK)
    TWO_TRACKS, TWO, TWO_STATS = _fit(CAMERA_FILES, TRACK)
    assert ONE_STATS["path_error_cm"] < 3.0 and TWO_STATS["path_error_cm"] < 1.0, (ONE_STATS, TWO_STATS)
    assert abs(TWO_STATS["e"] - TRUTH["e"]) < 0.01 and TWO_STATS["spin_error"] < 0.1, TWO_STATS
    return ONE, ONE_STATS, ONE_TRACKS, TWO, TWO_STATS, TWO_TRACKS


@app.cell
def _(ONE_STATS, TRUTH, TWO_STATS, md_table, mo):
    _rows = [[name, f"{s['path_error_cm']:.2f}", f"{s['depth_cm']:.2f}", f"{s['e']:.3f} (truth {TRUTH['e']})",
              f"{s['mu']:.3f} (truth {TRUTH['mu']})", f"{s['spin_error']:.0%}", f"{s['rms_px']:.2f}"]
             for name, s in (("one camera (side)", ONE_STATS), ("two cameras", TWO_STATS))]
    mo.vstack([
        mo.md("""
        ## One camera against two

        `estim.fit_image` (what `estim fit shot.csv --camera side.yaml --scene
        data/scenes/table_tennis.xml` runs) with its defaults: the release position,
        velocity and spin, e and mu, and with two cameras the offset of the second one's
        clock. *Path error* is the mean distance of the fitted 3-D path from the true one;
        *depth* the standard error of the release point along the side camera's axis, the
        direction one camera fixes worst (`fit.json`'s `"depth"`).
        """),
        md_table(["cameras", "path error [cm]", "depth ± [cm]", "e", "mu", "spin across the flight, error",
                  "rms [px]"], _rows),
    ])
    return


@app.cell
def _(ONE, ONE_TRACKS, OUT, TWO, TWO_TRACKS, estim, mo):
    from estim.show._image_plots import plot_image_fit, plot_path

    plot_image_fit(TWO_TRACKS, estim.FitResult({"pingpong": TWO}), OUT / "07_pixels.png")
    plot_path(ONE_TRACKS, estim.FitResult({"pingpong": ONE}), OUT / "07_path_one_camera.png")
    mo.vstack([
        mo.md("What each camera saw, with the two-camera fit drawn over it:"),
        mo.image(str(OUT / "07_pixels.png")),
        mo.md("The one-camera fit in 3-D: each pixel placed on its ray at the fitted depth."),
        mo.image(str(OUT / "07_path_one_camera.png")),
    ])
    return


@app.cell
def _(CAMERA_FILES, FAST, OUT, ROOT, TRACK, TWO, estim, json, mo):
    from estim.show._image_plots import replay_samples

    _fit = estim.FitResult({"pingpong": TWO})
    _tracks = estim.read_image_tracks_csv(TRACK, [estim.read_camera(p) for p in CAMERA_FILES])
    REPLAY = estim.render_replay(ROOT / "data" / "scenes" / "table_tennis.xml", _fit,
                                 replay_samples(_tracks, json.loads(json.dumps(_fit.to_json()))),
                                 OUT / "07_replay.gif", camera=_tracks.cameras[0], width=320 if FAST else 640)
    mo.vstack([
        mo.md("""
        ## The replay from the camera's viewpoint

        MuJoCo renders the fitted ball through the side camera itself (its pose and field
        of view), with each tracked pixel as a translucent halo on its ray at the fitted
        depth: the halo lands where the video saw the ball, the solid ball where the model
        puts it (`estim replay shot.csv fit.json --camera side.yaml ...`).
        """),
        mo.image(str(OUT / "07_replay.gif")),
    ])
    return (REPLAY,)


@app.cell
def _(ONE_STATS, OUT, REPLAY, START, TWO, TWO_STATS, json, time):
    summary = {"one_camera": ONE_STATS, "two_cameras": TWO_STATS, "dt_camera2": TWO.values["dt_camera2"],
               "replay_frames": REPLAY.n_frames, "total_s": time.perf_counter() - START}
    (OUT / "07_cameras.json").write_text(json.dumps(summary, indent=1))
    print("07_cameras:", json.dumps(summary))
    return


if __name__ == "__main__":
    app.run()
