"""Fit restitution from tracked video data: synthetic stairs tracks, then real ping-pong drops.

Run headless with ``python notebooks/02_fit_video_tracks.py`` (figures and the replay go to
``$ESTIM_NOTEBOOK_OUT``, default ``notebooks/out/``), or open it with
``marimo edit notebooks/02_fit_video_tracks.py``. The real data is read from
``../shared/realdata/`` beside the checkout; without it that part is skipped.
``ESTIM_NOTEBOOK_FAST=1`` (the test) renders a shorter, smaller replay.
"""

import marimo

__generated_with = "0.25.2"
app = marimo.App()


@app.cell
def _():
    import json
    import re
    import time

    import marimo as mo
    import matplotlib.pyplot as plt
    import numpy as np
    from _common import FAST, OUT, ROOT, md_table  # notebooks/_common.py

    import estim

    START = time.perf_counter()
    return FAST, OUT, ROOT, START, estim, json, md_table, mo, np, plt, re, time


@app.cell
def _(mo):
    mo.md(r"""
    # Fit restitution from tracked video data

    A tracker gives ball positions frame by frame; estim fits its exact hybrid model to them
    and returns the restitution $e$, the tangential coefficient $\mu_t$ and the release
    speed $v_{x0}$ of each ball, with standard errors. First on tracks whose truth is known
    (the bundled synthetic stairs data), then on real video tracks of a ping-pong ball
    dropped onto a table, in pixels, with neither the scale nor the surface given, against
    the restitution its authors published. The replay at the end shows model and data
    together.
    """)
    return


@app.cell
def _(ROOT, estim, json, time):
    STAIRS = ROOT / "data" / "scenes" / "stairs.xml"
    CSV = ROOT / "data" / "tracks" / "stairs_demo.csv"
    scene = estim.load_scene(STAIRS)
    tracks = estim.read_tracks_csv(CSV, scene=scene)
    truth = json.loads((ROOT / "data" / "tracks" / "stairs_demo_truth.json").read_text())
    data = {b: (tracks.t[b], tracks.position[b]) for b in tracks.balls}
    _t = time.perf_counter()
    result = estim.fit(scene, data)
    FIT_S = time.perf_counter() - _t
    return FIT_S, STAIRS, data, result, scene, tracks, truth


