"""A spinning table-tennis ball: topspin and backspin in flight and at the bounce, an edge
ball, and a fit of a 3D shot with the sizes of its effects.

Run headless with ``python notebooks/06_table_tennis.py`` (figures go to
``$ESTIM_NOTEBOOK_OUT``, default ``notebooks/out/``), or open it with
``marimo edit notebooks/06_table_tennis.py``. The scene is ``data/scenes/table_tennis.xml``
(regulation table, net, still air, the friction law on the table). Every simulation here
is a batch of four balls with the same sample times, so the notebook compiles one ODE
program for all of them, and one fit.
"""

import marimo

__generated_with = "0.25.2"
app = marimo.App()


@app.cell
def _():
    import json
    import time

    import jax
    import jax.numpy as jnp
    import marimo as mo
    import numpy as np
    from _common import OUT, ROOT, md_table  # notebooks/_common.py
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    import estim

    START = time.perf_counter()
    return Circle, Figure, OUT, ROOT, START, estim, jax, jnp, json, md_table, mo, np, time


@app.cell
def _(mo):
    mo.md(r"""
    # A spinning table-tennis ball

    A table-tennis ball is light (2.7 g) and big (40 mm) for its weight, and players spin it
    at up to a few hundred rad/s. In flight the air pushes it three ways: drag against its
    velocity, and the Magnus force $\propto \boldsymbol\omega \times \mathbf v$, down for
    topspin and up for backspin. At the bounce the table's friction acts at the contact
    point, where the ball's surface moves at $\mathbf v + \boldsymbol\omega \times
    (-r\,\mathbf n)$: topspin drives the ball forward off the table, backspin holds it back
    (the friction law, `estim.FrictionLaw`: Coulomb friction with sliding and gripping;
    the *Contact model* page of the docs derives it). The scene
    `data/scenes/table_tennis.xml` declares all of this: still air in its `<option>`, the
    friction law in its `<custom>`.
    """)
    return


@app.cell
def _(ROOT, estim, jax, jnp, np):
    scene = estim.load_scene(ROOT / "data" / "scenes" / "table_tennis.xml")
    BALL = scene.ball("pingpong")
    R = float(BALL.radius)
    T_END = 0.8
    TS = jnp.linspace(0.0, T_END, 401)  # one set of sample times: one compiled program
    NAMES = ("topspin", "no spin", "backspin", "edge ball")
    # Played from behind the near end line (y = -1.37 m) along +y. Topspin: the top of the
    # ball moves forward, omega along -x; backspin the opposite.
    SPIN = 150.0  # rad/s
    RELEASE = np.array([0.0, -1.5, 0.30])
    THROW = np.array([0.0, 5.0, 2.0])

    def stack(rows):
        """One batch of Params from one Params per ball."""
        return jax.tree.map(lambda *x: jnp.stack(x), *rows)

    def batch(positions, velocities, spins, e=0.9, mu=0.25):
        """Params of a batch of the scene's ball, one row per ball."""
        # (mu_t is the seed's law's tangential factor; the friction law does not read it.)
        return stack([estim.Params.for_ball(scene, "pingpong", e=e, mu_t=0.0, mu=mu, position=p, velocity=v, spin=w)
                      for p, v, w in zip(positions, velocities, spins, strict=True)])

    # The edge ball: dropped from rest with its centre 1 cm beyond the far end line
    # (y = 1.37 m): it meets the table's edge, not its top.
    EDGE_OFFSET = 0.01
    EDGE_RELEASE = np.array([0.0, 1.37 + EDGE_OFFSET, 0.30])
    positions = [RELEASE, RELEASE, RELEASE, EDGE_RELEASE]
    velocities = [THROW, THROW, THROW, np.zeros(3)]
    spins = [[-SPIN, 0.0, 0.0], [0.0, 0.0, 0.0], [SPIN, 0.0, 0.0], [0.0, 0.0, 0.0]]
    shots = estim.simulate(scene, batch(positions, velocities, spins), T_END, ts=TS)
    return BALL, EDGE_OFFSET, NAMES, R, SPIN, T_END, TS, batch, scene, shots, stack


