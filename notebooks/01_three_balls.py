"""Three balls down the stairs: the seed scene rebuilt with estim.

Run headless with ``python notebooks/01_three_balls.py`` (figures and GIFs go to
``$ESTIM_NOTEBOOK_OUT``, default ``notebooks/out/``), or open it with
``marimo edit notebooks/01_three_balls.py``. ``ESTIM_NOTEBOOK_FAST=1`` (the test) renders
shorter, smaller GIFs.
"""

import marimo

__generated_with = "0.25.2"
app = marimo.App()


@app.cell
def _():
    import json
    import time

    import jax.numpy as jnp
    import marimo as mo
    import numpy as np
    from _common import FAST, OUT, ROOT, md_table  # notebooks/_common.py
    from matplotlib.figure import Figure

    import estim
    from estim.show._plots import COLOURS  # the colours of estim's plots and replays

    START = time.perf_counter()
    return COLOURS, FAST, Figure, OUT, ROOT, START, estim, jnp, json, md_table, mo, np, time


@app.cell
def _(mo):
    mo.md(r"""
    # Three balls down the stairs

    The scene that started estim: a bocce ball, a golf ball and a ping-pong ball released
    side by side above a five-step staircase (treads 0.60 m wide, tops from 1.40 m down in
    steps of 0.20 m), all thrown forward at 1.15 m/s. Each ball is a point of radius $r$ in
    free flight under gravity; when it meets a tread top, $z - r = z_{\text{tread}}$, its
    velocity is reset,

    $$ v_z \mapsto -e\, v_z, \qquad v_x \mapsto \mu_t\, v_x , $$

    and only the coefficient of restitution $e$ differs between the balls. estim solves this
    hybrid system exactly: every flight is a parabola and every contact time the root of a
    quadratic, so no bounce can be missed and the numbers below are exact to rounding.
    """)
    return


@app.cell
def _(ROOT, estim, jnp, np, time):
    STAIRS = ROOT / "data" / "scenes" / "stairs.xml"
    scene = estim.load_scene(STAIRS)
    BALLS = ("bocce", "golf", "pingpong")
    E = {"bocce": 0.55, "golf": 0.70, "pingpong": 0.85}
    MU_T, VX0, X0, DROP, T_END = 0.98, 1.15, -0.20, 0.25, 2.3
    radius = np.array([scene.ball(b).radius for b in BALLS])
    # Released 0.25 m above the first tread (top 1.40 m), as in the seed notebook; the y
    # offsets (which keep the balls apart in the pictures) come from the scene file.
    release = np.array([[X0, scene.ball(b).position[1], 1.40 + r + DROP] for b, r in zip(BALLS, radius, strict=True)])
    np.testing.assert_allclose(release, [scene.ball(b).position for b in BALLS], atol=1e-12)
    params = estim.Params([E[b] for b in BALLS], [MU_T] * 3, radius, release, [(VX0, 0.0, 0.0)] * 3)
    ts = jnp.linspace(0.0, T_END, 500)
    _t = time.perf_counter()
    traj = estim.simulate(scene, params, T_END, ts=ts)  # all three balls in one call
    SIM_S = time.perf_counter() - _t
    return BALLS, E, MU_T, SIM_S, STAIRS, T_END, VX0, params, scene, traj