@app.cell
def _(FIT_S, OUT, data, estim, md_table, mo, np, result, tracks, truth):
    _noise = truth["settings"]["noise"]
    _rows, zscores = [], []
    for _b, _bf in result.balls.items():
        _tr = truth["balls"][_b]
        for _k in ("e", "mu_t", "vx0"):
            _v, _s, _true = _bf.values[_k], _bf.stderr[_k], _tr[_k]
            _z = (_v - _true) / _s
            zscores.append(_z)
            _rows.append([_b, _k, f"{_v:.4f} +- {_s:.4f}", f"{_true:.4f}", f"{_v - _true:+.4f}",
                          f"{_z:+.1f}"])
        # Every ball: converged, recovered to within 0.002 in e and mu_t (0.01 m/s in vx0),
        # with residuals at the 2 mm noise of the data.
        assert _bf.converged and _bf.at_noise_floor, (_b, _bf.notes)
        assert abs(_bf.values["e"] - _tr["e"]) < 0.002, (_b, _bf.values["e"])
        assert abs(_bf.values["mu_t"] - _tr["mu_t"]) < 0.002, (_b, _bf.values["mu_t"])
        assert abs(_bf.values["vx0"] - _tr["vx0"]) < 0.01, (_b, _bf.values["vx0"])
        assert abs(_bf.rms_m / _noise - 1) < 0.2, (_b, _bf.rms_m)
    zscores = np.array(zscores)
    _rms = [f"{b} {bf.rms_m * 1e3:.2f} mm" for b, bf in result.balls.items()]
    _bounces = [f"{b} {bf.n_bounces}" for b, bf in result.balls.items()]
    estim.plot_fit(data, result, OUT / "02_stairs_fit.png")
    estim.plot_residuals(data, result, OUT / "02_stairs_residuals.png")
    _s = truth["settings"]
    mo.vstack([
        mo.md(f"""
    ## 1. Synthetic tracks with known truth

    `data/tracks/stairs_demo.csv` holds three balls bouncing down the seed staircase, made
    from known parameters (`data/tracks/stairs_demo_truth.json`) and spoiled like real
    tracking data: {_s["frame_rate"]:g} frames per second, {_s["noise"] * 1e3:g} mm noise,
    {_s["drop_fraction"] * 100:g}% dropped frames, {_s["n_outliers"]} outliers of
    {_s["outlier_size"] * 100:g} cm per ball and {_s["lost_fraction"] * 100:g}% lost
    coordinates ({sum(tracks.n_obs(b) for b in tracks.balls)} samples in all).
    `estim.fit` starts from the data (flights split at the bounces), fits a robust (Cauchy)
    loss with Levenberg-Marquardt, and reports Gauss-Newton standard errors; it took
    {FIT_S:.1f} s here, JAX compile included.
    """),
        md_table(["ball", "parameter", "fitted +- stderr", "truth", "error", "error / stderr"], _rows),
        mo.md(f"""
    Every parameter is recovered: the largest error in e is
    {max(abs(result.balls[b].values["e"] - truth["balls"][b]["e"]) for b in result.balls):.4f},
    and the errors measured in standard errors have rms {np.sqrt(np.mean(zscores**2)):.1f}
    (1 if the standard errors are calibrated; with nine numbers from one data set, a rough
    check). The rms residuals ({", ".join(_rms)}) match the {_noise * 1e3:g} mm noise:
    nothing is left for the model to explain. Bounces in the data: {", ".join(_bounces)}.
    """),
        mo.image(src=(OUT / "02_stairs_fit.png").read_bytes()),
        mo.image(src=(OUT / "02_stairs_residuals.png").read_bytes()),
    ])
    return (zscores,)


@app.cell
def _(ROOT, estim, mo):
    REAL = ROOT.parent / "shared" / "realdata" / "pingpong_drop_nicofighter45"
    HAVE_REAL = (REAL / "table").is_dir()
    DT = 0.01  # s per frame, as the authors assumed
    DEMO_FILE = 9  # the file shown step by step
    AUTHORS_MPP = 137.1e-2 / 911  # the authors' scale (m per pixel)
    # The drop scene: a table top at z = 0 and the ping-pong ball (r = 2 cm, 2.7 g).
    drop_scene = estim.load_scene(ROOT / "data" / "scenes" / "drop.xml")
    if not HAVE_REAL:
        SKIP_MESSAGE = (f"Real data not found at {REAL}: the real-data part of this notebook "
                        "is skipped (it needs ../shared/realdata/ beside the checkout).")
        print(SKIP_MESSAGE)
    else:
        SKIP_MESSAGE = ""
    mo.md(f"""
    ## 2. Real tracks: a ping-pong ball dropped on a table

    `../shared/realdata/pingpong_drop_nicofighter45/table/` (MIT licence, from the public
    repository nicofighter45/TableTennis): 15 drops of a ping-pong ball (2.7 g, radius 2 cm)
    onto a table-tennis table, tracked from video by a colour tracker. Each file is a list of
    `a;b;` pixel coordinates of the ball centre, rows growing downward, no time column, no
    scale. We assume the authors' 100 frames per second; gravity then fixes the scale, and
    the surface is where consecutive flights meet. The data is read in place, never copied.

    {"**" + SKIP_MESSAGE + "**" if SKIP_MESSAGE else ""}
    """)
    return AUTHORS_MPP, DEMO_FILE, DT, HAVE_REAL, REAL, drop_scene