@app.cell
def _(EDGE_OFFSET, NAMES, R, SPIN, estim, np, scene, shots):
    def first_impact(i):
        """(t, position, velocity before, after, normal, solid) of ball i's first impact."""
        ev = shots.events
        k = int(np.flatnonzero(np.asarray(ev.kind[i]) == 0)[0])
        face = int(ev.face[i, k])
        normal = np.asarray(estim.contact_normals(scene, ev.face[i, k], ev.position[i, k]))
        return (float(ev.t[i, k]), np.asarray(ev.position[i, k]), np.asarray(ev.velocity_pre[i, k]),
                np.asarray(ev.velocity_post[i, k]), normal, scene.face_label(face)[0])

    bounces = {name: first_impact(i) for i, name in enumerate(NAMES)}
    # Flight: Magnus pushes topspin down and backspin up, so topspin lands first and short.
    t_top, t_none, t_back = (bounces[n][0] for n in NAMES[:3])
    y_top, y_none, y_back = (bounces[n][1][1] for n in NAMES[:3])
    assert t_top < t_none < t_back and y_top < y_none < y_back
    assert all(bounces[n][5] == "table" for n in NAMES)
    # Bounce, against the friction law's closed forms (Coulomb friction at the contact
    # point; the ball a thin shell, I = 2/3 m r^2, as the scene says). The normal speed is
    # reversed and scaled by e. The contact point slides along the table at v_y - r w_x
    # ... - r |w| for topspin, v_y for none, v_y + r |w| for backspin. Friction's impulse is at
    # most mu (1 + e) |v_n| m; stopping the slip takes m |slip| / (1 + m r^2 / I) = m |slip| / 2.5.
    # Topspin's small slip is stopped (the ball leaves rolling): dv_y = -slip / 2.5. The other
    # two slide through the whole impact: dv_y = -mu (1 + e) |v_n|.
    E, MU = 0.9, 0.25
    for _name, _w in zip(NAMES[:3], (-SPIN, 0.0, SPIN), strict=True):
        _, _, _pre, _post, _, _ = bounces[_name]
        _slip = _pre[1] + R * _w
        _grip = _slip / 2.5
        _slide = MU * (1 + E) * abs(_pre[2])
        _dv = -_grip if abs(_grip) <= _slide else -np.sign(_slip) * _slide
        assert (_name == "topspin") == (abs(_grip) <= _slide), _name
        np.testing.assert_allclose(_post[1:] - _pre[1:], [_dv, -(1 + E) * _pre[2]], rtol=1e-9, atol=1e-12)
    # The edge ball touches the edge line (y = 1.37, z = 0) when its centre is r from it:
    # d = 1 cm beyond the line, at height sqrt(r^2 - d^2), the normal along that line.
    EDGE_HEIGHT = float(np.sqrt(R**2 - EDGE_OFFSET**2))
    _, edge_at, _, edge_after, edge_normal, _ = bounces["edge ball"]
    np.testing.assert_allclose(edge_at[1:], [1.37 + EDGE_OFFSET, EDGE_HEIGHT], atol=1e-9)
    np.testing.assert_allclose(edge_normal, [0.0, EDGE_OFFSET / R, EDGE_HEIGHT / R], atol=1e-9)
    assert edge_after[1] > 0  # thrown off the table, away from it
    return EDGE_HEIGHT, bounces, edge_after, edge_normal