@app.cell
def _(BALLS, E, SIM_S, md_table, mo, np, scene, traj):
    # The bounce table, from the event list of the exact solution.
    _ev = traj.events
    _count = np.asarray(_ev.count)
    _kind = np.asarray(_ev.kind)
    _face = np.asarray(_ev.face)
    final = np.asarray(traj.final.position)
    bounces, per_tread = [], []
    for _i, _b in enumerate(BALLS):
        _n = int(_count[_i])
        _impact = _kind[_i, :_n] == 0  # 0: impact; 1: a landing to rest
        bounces.append(int(np.sum(_impact)))
        _solids = [scene.face_label(int(f))[0] for f in _face[_i, :_n][_impact]]
        per_tread.append({s: _solids.count(s) for s in dict.fromkeys(_solids)})
        assert all(scene.face_label(int(f))[1] == "+z" for f in _face[_i, :_n]), "a non-tread contact"

    # The seed numbers (exact closed-form solution of the same model, ../shared/seed).
    SEED_BOUNCES = [9, 6, 4]
    SEED_FINAL_X = [2.2427444662, 2.3048901184, 2.3278961376]
    SEED_FINAL_Z = [0.7329133018, 0.6932422527, 1.0811260425]
    assert bounces == SEED_BOUNCES, bounces
    np.testing.assert_allclose(final[:, 0], SEED_FINAL_X, atol=1e-9)
    np.testing.assert_allclose(final[:, 2], SEED_FINAL_Z, atol=1e-9)
    # The least elastic ball bounces most often.
    assert bounces[0] > bounces[1] > bounces[2] and E["bocce"] < E["golf"] < E["pingpong"]

    _rows = [[b, f"{E[b]:.2f}", bounces[i], f"{final[i, 0]:.10f}", f"{final[i, 2]:.10f}",
              ", ".join(f"{s} x{n}" for s, n in per_tread[i].items())] for i, b in enumerate(BALLS)]
    _hops = {b: max(per_tread[i].values()) for i, b in enumerate(BALLS)}
    mo.vstack([
        mo.md(f"""
    ## The bounce table

    One call of `estim.simulate` solves the three balls together (a batch of three
    `Params`), {SIM_S:.1f} s here including JAX's compile. Impacts per ball, the final
    position after 2.3 s, and the treads hit:
    """),
        md_table(["ball", "e", "bounces", "final x (m)", "final z (m)", "impacts per tread"], _rows),
        mo.md(f"""
    **The least elastic ball bounces most often.** The bocce (e = {E["bocce"]}) bounces
    {bounces[0]} times, the golf ball (e = {E["golf"]}) {bounces[1]}, the ping-pong ball
    (e = {E["pingpong"]}) only {bounces[2]}. A lossy ball's rebounds are low and short: it
    hops several times on the same tread (up to {_hops["bocce"]} on one tread) before a hop
    carries it over the edge, while each long, high flight of the lively ping-pong ball
    carries it from one tread to the next (at most {_hops["pingpong"]} impact per tread). The seed notebook's prose
    said the opposite ("bocce drops tread-to-tread, ping-pong makes many lively hops"); the
    exact solution says otherwise, as the seed's reference numbers record. They are
    matched here to 1e-9 m: bounces 9 / 6 / 4, final x 2.2427444662 / 2.3048901184 /
    2.3278961376 m.
    """),
    ])
    return bounces, final, per_tread


@app.cell
def _(BALLS, OUT, estim, mo, traj):
    estim.plot_heights(traj, list(BALLS), OUT / "01_heights.png",
                       title="Three balls down the stairs: height and the located impacts")
    mo.vstack([
        mo.md("""
    ## Height traces

    The centre height of each ball, with a marker at every impact the solver located (an
    event of the exact solution, not a sign change spotted between samples). The treads
    are 0.20 m apart, so markers 0.20 m lower belong to the next tread down; markers at
    the same height are repeated hops on one tread.
    """),
        mo.image(src=(OUT / "01_heights.png").read_bytes()),
    ])
    return