@app.cell
def _(AUTHORS_MPP, DEMO_FILE, DT, HAVE_REAL, OUT, REAL, drop_scene, estim, mo, np, plt):
    mo.stop(not HAVE_REAL, mo.md("*Skipped: no real data.*"))
    _track = estim.read_pixel_track(REAL / "table" / f"tracked-{DEMO_FILE}.txt", frame_interval=DT)
    _scale = estim.estimate_pixel_scale(_track, DT)
    _surface = estim.estimate_surface_row(_track, metres_per_pixel=_scale.metres_per_pixel,
                                          radius=drop_scene.ball("pingpong").radius)
    _ft = estim.restitution_from_flight_times(_track)

    _fig, _ax = plt.subplots(figsize=(8, 3.8))
    _ax.plot(_track.t, _track.b, ".", ms=3, color="#f08c1a", label="tracked centre row b")
    _ax.axhline(_surface.centre_row, color="0.4", lw=1, ls="--", label="centre row at contact")
    _ax.axhline(_surface.surface_row, color="k", lw=1.2, label="surface row (one radius lower)")
    for _tb in _surface.bounce_t:
        _ax.axvline(_tb, color="0.75", lw=0.8, zorder=0)
    _ax.invert_yaxis()
    _ax.set_xlabel("t = frame x 0.01 s")
    _ax.set_ylabel("image row b (px, down)")
    _ax.set_title(f"table/tracked-{DEMO_FILE}.txt: the raw track (grey lines: bounces from the flights)")
    _ax.grid(alpha=0.25)
    _ax.legend(fontsize=7, loc="upper right")
    _fig.tight_layout()
    _fig.savefig(OUT / "02_real_track.png", dpi=110)
    plt.close(_fig)

    _per = np.array([f[3] for f in _scale.flights]) * 1e3
    _ratios = ", ".join(f"{x:.3f}" for x in _ft.e)
    mo.vstack([
        mo.md(f"""
    ### One file, step by step (`table/tracked-{DEMO_FILE}.txt`, {len(_track.t)} frames)

    - **Scale from gravity** (`estim.estimate_pixel_scale`): every flight is a parabola
      in the image whose curvature is g / (2 s). Its {len(_scale.flights)} flights give
      {", ".join(f"{v:.3f}" for v in _per)} mm/px, combined
      {_scale.metres_per_pixel * 1e3:.3f} +- {_scale.stderr * 1e3:.3f} mm/px (the authors
      used {AUTHORS_MPP * 1e3:.3f} mm/px).
    - **Surface** (`estim.estimate_surface_row`): consecutive flight parabolas meet at
      row {_surface.centre_row:.1f} (the ball centre at contact); the table is one radius
      lower, at row {_surface.surface_row:.1f}.
    - **Scale-free restitution** (`estim.restitution_from_flight_times`): ratios of
      successive flight durations, which need neither scale nor frame interval: {_ratios}.
    """),
        mo.image(src=(OUT / "02_real_track.png").read_bytes()),
    ])
    return


@app.cell
def _(DT, HAVE_REAL, REAL, drop_scene, estim, time):
    # `estim.fit_pixels`, the pixel pipeline of `estim fit --pixels` with its defaults
    # (scale from gravity, surface from the bounces, frames before the release skipped, up
    # to 5 restarts), on the whole track and from the first bounce on. Every file is padded
    # to 400 samples so that all share one compiled fit. The same method, files and
    # selection as docs/scripts/realdata_table_fits.py (the table in docs/pages/fitting.md).
    _files = sorted((REAL / "table").glob("tracked-*.txt"), key=lambda p: int(p.stem.split("-")[1]))
    assert len(_files) == 15 or not HAVE_REAL
    real_rows, real_fits = [], {}
    _t = time.perf_counter()
    for _path in _files:  # none without the data
        _i = int(_path.stem.split("-")[1])
        _row = {"file": _i}
        for _k in (0, 1):
            try:
                _res, _data, _s, _ = estim.fit_pixels(_path, drop_scene, ball="pingpong",
                                                      frame_interval=DT, from_bounce=_k, pad_to=400)
            except ValueError as _exc:  # fewer bounces than from_bounce asks for
                _row[_k] = {"error": str(_exc)}
                continue
            _bf = _res.balls["pingpong"]
            _row[_k] = {"e": _bf.values["e"], "se": _bf.stderr["e"], "rms_px": _bf.rms_m / _s,
                        "noise_px": _bf.noise_m / _s, "bounces": _bf.n_bounces, "mpp": _s}
            real_fits[(_i, _k)] = (_res, _data)
        _track = estim.read_pixel_track(_path, frame_interval=DT)
        _row["ratios"] = [float(x) for x in estim.restitution_from_flight_times(_track).e]
        real_rows.append(_row)
    REAL_FIT_S = time.perf_counter() - _t
    return REAL_FIT_S, real_fits, real_rows