@app.cell
def _(Circle, EDGE_HEIGHT, Figure, NAMES, OUT, SPIN, bounces, edge_after, edge_normal, md_table, mo, np, shots):
    _fig = Figure(figsize=(10, 4.2), layout="tight")
    _ax, _edge = _fig.subplots(1, 2, gridspec_kw={"width_ratios": [3, 1]})
    _pos = np.asarray(shots.position)
    for _i, (_name, _c) in enumerate(zip(NAMES[:3], ("C3", "0.3", "C0"), strict=True)):
        _ax.plot(_pos[_i, :, 1], _pos[_i, :, 2], color=_c, lw=1.6, label=_name)
        _ax.plot(*bounces[_name][1][1:], "v", color=_c, ms=6)
    _ax.plot([-1.37, 1.37], [0, 0], color="navy", lw=4, label="table")
    _ax.plot([0, 0], [0, 0.1525], color="0.6", lw=2, label="net")
    _ax.set(xlabel="y along the table [m]", ylabel="z [m] (ball centre)", ylim=(-0.05, None),
            title=f"{SPIN:.0f} rad/s of topspin and backspin, 5.4 m/s, still air")
    _ax.set_aspect("equal")
    _ax.legend(fontsize=8)
    _ax.grid(alpha=0.3)
    _p = _pos[3]
    _edge.plot(_p[:, 1], _p[:, 2], color="C2", lw=1.6, label="edge ball")
    _edge.fill_between([1.2, 1.37], [-0.03, -0.03], [0, 0], color="navy")
    _at = bounces["edge ball"][1]
    _edge.add_patch(Circle(_at[1:], 0.02, fill=False, color="C2"))
    _edge.arrow(1.37, 0.0, 0.02 * edge_normal[1], 0.02 * edge_normal[2], color="k", width=0.0008)
    _edge.set(xlim=(1.25, 1.5), ylim=(-0.03, 0.12), xlabel="y [m]", title="an edge ball")
    _edge.set_aspect("equal")
    _edge.grid(alpha=0.3)
    _fig.savefig(OUT / "06_spin.png", dpi=110)

    _rows = [[n, f"{bounces[n][0]:.3f}", f"{bounces[n][1][1]:+.3f}",
              f"({bounces[n][2][1]:.2f}, {bounces[n][2][2]:.2f})", f"({bounces[n][3][1]:.2f}, {bounces[n][3][2]:.2f})"]
             for n in NAMES[:3]]
    mo.vstack([
        mo.md("""
        ## Topspin and backspin

        The same throw (5 m/s along the table, 2 m/s up, from 0.13 m behind the end line)
        with 150 rad/s of topspin, none, and backspin. In flight, topspin dips and lands
        first and short; backspin floats and lands long. At the bounce the table's friction
        acts against the slip of the ball's bottom along the table, v − rω: topspin's slip
        is small, friction stops it within the impact and the ball leaves rolling, having
        lost only a fifth of it (a thin shell: m r²/I = 3/2); without spin, and with
        backspin, the ball slides through the whole impact and loses μ(1 + e)|v_n| of its
        speed along the table (both checked against these closed forms to 1e-9). The
        normal speed is reversed and scaled by e = 0.9.
        """),
        md_table(["spin", "bounce at t [s]", "y [m]", "(vy, vz) before [m/s]", "(vy, vz) after [m/s]"], _rows),
        mo.md(f"""
        **An edge ball.** Dropped with its centre 1 cm beyond the far end line, the ball
        meets the table's edge, not its top: estim's exact geometry has it touch the edge
        line when its centre is r = 2 cm from it, at height √(r² − d²) = {EDGE_HEIGHT * 1e3:.2f} mm
        (checked to 1 nm), and the contact normal points from the edge to the centre,
        ({edge_normal[1]:.3f}, {edge_normal[2]:.3f}) in (y, z): the ball leaves away from the
        table at {edge_after[1]:.2f} m/s.
        """),
        mo.image(str(OUT / "06_spin.png")),
    ])
    return


@app.cell
def _(BALL, estim, np, scene):
    # A 3D shot to fit: released with a sideways component and topspin tilted by sidespin,
    # 180 Hz, 2 mm of noise per coordinate, one bounce on the table (estim's own model, so
    # the truth is known).
    TRUTH = {"e": 0.88, "mu": 0.3, "position": np.array([-0.2, -1.6, 0.25]),
             "velocity": np.array([0.4, 6.5, 1.6]), "spin": np.array([-120.0, 0.0, 40.0])}
    NOISE = 0.002
    _t = np.arange(0.0, 0.6, 1.0 / 180.0)
    _truth = estim.Params.for_ball(scene, "pingpong", e=TRUTH["e"], mu_t=0.0, mu=TRUTH["mu"], position=TRUTH["position"],
                                   velocity=TRUTH["velocity"], spin=TRUTH["spin"])
    _clean = np.asarray(estim.simulate(scene, _truth, 0.6, ts=_t).position)
    SHOT = (_t, _clean + np.random.default_rng(7).normal(0.0, NOISE, _clean.shape))
    assert float(BALL.mass) == 0.0027
    return NOISE, SHOT, TRUTH