@app.cell
def _(BALLS, COLOURS, E, Figure, MU_T, OUT, mo, np, scene, traj):
    # Mechanical energy per unit mass, E = g z + |v|^2 / 2 (potential energy from z = 0).
    _g = float(scene.gravity)
    _pos, _vel = np.asarray(traj.position), np.asarray(traj.velocity)
    energy = _g * _pos[..., 2] + 0.5 * np.sum(_vel**2, axis=-1)
    energy_ratio = energy[:, -1] / energy[:, 0]
    # Free flight conserves E, every impact removes some: E never increases ...
    assert np.all(np.diff(energy, axis=1) <= 1e-9 * energy[:, :1])
    # ... and each impact removes exactly (1 - e^2) of the vertical and (1 - mu_t^2) of the
    # horizontal kinetic energy, so the losses at the events add up to E(0) - E(2.3 s).
    _ev = traj.events
    _pre, _post = np.asarray(_ev.velocity_pre), np.asarray(_ev.velocity_post)
    _valid = np.arange(_pre.shape[1])[None, :] < np.asarray(_ev.count)[:, None]
    _e = np.array([E[b] for b in BALLS])[:, None]
    _loss_model = 0.5 * ((1 - _e**2) * _pre[..., 2] ** 2 + (1 - MU_T**2) * _pre[..., 0] ** 2)
    _loss_events = 0.5 * (np.sum(_pre**2, axis=-1) - np.sum(_post**2, axis=-1))
    np.testing.assert_allclose(np.where(_valid, _loss_events, 0), np.where(_valid, _loss_model, 0), atol=1e-12)
    np.testing.assert_allclose(np.sum(np.where(_valid, _loss_events, 0), axis=1), energy[:, 0] - energy[:, -1], rtol=1e-9)
    speed = [np.abs(_pre[i, _valid[i], 2]) for i in range(len(BALLS))]
    # The ping-pong ball keeps the most energy.
    assert energy_ratio[2] > max(energy_ratio[0], energy_ratio[1])

    # The plot, drawn here with matplotlib: estim.plot_energy exists but fails today
    # (it reads traj.gravity, which Trajectory does not have); switch to it once it works.
    _ts = np.asarray(traj.ts)
    _et = np.asarray(_ev.t)
    _ez = np.asarray(_ev.position)[..., 2]
    _fig = Figure(figsize=(8, 4.5), layout="tight")
    _ax = _fig.subplots()
    for _i, _b in enumerate(BALLS):
        # samples, and both sides of every impact, so each impact shows as the step it is
        _v = _valid[_i]
        _t = np.concatenate([_ts, _et[_i, _v], _et[_i, _v]])
        _en = np.concatenate([energy[_i], _g * _ez[_i, _v] + 0.5 * np.sum(_pre[_i, _v] ** 2, -1),
                              _g * _ez[_i, _v] + 0.5 * np.sum(_post[_i, _v] ** 2, -1)])
        _order = np.argsort(_t, kind="stable")
        _c = COLOURS.get(_b, f"C{_i}")
        _ax.plot(_t[_order], _en[_order] / energy[_i, 0], "-", lw=1.5, color=_c,
                 label=f"{_b} (e = {E[_b]}): keeps {energy_ratio[_i]:.0%}")
        _ax.plot(_et[_i, _v], _en[len(_ts) + _v.sum():] / energy[_i, 0], "v", ms=5, color=_c)
    _ax.set_xlabel("time t [s]")
    _ax.set_ylabel("E / E0   (E = g z + |v|^2 / 2)")
    _ax.set_title("Normalised mechanical energy: a step down at every impact")
    _ax.grid(alpha=0.3)
    _ax.legend(fontsize=8)
    _fig.savefig(OUT / "01_energy.png", dpi=110)
    _kept = ", ".join(f"{b} {E[b] ** 2:.0%}" for b in BALLS)
    _ratio = ", ".join(f"{b} {r:.0%}" for b, r in zip(BALLS, energy_ratio, strict=True))
    mo.vstack([
        mo.md(f"""
    ## Energy

    $E = g z + |v|^2 / 2$ per unit mass (potential energy from the ground, $z = 0$),
    divided by its value at release. In flight it is constant (gravity is conservative); at
    every impact it steps down, because the ball keeps only $e^2$ of its vertical kinetic
    energy ({_kept}) and $\\mu_t^2$ = {MU_T**2:.0%} of its horizontal one; the steps add up
    to the whole loss (checked above to rounding). After 2.3 s the balls keep {_ratio} of
    their energy.

    More bounces do not mean more loss: an impact removes a fraction of the vertical
    kinetic energy the ball *has*, and the bocce's extra bounces are short hops (vertical
    speeds at impact down to {speed[0].min():.2f} m/s, median {np.median(speed[0]):.2f})
    that carry little of it, while the golf ball's fewer impacts are hard (median
    {np.median(speed[1]):.2f} m/s). The ping-pong ball loses least: few impacts, each
    keeping {E["pingpong"] ** 2:.0%}.
    """),
        mo.image(src=(OUT / "01_energy.png").read_bytes()),
    ])
    return (energy_ratio,)