@app.cell
def _(
    AUTHORS_MPP,
    HAVE_REAL,
    OUT,
    REAL,
    REAL_FIT_S,
    md_table,
    mo,
    np,
    plt,
    re,
    real_rows,
):
    def _analyse():
        _txt = (REAL / "upstream_results_rebond.txt").read_text(encoding="utf-8", errors="replace")
        E_AUTHORS = float(re.search(r"restitution est de ([0-9.]+)", _txt).group(1))
        SE_AUTHORS = float(re.search(r"incertitude sur la valeur est de ([0-9.]+)", _txt).group(1))
        RMS_OK_PX = 4.0  # "a few pixels" (as docs/scripts/realdata_table_fits.py): the
        # tracker's noise is ~0.5 px, the good after-bounce fits reach 1-3 px

        def _why_not(r):
            """'' if the after-bounce fit measures e: identifiable (a bounce in the window,
            finite stderr) and the model follows the data to a few pixels; else why not."""
            f = r.get(1, {})
            if "e" not in f:
                return "fewer than 2 bounces"
            if f["bounces"] < 1 or not np.isfinite(f["se"]):
                return "no 2nd bounce, e not identifiable"
            if f["rms_px"] > RMS_OK_PX:
                return f"rms {f['rms_px']:.1f} px > {RMS_OK_PX:g} px"
            return ""

        def _ok(r):
            return not _why_not(r)

        e_whole = np.array([r[0]["e"] for r in real_rows])
        good = [r for r in real_rows if _ok(r)]
        e_after = np.array([r[1]["e"] for r in good])
        se_after = np.array([r[1]["se"] for r in good])
        mpp = np.array([r[0]["mpp"] for r in real_rows])
        second = np.array([r["ratios"][1] for r in real_rows if len(r["ratios"]) > 1])
        first = np.array([r["ratios"][0] for r in real_rows])

        def _mean_sem(x):
            return float(np.mean(x)), float(np.std(x, ddof=1) / np.sqrt(len(x)))

        E_WHOLE, SEM_WHOLE = _mean_sem(e_whole)
        E_AFTER, SEM_AFTER = _mean_sem(e_after)
        # Sensitivity to the rms cut: every file whose after-bounce e is identifiable.
        ident = [r for r in real_rows if "e" in r.get(1, {}) and np.isfinite(r[1]["se"]) and r[1]["bounces"] >= 1]
        E_IDENT, SEM_IDENT = _mean_sem([r[1]["e"] for r in ident])
        not_used = {r["file"]: _why_not(r) for r in real_rows if not _ok(r)}
        # What the notebook claims, checked: the whole-track e is biased low (air drag on the
        # fall from the hand), the after-bounce e agrees with the published value within the
        # combined uncertainty, and so do the scale-free flight-time ratios after bounce 1.
        assert len(good) >= 5, [r["file"] for r in good]
        assert E_WHOLE + 2 * SEM_WHOLE < E_AFTER, (E_WHOLE, E_AFTER)
        assert abs(E_AFTER - E_AUTHORS) < 2 * np.hypot(SEM_AFTER, SE_AUTHORS), (E_AFTER, E_AUTHORS)
        assert np.mean(first) < np.mean(second) - 0.05

        def _fmt(f):
            if "e" not in f:
                return ["n/a (no bounce after the first)", ""]
            if not np.isfinite(f["se"]):
                return ["not identifiable (no bounce in the window)", f"{f['rms_px']:.1f}"]
            return [f"{f['e']:.4f} +- {f['se']:.4f}", f"{f['rms_px']:.1f}"]

        _rows = [[r["file"], *_fmt(r[0]), *_fmt(r.get(1, {})), "yes" if _ok(r) else "no: " + _why_not(r),
                  ", ".join(f"{x:.3f}" for x in r["ratios"])] for r in real_rows]

        _fig, _ax = plt.subplots(figsize=(8, 4))
        _files = np.array([r["file"] for r in real_rows])
        _ax.axhspan(E_AUTHORS - SE_AUTHORS, E_AUTHORS + SE_AUTHORS, color="0.85", label="authors: mean +- uncertainty")
        _ax.axhline(E_AUTHORS, color="0.5", lw=1)
        _ax.plot(_files, e_whole, "s", color="C3", mfc="none", label="whole track (drag-free model)")
        _ax.errorbar([r["file"] for r in good], e_after, yerr=se_after, fmt="o", color="C0",
                     label=f"after bounce 1 (rms <= {RMS_OK_PX:g} px)")
        _bad = [r for r in real_rows if "e" in r.get(1, {}) and np.isfinite(r[1]["se"]) and not _ok(r)]
        if _bad:
            _ax.plot([r["file"] for r in _bad], [r[1]["e"] for r in _bad], "x", color="0.5",
                     label=f"after bounce 1, rms > {RMS_OK_PX:g} px (not used)")
        _ax.set_xlabel("file (table/tracked-N.txt)")
        _ax.set_ylabel("restitution e")
        _ax.set_title("Ping-pong ball on a table: e per drop")
        _ax.set_xticks(_files)
        _ax.grid(alpha=0.25)
        _ax.legend(fontsize=7, loc="center right")
        _fig.tight_layout()
        _fig.savefig(OUT / "02_real_e.png", dpi=110)
        plt.close(_fig)

        view = mo.vstack([
            mo.md(f"""
        ### All 15 drops

        Each file fitted twice with the pixel pipeline of `estim fit --pixels` (scale from
        gravity, surface from the bounces, frames in the hand skipped): on the whole track, and
        from the first bounce on. Selected ("used") are the after-bounce fits that measure e:
        a bounce inside their window and rms residuals of at most {RMS_OK_PX:g} px. The last
        column is the scale-free ratio of successive flight times. {len(real_rows)} files,
        {2 * len(real_rows)} fits in {REAL_FIT_S:.1f} s (one compile: all files are padded to
        the same length).
        """),
            md_table(["file", "e, whole track", "rms (px)", "e, after bounce 1", "rms (px)", "used",
                      "e from flight-time ratios"], _rows),
            mo.md(f"""
        **What the numbers show.**

        - Over the whole track the drag-free model does not fit: rms residuals of
          {np.median([r[0]["rms_px"] for r in real_rows]):.1f} px (median; up to
          {max(r[0]["rms_px"] for r in real_rows):.0f} px) against a tracker noise near
          {np.median([r[0]["noise_px"] for r in real_rows]):.1f} px,
          and e = {E_WHOLE:.3f} +- {SEM_WHOLE:.3f} (mean +- standard error over the 15 files),
          **biased low**. The cause is air drag on a 2.7 g ball falling about 2 m from the hand:
          the first fall is slower than a parabola, so a drag-free model explains the first
          rebound with a smaller e. The flight-time ratios show it without any model or scale:
          the first ratio (the fall from the hand) is {np.mean(first):.3f} on average, the
          second {np.mean(second):.3f}. The same drag inflates gravity's pixel scale:
          {np.mean(mpp) * 1e3:.3f} +- {np.std(mpp, ddof=1) * 1e3:.3f} mm/px against the
          authors' {AUTHORS_MPP * 1e3:.3f}.
        - **After the first bounce** the ball is slower and the model follows the data to a few
          pixels on {len(good)} files: e = **{E_AFTER:.4f} +- {SEM_AFTER:.4f}** (mean +-
          standard error; range {e_after.min():.3f}-{e_after.max():.3f}), against the authors'
          **{E_AUTHORS:.4f} +- {SE_AUTHORS:.4f}**: a difference of {E_AFTER - E_AUTHORS:+.4f},
          within the combined uncertainty ({np.hypot(SEM_AFTER, SE_AUTHORS):.4f}).
        - The standard errors the fit prints per file (median {np.median(se_after):.4f}) are
          conditional on the model and smaller than the scatter between drops (standard
          deviation {np.std(e_after, ddof=1):.4f}): the fits sit above the tracker's noise floor,
          and they say so. The spread over drops is the honest uncertainty.
        - **Not used** (the table says why): {"; ".join(f"file {k}: {v}" for k, v in not_used.items())}.
          Without a second bounce after the first, e cannot come from that window (the fit
          reports it as not identifiable). Taking every file whose after-bounce e is
          identifiable ({len(ident)} files, the rms cut dropped) gives
          e = {E_IDENT:.4f} +- {SEM_IDENT:.4f}: the cut moves the mean by
          {E_AFTER - E_IDENT:+.4f}.
        - **A caveat on what agrees.** The authors' analysis, like this fit, has no air drag.
          Simulated drops with quadratic drag (C_d = 0.3, which reproduces the slow fall from
          the hand seen here) and a known e = 0.87, run through this same pipeline, come out at
          e = 0.80-0.81 after bounce 1 (`python docs/scripts/realdata_table_fits.py
          --drag-check`): at these speeds a drag-free fit reads e several hundredths low, so
          the ball's own e is probably higher than both numbers. Fitting C_d per file as well
          does not settle it on these tracks: e and C_d trade off.
        """),
            mo.image(src=(OUT / "02_real_e.png").read_bytes()),
        ])
        summary = {"e_whole_track": E_WHOLE, "sem_whole_track": SEM_WHOLE, "e_after_bounce_1": E_AFTER,
                   "sem_after_bounce_1": SEM_AFTER, "files_used": [r["file"] for r in good],
                   "files_not_used": {str(k): v for k, v in not_used.items()},
                   "e_all_identifiable": E_IDENT, "sem_all_identifiable": SEM_IDENT,
                   "e_authors": E_AUTHORS, "se_authors": SE_AUTHORS, "fit_s": REAL_FIT_S}
        return summary, view

    real_summary, _view = _analyse() if HAVE_REAL else (None, mo.md("*Skipped: no real data.*"))
    mo.vstack([_view])
    return (real_summary,)