@app.cell
def _(NOISE, SHOT, TRUTH, estim, np, scene, time):
    _t0 = time.perf_counter()
    fit = estim.fit(scene, {"pingpong": SHOT}, effects=True)
    FIT_S = time.perf_counter() - _t0
    bf = fit.balls["pingpong"]
    fitted_spin = np.array([bf.values[f"spin_{c}"] for c in "xyz"])
    # The spin across the flight (the part of omega perpendicular to the velocity) is what
    # bends the path; the part along the velocity does nothing in flight.
    _u = TRUTH["velocity"] / np.linalg.norm(TRUTH["velocity"])

    def across(w):
        return w - np.dot(w, _u) * _u

    SPIN_ERROR = float(np.linalg.norm(across(fitted_spin) - across(TRUTH["spin"])) / np.linalg.norm(across(TRUTH["spin"])))
    assert abs(bf.values["e"] - TRUTH["e"]) < 0.01, bf.values
    # The topspin bounce grips: the data only bound mu from below, and the scene's prior
    # (0.25 +- 0.1) holds it, as a note says. Then the true mu must move the fitted path by
    # less than a tenth of the noise: the data cannot tell the two apart.
    MU_HELD = any(_n.startswith("mu is held by its prior") for _n in bf.notes)
    if MU_HELD:
        _p = np.array([bf.values[k] for k in ("x0", "y0", "z0")])
        _runs = [np.asarray(estim.simulate(scene, estim.Params.for_ball(
            scene, "pingpong", e=bf.values["e"], mu_t=0.0, mu=_mu, position=_p,
            velocity=np.array([bf.values[c] for c in ("vx0", "vy0", "vz0")]), spin=fitted_spin),
            float(SHOT[0][-1]), ts=SHOT[0]).position) for _mu in (bf.values["mu"], TRUTH["mu"])]
        assert np.max(np.linalg.norm(_runs[0] - _runs[1], axis=1)) < 0.1 * NOISE
    else:
        assert abs(bf.values["mu"] - TRUTH["mu"]) < 0.03, bf.values
    assert SPIN_ERROR < 0.1, SPIN_ERROR
    assert bf.at_noise_floor and abs(bf.noise_m / NOISE - 1) < 0.2, (bf.rms_m, bf.noise_m)
    return FIT_S, MU_HELD, SPIN_ERROR, bf, fit, fitted_spin


@app.cell
def _(bf):
    # The effect sizes of the fitted shot (`estim.fit(..., effects=True)`, `estim fit
    # --effects`): how far each effect of the model moves the fitted ball over the track, the
    # fitted ball against the same ball without it, in mm and in noise levels (the noise the
    # fit read from the data).
    EFFECTS = {_m["effect"]: {"max_mm": _m["max_deviation_mm"], "noise_levels": _m["noise_levels"],
                              "switched_off": _m["switched_off"], "verdict": _m["verdict"]}
               for _m in bf.effects}
    return (EFFECTS,)