@app.cell
def _(BALLS, E, FAST, MU_T, OUT, STAIRS, T_END, VX0, estim, mo, np, params, scene, time, traj):
    # The animations: a ReplayMotion holds what a replay shows per frame. Here it carries
    # the simulated positions only (no measured samples: no halos, no trails).
    _fps, _w, _h = (10.0, 480, 270) if FAST else (25.0, 640, 360)
    _t = time.perf_counter()
    _frames_t = estim.frame_times(0.0, T_END, _fps)
    _pos, _ = traj.evaluate(_frames_t)  # exact positions at the frame times
    _pos = np.asarray(_pos)
    _empty = (np.zeros(0), np.zeros((0, 3)))
    motion = estim.ReplayMotion(
        balls=BALLS, t=_frames_t, fps=_fps,
        fitted={b: _pos[i] for i, b in enumerate(BALLS)},
        measured={b: np.full((len(_frames_t), 3), np.nan) for b in BALLS},
        samples={b: _empty for b in BALLS},
        params={b: {"e": E[b], "mu_t": MU_T, "vx0": VX0} for b in BALLS},
        radius={b: float(params.radius[i]) for i, b in enumerate(BALLS)},
    )
    _n_side = estim.write_gif(estim.SideView(scene, motion, _w, _h).frames(), OUT / "01_sideview.gif", _fps)
    gif_notes = []
    try:
        _n_mj = estim.write_gif(estim.render_frames(STAIRS, motion, width=_w, height=_h),
                                OUT / "01_mujoco.gif", _fps)
    except estim.RenderError as _err:  # no offscreen OpenGL on this machine
        _n_mj = 0
        gif_notes.append(f"MuJoCo GIF skipped: {_err}")
        print(gif_notes[-1])
    GIF_S = time.perf_counter() - _t
    _items = [
        mo.md(f"""
    ## Side view and MuJoCo

    The same exact positions, sampled at {_fps:g} frames per second ({_n_side} frames,
    made in {GIF_S:.1f} s with the MuJoCo one): a matplotlib side view (`estim.SideView`)
    and MuJoCo's renderer on the scene file itself (`estim.render_frames`). MuJoCo only
    draws: each frame sets the balls' free-joint positions and calls `mj_forward`; no
    MuJoCo physics runs. (The legends say "fitted" because the same tools replay fits;
    here the balls are the simulation.)
    """),
        mo.image(src=(OUT / "01_sideview.gif").read_bytes()),
    ]
    if _n_mj:
        _items.append(mo.image(src=(OUT / "01_mujoco.gif").read_bytes()))
    else:
        _items.append(mo.md(f"*{gif_notes[0]}*"))
    mo.vstack(_items)
    return GIF_S, gif_notes, motion


@app.cell
def _(BALLS, GIF_S, OUT, SIM_S, START, bounces, energy_ratio, final, json, mo, time):
    _summary = {
        "bounces": dict(zip(BALLS, bounces, strict=True)),
        "final_x": dict(zip(BALLS, final[:, 0].tolist(), strict=True)),
        "final_z": dict(zip(BALLS, final[:, 2].tolist(), strict=True)),
        "energy_kept": dict(zip(BALLS, energy_ratio.tolist(), strict=True)),
        "simulate_s": SIM_S,
        "gif_s": GIF_S,
        "total_s": time.perf_counter() - START,
    }
    (OUT / "01_three_balls.json").write_text(json.dumps(_summary, indent=2) + "\n")
    print("01_three_balls:", json.dumps(_summary))
    mo.md(f"""
    ## Summary

    Bounces {bounces[0]} / {bounces[1]} / {bounces[2]} for the bocce, golf and ping-pong
    balls: the least elastic ball bounces most often on these stairs. Next:
    `02_fit_video_tracks.py` goes the other way, from tracked positions to e, and
    `03_gradient_sanity.py` checks the derivatives through the bounces.
    """)
    return


if __name__ == "__main__":
    app.run()