@app.cell
def _(DEMO_FILE, HAVE_REAL, OUT, mo, np, plt, real_fits):
    mo.stop(not HAVE_REAL)
    _fig, _ax = plt.subplots(figsize=(8, 4))
    for _k, _c, _label in ((0, "C3", "fit to the whole track"), (1, "C0", "fit after bounce 1")):
        if (DEMO_FILE, _k) not in real_fits:
            continue
        _res, _data = real_fits[(DEMO_FILE, _k)]
        _bf = _res.balls["pingpong"]
        _t, _p = _data["pingpong"]
        _n = int(np.sum(np.isfinite(_p[:, 2])))
        if _k == 0:
            _ax.plot(_t[:_n], _p[:_n, 2], ".", ms=3, color="0.45", label="tracked (metres, from the scale)")
        _ax.plot(_bf.model_t[:_n], _bf.model_position[:_n, 2], "-", color=_c, lw=1.4,
                 label=f"{_label}: e = {_bf.values['e']:.3f}, rms {_bf.rms_m * 1e3:.1f} mm")
    _ax.set_xlabel("t (s)")
    _ax.set_ylabel("height of the centre above the table (m)")
    _ax.set_title(f"table/tracked-{DEMO_FILE}.txt: data and the two fits")
    _ax.grid(alpha=0.25)
    _ax.legend(fontsize=7)
    _fig.tight_layout()
    _fig.savefig(OUT / "02_real_fit.png", dpi=110)
    plt.close(_fig)
    mo.vstack([
        mo.md(f"""
    The two fits of file {DEMO_FILE} in metres: the whole-track fit has to compromise
    between the slow fall from the hand and the later bounces; the fit after bounce 1 only
    sees the slower flights, where drag matters less.
    """),
        mo.image(src=(OUT / "02_real_fit.png").read_bytes()),
    ])
    return