@app.cell
def _(EFFECTS, FIT_S, Figure, MU_HELD, OUT, SHOT, SPIN_ERROR, TRUTH, bf, md_table, mo, np):
    _t, _obs = SHOT
    _model = np.asarray(bf.model_position)
    _fig = Figure(figsize=(10, 3.6), layout="tight")
    _side, _above = _fig.subplots(1, 2)
    _side.plot(_obs[:, 1], _obs[:, 2], ".", ms=3, color="0.5", label="track (2 mm noise)")
    _side.plot(_model[:, 1], _model[:, 2], "-", color="C3", lw=1.2, label="fitted model")
    _side.legend(fontsize=8)
    _above.plot(_obs[:, 0], _obs[:, 1], ".", ms=3, color="0.5")
    _above.plot(_model[:, 0], _model[:, 1], "-", color="C3", lw=1.2)
    _side.set(xlabel="y [m]", ylabel="z [m]", title="from the side")
    _above.set(xlabel="x [m]", ylabel="y [m]", title="from above")
    for _a in (_side, _above):
        _a.grid(alpha=0.3)
    _fig.savefig(OUT / "06_fit.png", dpi=110)
    _rows = [["e", f"{TRUTH['e']:.3f}", f"{bf.values['e']:.3f} ± {bf.stderr['e']:.3f}"],
             ["mu", f"{TRUTH['mu']:.3f}", f"{bf.values['mu']:.3f} ± {bf.stderr['mu']:.3f}"]]
    _rows += [[f"spin_{c}", f"{TRUTH['spin'][i]:.0f}", f"{bf.values[f'spin_{c}']:.0f} ± {bf.stderr[f'spin_{c}']:.0f}"]
              for i, c in enumerate("xyz")]
    _effects = [[n, v["switched_off"], f"{v['max_mm']:.1f}", f"{v['noise_levels']:.3g}", v["verdict"]]
                for n, v in EFFECTS.items()]
    mo.vstack([
        mo.md(f"""
        ## A 3D shot, fitted

        A shot with topspin tilted by sidespin, tracked at 180 Hz with 2 mm of noise, fitted
        with `estim.fit(scene, {{"pingpong": (t, positions)}})` and the scene's defaults: the
        release position, velocity and spin (3-vectors), e, the friction coefficient mu and
        the drag coefficient (the scene gives these priors, and the spin a loose one:
        0 ± 1000 rad/s per axis).
        The starting values come from the data (the release state from the first 0.1 s,
        the spin from the flight's curvature, e and mu from the velocity jump at the
        bounce). The fit took {FIT_S:.0f} s with JAX's compile; rms {bf.rms_m * 1e3:.2f} mm.
        The spin across the flight is read to {SPIN_ERROR:.1%}; the part along the
        velocity does not bend the path and is only weakly fixed (by the bounce).
        {"The topspin bounce grips: the data only bound mu from below, and the scene's prior on mu (0.25 ± 0.1, declared in `data/scenes/table_tennis.xml`) holds it; the true mu moves the fitted path by less than a tenth of the noise." if MU_HELD else ""}
        """),
        md_table(["parameter", "truth", "fitted ± standard error"], _rows),
        mo.md("""
        **What the data can tell apart** (`estim.fit(..., effects=True)`, `estim fit
        --effects`). Each effect's size is the largest distance between the fitted ball and
        the same ball without that effect, over the track, in noise levels: quadratic drag
        (C_D = 0), the air's viscosity (Stokes drag), Magnus (lift factor 0), the spin's
        effect at the bounce (no spin at all against spin, both without Magnus) and the
        bounce's friction (mu = 0). An effect of many noise levels is one the track
        measures; one below a noise level is one it cannot tell from its absence. (A large
        effect does not make its coefficient identifiable: mu = 0 changes this bounce a lot,
        but any mu above the grip threshold gives the same bounce.)
        """),
        md_table(["effect", "switched off", "moves the ball by [mm]", "noise levels", "verdict"], _effects),
        mo.image(str(OUT / "06_fit.png")),
    ])
    return


@app.cell
def _(EDGE_HEIGHT, EFFECTS, FIT_S, MU_HELD, OUT, SPIN_ERROR, START, bf, bounces, json, time):
    summary = {"bounce_t": {n: b[0] for n, b in bounces.items()},
               "after_vy": {n: float(b[3][1]) for n, b in bounces.items()},
               "edge": {"position": [float(x) for x in bounces["edge ball"][1]],
                        "normal": [float(x) for x in bounces["edge ball"][4]], "height": EDGE_HEIGHT},
               "fit": {"e": bf.values["e"], "mu": bf.values["mu"], "mu_held_by_prior": MU_HELD, "rms_m": bf.rms_m,
                       "spin_error": SPIN_ERROR, "fit_s": FIT_S},
               "effects": EFFECTS, "total_s": time.perf_counter() - START}
    (OUT / "06_table_tennis.json").write_text(json.dumps(summary, indent=1))
    print("06_table_tennis:", json.dumps(summary))
    return


if __name__ == "__main__":
    app.run()