@app.cell
def _(FAST, OUT, STAIRS, estim, mo, result, scene, time, tracks):
    # The replay: the fitted model (solid balls) against the measured samples (halos) in
    # the scene's own MJCF file, rendered offscreen by MuJoCo (kinematics only: positions
    # set from estim's solution, no MuJoCo physics), and the same as a matplotlib side view.
    _fps, _w, _h = (10.0, 480, 270) if FAST else (25.0, 640, 360)
    _t = time.perf_counter()
    replay_notes = []
    try:
        replay_info = estim.render_replay(STAIRS, result, tracks, OUT / "02_replay.gif",
                                          fps=_fps, width=_w, height=_h)
    except estim.RenderError as _err:  # no offscreen OpenGL on this machine
        replay_info = None
        replay_notes.append(f"MuJoCo replay skipped: {_err}")
        print(replay_notes[-1])
    side_info = estim.render_sideview(scene, result, tracks, OUT / "02_sideview.gif",
                                      fps=_fps, width=_w, height=_h)
    REPLAY_S = time.perf_counter() - _t
    _items = [mo.md(f"""
    ## 3. Replay

    The fit of section 1 replayed over the data's {side_info.t_end - side_info.t_start:.2f} s
    ({side_info.n_frames} frames at {_fps:g} fps; rendered in {REPLAY_S:.1f} s): solid balls
    are the fitted model, translucent halos the measured samples, dots the samples of the
    last 0.3 s. Where model and data agree the halo surrounds the ball; at an outlier it
    jumps away. `estim.render_replay` renders the scene file `{STAIRS.name}` with MuJoCo
    (kinematics only, no MuJoCo physics: the motion is estim's exact solution);
    `estim.render_sideview` draws the same with matplotlib.
    """)]
    if replay_info is not None:
        _items.append(mo.image(src=(OUT / "02_replay.gif").read_bytes()))
    else:
        _items.append(mo.md(f"*{replay_notes[0]}*"))
    _items.append(mo.image(src=(OUT / "02_sideview.gif").read_bytes()))
    mo.vstack(_items)
    return REPLAY_S, replay_info, side_info


@app.cell
def _(DT, HAVE_REAL, OUT, REAL, ROOT, estim, mo, real_summary, time):
    # All 15 drops together, in still air (data/scenes/drop_air.xml): one e and one drag
    # coefficient shared by every clip, each clip with its own release state and its own
    # pixel scale, read from its bounce-to-bounce flights (`estim fit tracked-*.txt --pixels --frame-interval 0.01 --scene
    # data/scenes/drop_air.xml --ball pingpong --shared e drag_coefficient`).
    def _pooled():
        _files = sorted((REAL / "table").glob("tracked-*.txt"), key=lambda p: int(p.stem.split("-")[1]))
        _air = estim.load_scene(ROOT / "data" / "scenes" / "drop_air.xml")
        _t = time.perf_counter()
        _res, _ = estim.fit_files(_files, _air, shared=("e", "drag_coefficient"), pixels=True, ball="pingpong",
                                  frame_interval=DT, restarts=1)
        _s = time.perf_counter() - _t
        _sf = _res.shared["pingpong"]
        assert 0.8 < _sf.values["e"] < 1.0 and 0.0 < _sf.stderr["e"] < 0.05, (_sf.values, _sf.stderr)
        assert 0.1 < _sf.values["drag_coefficient"] < 1.5, _sf.values
        estim.plot_forest(_res, OUT / "02_forest.png")
        _summary = {"e": _sf.values["e"], "se_e": _sf.stderr["e"],
                    "drag_coefficient": _sf.values["drag_coefficient"],
                    "se_drag_coefficient": _sf.stderr["drag_coefficient"],
                    "q_e": _sf.heterogeneity["e"][0], "dof_e": _sf.heterogeneity["e"][1],
                    "disagree": sorted({c for c, *_ in _sf.disagree}), "fit_s": _s}
        _e_alone = real_summary["e_whole_track"] if real_summary else float("nan")
        _view = mo.vstack([
            mo.md(f"""
    ## 4. All drops together: one e, one drag coefficient

    The 15 drops are one ball on one table. Fitted together in still air (the scene
    `drop_air.xml`), with e and the drag coefficient shared by every clip and each clip
    keeping its own release state and pixel scale (read from its bounce-to-bounce flights,
    where drag bends the track least), they read
    **e = {_sf.values['e']:.4f} +- {_sf.stderr['e']:.4f}** and
    **C_D = {_sf.values['drag_coefficient']:.3f} +- {_sf.stderr['drag_coefficient']:.3f}**
    ({_s:.0f} s). One by one and without drag the whole tracks read e = {_e_alone:.3f}: drag
    slows the fall from the hand, and a model without it explains the slow arrival with a
    smaller e. One by one *with* drag each clip trades e against C_D (several at e = 1);
    shared, the clips pin both down.

    The forest plot shows each clip's own e and C_D (the other held at its shared value) and
    its one-by-one fit. The clips scatter far more than their tracking noise allows
    (Cochran's Q = {_sf.heterogeneity['e'][0]:.0f} on {_sf.heterogeneity['e'][1]} degrees of
    freedom): what differs between drops (the release, spin from the hand, where the ball
    meets the table, the tracker) is more than the noise. The standard errors account for
    that scatter (the largest of the clustered sandwich, the model-based error and the
    clips' own scatter): they are the honest uncertainty of this ball's e, not the
    noise-only one. Clips more than 3 of their own standard errors from the shared values:
    {", ".join(_summary["disagree"]) or "none"}.
    """),
            mo.image(src=(OUT / "02_forest.png").read_bytes()),
        ])
        return _summary, _view

    pooled_summary, _view = _pooled() if HAVE_REAL else (None, mo.md("*Skipped: no real data.*"))
    mo.vstack([_view])
    return (pooled_summary,)


@app.cell
def _(FIT_S, OUT, REPLAY_S, START, json, mo, pooled_summary, real_summary, result, time, zscores):
    _summary = {
        "stairs": {b: {k: bf.values[k] for k in ("e", "mu_t", "vx0")} for b, bf in result.balls.items()},
        "stairs_zscore_rms": float((zscores**2).mean() ** 0.5),
        "fit_s": FIT_S,
        "replay_s": REPLAY_S,
        "total_s": time.perf_counter() - START,
    }
    if real_summary is not None:
        _summary["real"] = real_summary
        _summary["pooled"] = pooled_summary
    (OUT / "02_fit_video_tracks.json").write_text(json.dumps(_summary, indent=2) + "\n")
    print("02_fit_video_tracks:", json.dumps(_summary))
    mo.md(f"""
    ## Summary

    - Synthetic stairs tracks: e, mu_t and vx0 of all three balls recovered with calibrated
      standard errors and residuals at the noise level.
    - Real table drops: {"skipped (no data)" if real_summary is None else
      "e = {e_after_bounce_1:.4f} +- {sem_after_bounce_1:.4f} after the first bounce against "
      "the published {e_authors:.4f} +- {se_authors:.4f}; the whole-track e "
      "({e_whole_track:.3f}) is biased low by air drag, which the drag-free model "
      "lacks.".format(**real_summary)}
    """)
    return


if __name__ == "__main__":
    app.run()
