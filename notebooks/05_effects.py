"""Effects a scene calls for: drag on a ping-pong ball and a bocce ball, and spin.

Run headless with ``python notebooks/05_effects.py`` (figures go to ``$ESTIM_NOTEBOOK_OUT``,
default ``notebooks/out/``), or open it with ``marimo edit notebooks/05_effects.py``.
Every air run here shares one compiled ODE program (the same four balls, the same 1001
sample times; the air, the spin and the tolerances are values, not structure), so the
notebook compiles two programs: the closed form and the ODE path.
"""

import marimo

__generated_with = "0.25.2"
app = marimo.App()


@app.cell
def _():
    import json
    import statistics
    import time

    import jax
    import jax.numpy as jnp
    import marimo as mo
    import numpy as np
    from _common import OUT, ROOT, md_table  # notebooks/_common.py
    from matplotlib.figure import Figure

    import estim
    import estim.forward._ode as estim_ode  # only for TRACE_COUNT: how often the ODE solver was traced
    from estim.show._plots import COLOURS  # the colours of estim's plots and replays

    START = time.perf_counter()
    TRACES_AT_START = estim_ode.TRACE_COUNT

    def median_s(fn, repeats):
        """Median wall time (s) of ``fn()`` over ``repeats`` calls (after one warm-up)."""
        jax.block_until_ready(fn())
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(fn())
            times.append(time.perf_counter() - t)
        return statistics.median(times)
    return (COLOURS, Figure, OUT, ROOT, START, TRACES_AT_START, estim_ode, estim, jax, jnp, json,
            md_table, median_s, mo, np, time)


@app.cell
def _(mo):
    mo.md(r"""
    # Effects a scene calls for

    In a vacuum a ball's flight is a parabola and estim solves it exactly, in closed form.
    Real balls fly through air. Whether that matters depends on the ball: drag decelerates
    a ball by

    $$ |a_\text{drag}| = k\, v^2, \qquad k = \frac{\rho\, C_D\, \pi r^2}{2 m}, $$

    which is large for a light, big ball and small for a heavy, compact one. This notebook
    measures what still air ($\rho$ = 1.204 kg/m³, $\eta$ = 1.81e-5 Pa s, $C_D$ = 0.47) and
    spin do to the seed scene's balls on the staircase, checks the ODE path against the
    closed form of a vertical drop with drag, and shows that a scene without air pays
    nothing for any of this: the scene decides the physics (`data/scenes/stairs.xml`
    has no air, `data/scenes/stairs_air.xml` is the same staircase in still air). The
    force laws are on the *Drag and Magnus* page of the docs (`docs/pages/effects.md`).
    """)
    return


@app.cell
def _(ROOT, estim, jax, jnp, np):
    SCENES = ROOT / "data" / "scenes"
    vacuum_scene = estim.load_scene(SCENES / "stairs.xml")
    air_scene = estim.load_scene(SCENES / "stairs_air.xml")
    RHO = float(air_scene.air.density)
    ETA = float(air_scene.air.viscosity)
    G = float(vacuum_scene.gravity)
    CD = 0.47  # estim's default drag coefficient (a smooth sphere)
    T_END, VX0, MU_T = 2.3, 1.15, 0.98
    N_SAMPLES = 1001  # as estim.effect_sizes samples: every air run shares one program
    TS = jnp.linspace(0.0, T_END, N_SAMPLES)
    # The seed's three balls and, fourth, a regulation ping-pong ball (40 mm diameter,
    # 2.7 g): the scene's ping-pong ball is oversized (80 mm, 5 g).
    BALLS = ("bocce", "golf", "pingpong", "regulation pingpong")
    E = {"bocce": 0.55, "golf": 0.70, "pingpong": 0.85, "regulation pingpong": 0.85}
    _spec = {b.name: (b.radius, b.mass, b.position[1]) for b in vacuum_scene.balls}
    _spec["regulation pingpong"] = (0.020, 0.0027, _spec["pingpong"][2])
    RADIUS = np.array([_spec[b][0] for b in BALLS])
    MASS = np.array([_spec[b][1] for b in BALLS])
    K = RHO * CD * np.pi * RADIUS**2 / (2 * MASS)  # quadratic drag per squared speed (1/m)

    def balls(position, velocity, spin=None, names=BALLS):
        """Params of a batch of balls (by name; default the four): one row of position,
        velocity and spin per ball, radius, mass and e from the ball."""
        spin = np.zeros((len(names), 3)) if spin is None else spin
        rows = []
        for j, b in enumerate(names):
            i = BALLS.index(b)
            rows.append(estim.Params(E[b], MU_T, RADIUS[i], position[j], velocity[j], mass=MASS[i],
                                     drag_coefficient=CD, spin=spin[j]))
        return jax.tree.map(lambda *x: jnp.stack(x), *rows)

    # Released as in the seed: x0 = -0.20 m, 0.25 m above the first tread (top 1.40 m),
    # thrown forward at 1.15 m/s. The scene's balls start exactly there.
    RELEASE = np.array([[-0.20, _spec[b][2], 1.40 + _spec[b][0] + 0.25] for b in BALLS])
    for _i, _b in enumerate(BALLS[:3]):
        np.testing.assert_allclose(RELEASE[_i], vacuum_scene.ball(_b).position, atol=1e-12)
    THROW = np.tile([VX0, 0.0, 0.0], (len(BALLS), 1))
    seed_params = balls(RELEASE, THROW)
    return (BALLS, CD, E, ETA, G, K, MASS, MU_T, RADIUS, RHO, T_END, TS, VX0, air_scene, balls,
            seed_params, vacuum_scene)


@app.cell
def _(BALLS, T_END, TRACES_AT_START, TS, estim_ode, air_scene, estim, median_s, mo, np, seed_params,
      time, vacuum_scene):
    # The same balls in both scenes. Count how often the ODE solver is traced.
    _t = time.perf_counter()
    vacuum = estim.simulate(vacuum_scene, seed_params, T_END, ts=TS)
    VACUUM_FIRST_S = time.perf_counter() - _t
    TRACES_AFTER_VACUUM = estim_ode.TRACE_COUNT - TRACES_AT_START
    _t = time.perf_counter()
    still = estim.simulate(air_scene, seed_params, T_END, ts=TS)
    AIR_FIRST_S = time.perf_counter() - _t
    TRACES_AFTER_AIR = estim_ode.TRACE_COUNT - TRACES_AT_START
    assert TRACES_AFTER_VACUUM == 0, "a gravity-only scene traced the ODE solver"
    assert TRACES_AFTER_AIR == 1

    def impacts(traj):
        """Impact times per ball (kind 0; kind 1 is a landing to rest)."""
        t, kind, n = (np.asarray(x) for x in (traj.events.t, traj.events.kind, traj.events.count))
        return [t[i, : n[i]][kind[i, : n[i]] == 0] for i in range(len(BALLS))]

    VACUUM_BOUNCES = [len(x) for x in impacts(vacuum)]
    AIR_BOUNCES = [len(x) for x in impacts(still)]
    # The closed form's seed numbers: bounces 9 / 6 / 4.
    assert VACUUM_BOUNCES[:3] == [9, 6, 4], VACUUM_BOUNCES
    VACUUM_US = median_s(lambda: estim.simulate(vacuum_scene, seed_params, T_END, ts=TS), 20) * 1e6
    AIR_US = median_s(lambda: estim.simulate(air_scene, seed_params, T_END, ts=TS), 5) * 1e6
    assert estim_ode.TRACE_COUNT - TRACES_AT_START == 1  # calling again reuses the program
    mo.md(f"""
    ## Effects cost nothing unless the scene asks

    `estim.simulate` takes its physics from the scene. On `stairs.xml` (gravity only) it
    runs the closed form: the ODE solver was traced **{TRACES_AFTER_VACUUM} times**
    (`estim.forward._ode.TRACE_COUNT`, which counts traces of the ODE program) for the four balls,
    first call {VACUUM_FIRST_S:.1f} s with JAX's compile, then {VACUUM_US:.0f} µs per
    call. The same call on `stairs_air.xml`, which adds one line,
    `<option density="1.204" viscosity="1.81e-5"/>`, traces the ODE program once
    (count {TRACES_AFTER_AIR}), takes {AIR_FIRST_S:.1f} s the first time and then
    {AIR_US / 1e3:.1f} ms per call, **{AIR_US / VACUUM_US:.0f}×** the closed form. Every
    other air run in this notebook (other air, spin, drop heights, `estim.effect_sizes`)
    reuses that one program: the air, drag coefficients, spins and tolerances are values,
    not structure (the count is checked again at the end).

    Bounces in 2.3 s, vacuum → still air: {", ".join(f"{b} {v} → {a}" for b, v, a in
    zip(BALLS, VACUUM_BOUNCES, AIR_BOUNCES, strict=True))} (the vacuum's 9 / 6 / 4 are the
    seed's closed-form numbers).
    """)
    return (AIR_BOUNCES, AIR_US, TRACES_AFTER_AIR, TRACES_AFTER_VACUUM, VACUUM_BOUNCES,
            VACUUM_US, impacts, still, vacuum)


@app.cell
def _(BALLS, COLOURS, Figure, K, OUT, RHO, CD, impacts, md_table, mo, np, still, vacuum):
    # Drag on the stairs: the ping-pong ball against the bocce ball.
    _ts = np.asarray(vacuum.ts)
    _tv, _ta = impacts(vacuum), impacts(still)
    STAIRS_DELAY_MS = {b: float((_ta[i][0] - _tv[i][0]) * 1e3) for i, b in enumerate(BALLS)}
    _final_v, _final_a = np.asarray(vacuum.final.position), np.asarray(still.final.position)
    STAIRS_SHORT_MM = {b: float((_final_v[i, 0] - _final_a[i, 0]) * 1e3) for i, b in enumerate(BALLS)}
    _fig = Figure(figsize=(9, 6.5), layout="tight")
    _axes = _fig.subplots(2, 1, sharex=True)
    for _ax, _b in zip(_axes, ("pingpong", "bocce"), strict=True):
        _i = BALLS.index(_b)
        _c = COLOURS.get(_b, "C0")
        _ax.plot(_ts, np.asarray(vacuum.position)[_i, :, 2], "--", color="0.45", lw=1.2,
                 label=f"vacuum (closed form): {len(_tv[_i])} bounces")
        _ax.plot(_ts, np.asarray(still.position)[_i, :, 2], "-", color=_c, lw=1.6,
                 label=f"still air (ODE path): {len(_ta[_i])} bounces")
        _ax.plot(_tv[_i], np.interp(_tv[_i], _ts, np.asarray(vacuum.position)[_i, :, 2]), "v", color="0.45", ms=5)
        _ax.plot(_ta[_i], np.interp(_ta[_i], _ts, np.asarray(still.position)[_i, :, 2]), "v", color=_c, ms=5)
        _ax.set_ylabel("centre height z [m]")
        _ax.set_title(f"{_b}: k = {K[_i]:.3g} /m, first bounce {STAIRS_DELAY_MS[_b]:+.2f} ms, "
                      f"final x {-STAIRS_SHORT_MM[_b]:+.0f} mm", fontsize=10)
        _ax.grid(alpha=0.3)
        _ax.legend(fontsize=8, loc="upper right")
    _axes[-1].set_xlabel("time t [s]")
    _fig.savefig(OUT / "05_drag_heights.png", dpi=110)

    _rows = [[b, f"{K[i]:.4f}", f"{STAIRS_DELAY_MS[b]:+.3f}", f"{STAIRS_SHORT_MM[b]:.1f}",
              f"{len(_tv[i])} → {len(_ta[i])}"] for i, b in enumerate(BALLS)]
    _pp, _bo = BALLS.index("pingpong"), BALLS.index("bocce")
    DELAY_RATIO = STAIRS_DELAY_MS["pingpong"] / STAIRS_DELAY_MS["bocce"]
    # Drag delays every ball, and the ping-pong ball far more than the bocce ball.
    assert STAIRS_DELAY_MS["pingpong"] > 10 * STAIRS_DELAY_MS["bocce"] > 0
    # ... by about the ratio of their drag constants (first order in k).
    assert abs(DELAY_RATIO / (K[_pp] / K[_bo]) - 1) < 0.2, (DELAY_RATIO, K[_pp] / K[_bo])
    mo.vstack([
        mo.md(f"""
    ## Drag on the stairs: ping-pong against bocce

    The seed release (0.25 m above the first tread, thrown at 1.15 m/s), in a vacuum and
    in still air. The first bounce is the cleanest measure of the drag: before it, the two
    runs differ by the air alone. The ping-pong ball's first bounce comes
    {STAIRS_DELAY_MS["pingpong"]:.2f} ms later than in a vacuum, the bocce ball's
    {STAIRS_DELAY_MS["bocce"] * 1e3:.0f} µs later: a ratio of {DELAY_RATIO:.0f}, close to
    the ratio of their drag constants $k$ ({K[_pp] / K[_bo]:.0f}, next section). By the
    end, 2.3 s later, the ping-pong ball is {STAIRS_SHORT_MM["pingpong"]:.0f} mm short of
    its vacuum position.
    """),
        md_table(["ball", "k = ρ C_D π r² / 2m (1/m)", "first bounce later by (ms)",
                  "final x shorter by (mm)", "bounces vacuum → air"], _rows),
        mo.md(f"""
    (ρ = {RHO} kg/m³, C_D = {CD}.) Small changes early can still move the end a lot: on a
    staircase a few millimetres decide whether a late hop clears a tread's edge, so final
    positions jump where bounce times change smoothly.
    """),
        mo.image(src=(OUT / "05_drag_heights.png").read_bytes()),
    ])
    return DELAY_RATIO, STAIRS_DELAY_MS, STAIRS_SHORT_MM


@app.cell
def _(BALLS, COLOURS, CD, Figure, G, K, MASS, OUT, RADIUS, RHO, STAIRS_DELAY_MS, T_END, TS,
      balls, estim, impacts, md_table, mo, np, vacuum_scene):
    # The vertical drop: from rest, H above the top tread, quadratic drag only. Its first
    # contact has a closed form, t = (v_t / g) arccosh(exp(g H / v_t^2)).
    H = 1.0
    _drop = np.array([[0.0, 0.0, 1.40 + r + H] for r in RADIUS])
    _quad_only = vacuum_scene.with_air(estim.Air(density=RHO))  # no viscosity
    _traj = estim.simulate(_quad_only, balls(_drop, np.zeros((len(BALLS), 3))), T_END, ts=TS)
    DROP_T = np.array([x[0] for x in impacts(_traj)])
    VT = np.sqrt(G / K)  # terminal speed, where k v^2 = g
    DROP_T_EXACT = VT / G * np.arccosh(np.exp(G * H / VT**2))
    T0 = np.sqrt(2 * H / G)  # in a vacuum
    DROP_DELAY_MS = (DROP_T - T0) * 1e3
    # Small k: ln cosh x = x^2/2 - x^4/12 + ..., so t = t0 (1 + k H / 6 + ...).
    _approx_ms = T0 * K * H / 6 * 1e3
    DROP_REL_ERR = np.abs(DROP_T - DROP_T_EXACT) / DROP_T_EXACT
    assert np.all(DROP_REL_ERR < 1e-7), DROP_REL_ERR
    _v_hit = VT * np.tanh(G * DROP_T_EXACT / VT)
    _dec = K * _v_hit**2 / G  # drag / gravity at the moment of impact

    _fig = Figure(figsize=(7, 4.5), layout="tight")
    _ax = _fig.subplots()
    _kk = np.geomspace(K.min() / 2, K.max() * 2, 100)
    _vt = np.sqrt(G / _kk)
    _ax.loglog(_kk, (_vt / G * np.arccosh(np.exp(G * H / _vt**2)) - T0) * 1e3, "-", color="0.3",
               label=r"closed form $(v_t/g)\,\mathrm{arccosh}(e^{gH/v_t^2}) - t_0$")
    _ax.loglog(_kk, T0 * _kk * H / 6 * 1e3, ":", color="0.5", label=r"small $k$: $t_0\,k H/6$")
    for _i, _b in enumerate(BALLS):
        _ax.loglog([K[_i]], [DROP_DELAY_MS[_i]], "o", ms=8, color=COLOURS.get(_b, "C3"),
                   label=f"{_b}: estim, ODE path")
    _ax.set_xlabel(r"$k = \rho C_D \pi r^2 / (2m)$ [1/m]")
    _ax.set_ylabel("first contact later than in a vacuum [ms]")
    _ax.set_title(f"Vertical drop from {H:g} m with quadratic drag", fontsize=10)
    _ax.grid(alpha=0.3, which="both")
    _ax.legend(fontsize=7)
    _fig.savefig(OUT / "05_drop_delay.png", dpi=110)

    _rows = [[b, f"{RADIUS[i] * 1e3:.0f}", f"{MASS[i] * 1e3:g}", f"{K[i]:.4f}", f"{VT[i]:.1f}",
              f"{_dec[i]:.1%}", f"{DROP_DELAY_MS[i]:.4f}", f"{(DROP_T_EXACT[i] - T0) * 1e3:.4f}",
              f"{_approx_ms[i]:.4f}", f"{DROP_REL_ERR[i]:.1e}", f"{STAIRS_DELAY_MS[b]:.4f}"]
             for i, b in enumerate(BALLS)]
    _pp, _bo, _reg = (BALLS.index(b) for b in ("pingpong", "bocce", "regulation pingpong"))
    mo.vstack([
        mo.md(f"""
    ## From first principles: the drag constant and a drop with a closed form

    Quadratic drag decelerates a ball by $k v^2$ with $k = \\rho C_D \\pi r^2 / (2m)$; its
    terminal speed is $v_t = \\sqrt{{g/k}}$. A ball dropped from rest through a height $H$
    with this drag alone reaches it at

    $$ t = \\frac{{v_t}}{{g}}\\,\\operatorname{{arccosh}}\\!\\left(e^{{g H / v_t^2}}\\right)
       \\;\\approx\\; t_0 \\left(1 + \\frac{{k H}}{{6}}\\right),
       \\qquad t_0 = \\sqrt{{2H/g}} = {T0 * 1e3:.2f}\\ \\text{{ms}} , $$

    so the delay is, to first order, proportional to $k$. Below, each ball is dropped from
    rest {H:g} m above the top tread in air with density only (no viscosity), on the ODE
    path at estim's default tolerances (rtol 1e-8, atol 1e-9), and its first contact time
    is compared with the closed form: they agree to {DROP_REL_ERR.max():.1e} relative
    (largest over the balls). The last column repeats the stairs' first-bounce delay
    (still air, thrown): the same ordering, a shorter flight.
    """),
        md_table(["ball", "r (mm)", "m (g)", "k (1/m)", "v_t (m/s)", "drag/g at impact",
                  "delay, estim (ms)", "delay, closed form (ms)", "t0 k H/6 (ms)",
                  "rel. error of t", "stairs delay (ms)"], _rows),
        mo.md(f"""
    The ping-pong ball's $k$ is {K[_pp] / K[_bo]:.0f} times the bocce ball's (its 5 g
    against 920 g outweighs its smaller cross-section, {RADIUS[_pp] ** 2 / RADIUS[_bo] ** 2:.2f}
    of the bocce's), and so is its delay: {DROP_DELAY_MS[_pp]:.2f} ms against
    {DROP_DELAY_MS[_bo] * 1e3:.0f} µs after a {H:g} m drop. At impact drag is
    {_dec[_pp]:.1%} of gravity for the ping-pong ball and {_dec[_bo]:.2%} for the bocce
    ball. A regulation ping-pong ball (40 mm, 2.7 g; the scene's is 80 mm, 5 g) has
    $k$ = {K[_reg]:.3f} /m, {K[_reg] / K[_pp]:.2f} of the scene's, and its drop is
    {DROP_DELAY_MS[_reg]:.1f} ms late: drag matters for any ping-pong ball.
    """),
        mo.image(src=(OUT / "05_drop_delay.png").read_bytes()),
    ])
    return DROP_DELAY_MS, DROP_REL_ERR, DROP_T, DROP_T_EXACT, H, VT


@app.cell
def _(BALLS, T_END, estim, mo, seed_params, vacuum_scene):
    # estim's effect-size report: each force alone against the vacuum (or still air).
    report = estim.effect_sizes(vacuum_scene, seed_params, T_END, names=list(BALLS))
    _lin = [report.row("linear drag", b)["bounce1_ms"] / report.row("quadratic drag", b)["bounce1_ms"]
            for b in BALLS]

    def _dev(effect, ball):
        return report.row(effect, ball)["max_deviation_mm"]

    # The largest deviation each of spin and wind causes, against drag's (still air).
    _vs = ", ".join(f"{b} {_dev('Magnus', b) / _dev('still air', b):.2g}× / {_dev('wind', b) / _dev('still air', b):.2g}×"
                    for b in BALLS)
    mo.vstack([
        mo.md("""
    ## Each force alone: `estim.effect_sizes`

    `estim.effect_sizes(scene, params, t_end, ...)` (and the `estim effects` command) runs
    the balls in a vacuum and under each effect alone: still air (both drags), quadratic
    drag, linear (Stokes) drag, Magnus lift for 50 rad/s of backspin with drag off, and a
    3 m/s wind down the stairs against still air. The changes: final position, first and
    second bounce times, the largest distance between the two trajectories, bounces.
    """),
        mo.md(report.format_table(markdown=True)),
        mo.md(f"""
    Linear drag delays the first bounce {min(_lin):.1e} to {max(_lin):.1e} times as much as
    quadratic drag: air is not viscous enough at these sizes and speeds for Stokes' law to
    matter (MuJoCo's `viscosity` option asks for it, so estim has it). Spin and wind are
    another matter: the largest deviation they cause, as a multiple of drag's (Magnus /
    wind over still air), is {_vs}. So for a light ball that spins, or flies in a breeze,
    drag alone is not the whole story.
    """),
    ])
    return (report,)


@app.cell
def _(BALLS, COLOURS, Figure, MASS, OUT, RADIUS, RHO, T_END, TS, VX0, air_scene, balls, estim,
      impacts, md_table, mo, np, still):
    # Magnus: the ping-pong and bocce balls with backspin and topspin, in still air (drag
    # on), against the same balls without spin (the still-air run above).
    SPIN = 50.0  # rad/s, about 8 revolutions per second
    _pp, _bo = BALLS.index("pingpong"), BALLS.index("bocce")
    # Four runs in one batch of four: (ball, spin sign); backspin of a ball moving along +x
    # is omega along -y (omega x v points up).
    _runs = [("pingpong", 1), ("pingpong", -1), ("bocce", 1), ("bocce", -1)]
    _release = np.array([[-0.20, 0.0, 1.40 + RADIUS[BALLS.index(b)] + 0.25] for b, _ in _runs])
    _spin = np.array([[0.0, -s * SPIN, 0.0] for _, s in _runs])
    _p = balls(_release, np.tile([VX0, 0.0, 0.0], (4, 1)), _spin, names=[b for b, _ in _runs])
    spun = estim.simulate(air_scene, _p, T_END, ts=TS)
    _t_spun, _t_still = impacts(spun), impacts(still)
    _final_spun, _final_still = np.asarray(spun.final.position), np.asarray(still.final.position)
    MAGNUS = {}
    for _k, (_b, _s) in enumerate(_runs):
        _i = BALLS.index(_b)
        # First principles at release: |a_M| = rho pi r^2 r kappa |omega| |w| / (2 m),
        # kappa = min(1.5, 0.6 + 0.09 / S), S = r |omega| / |w|; lift along omega x w.
        _S = RADIUS[_i] * SPIN / VX0
        _kappa = min(1.5, 0.6 + 0.09 / _S)
        _a = RHO * np.pi * RADIUS[_i] ** 3 * _kappa * SPIN * VX0 / (2 * MASS[_i])
        _a_estim = np.asarray(estim.air_acceleration(
            estim.Air(density=RHO), RADIUS[_i], MASS[_i], 0.0, _spin[_k], np.array([VX0, 0.0, 0.0])))
        np.testing.assert_allclose(_a_estim, [0.0, 0.0, _s * _a], rtol=1e-12, atol=1e-15)
        MAGNUS[f"{_b} {'backspin' if _s > 0 else 'topspin'}"] = {
            "lift_at_release_over_g": float(_s * _a / 9.81),
            "bounce1_ms": float((_t_spun[_k][0] - _t_still[_i][0]) * 1e3),
            "final_dx_mm": float((_final_spun[_k, 0] - _final_still[_i, 0]) * 1e3),
            "bounces": [len(_t_still[_i]), len(_t_spun[_k])],
        }
    _m = MAGNUS
    # Backspin lifts (a later first bounce), topspin dips (an earlier one), and both far
    # more for the light ball.
    assert _m["pingpong backspin"]["bounce1_ms"] > 0 > _m["pingpong topspin"]["bounce1_ms"]
    assert _m["bocce backspin"]["bounce1_ms"] > 0 > _m["bocce topspin"]["bounce1_ms"]
    assert abs(_m["pingpong backspin"]["bounce1_ms"]) > 10 * abs(_m["bocce backspin"]["bounce1_ms"])

    _ts = np.asarray(TS)
    _fig = Figure(figsize=(9, 6.5), layout="tight")
    _axes = _fig.subplots(2, 1, sharex=True)
    for _ax, _b in zip(_axes, ("pingpong", "bocce"), strict=True):
        _i = BALLS.index(_b)
        _ax.plot(np.asarray(still.position)[_i, :, 0], np.asarray(still.position)[_i, :, 2], "-",
                 color=COLOURS.get(_b, "C0"), lw=1.6, label="no spin")
        for _k, (_bb, _s) in enumerate(_runs):
            if _bb == _b:
                _name = "backspin" if _s > 0 else "topspin"
                _ax.plot(np.asarray(spun.position)[_k, :, 0], np.asarray(spun.position)[_k, :, 2],
                         "--" if _s > 0 else ":", color="C2" if _s > 0 else "C3", lw=1.4,
                         label=f"{_name} {SPIN:g} rad/s: final x {_m[f'{_b} {_name}']['final_dx_mm']:+.0f} mm")
        _ax.set_ylabel("centre height z [m]")
        _ax.set_title(f"{_b} in still air, thrown at {VX0} m/s", fontsize=10)
        _ax.grid(alpha=0.3)
        _ax.legend(fontsize=8, loc="upper right")
    _axes[-1].set_xlabel("x [m] (down the stairs)")
    _fig.savefig(OUT / "05_magnus.png", dpi=110)

    _rows = [[k, f"{v['lift_at_release_over_g']:+.3f}", f"{v['bounce1_ms']:+.3f}",
              f"{v['final_dx_mm']:+.0f}", f"{v['bounces'][0]} → {v['bounces'][1]}"] for k, v in _m.items()]
    mo.vstack([
        mo.md(f"""
    ## Spin: backspin lifts, topspin dips

    A spinning ball feels the Magnus force,
    $a_M = \\frac{{\\rho \\pi r^3}}{{2m}}\\,\\kappa(S)\\,(\\omega \\times w)$ with spin ratio
    $S = r|\\omega|/|w|$ and $\\kappa = \\min(1.5,\\ 0.6 + 0.09/S)$. For a ball thrown
    along $+x$, backspin ($\\omega$ along $-y$) gives $\\omega \\times v$ upwards. Here
    {SPIN:g} rad/s (about 8 revolutions per second) of backspin and of topspin, in still
    air with drag, against the same throw without spin. The second column is the lift at
    release over $g$, computed by hand from the formula (and checked against
    `estim.air_acceleration`); the others are measured on the staircase.
    """),
        md_table(["ball, spin", "Magnus lift / g at release", "first bounce changes by (ms)",
                  "final x changes by (mm)", "bounces no spin → spin"], _rows),
        mo.md(f"""
    At release the ping-pong ball's backspin lift is
    {_m["pingpong backspin"]["lift_at_release_over_g"]:.1%} of its weight, the bocce
    ball's {_m["bocce backspin"]["lift_at_release_over_g"]:.2%}. Backspin holds the
    ping-pong ball up (first bounce {_m["pingpong backspin"]["bounce1_ms"]:+.1f} ms),
    topspin pulls it down ({_m["pingpong topspin"]["bounce1_ms"]:+.1f} ms); the bocce
    ball hardly notices ({_m["bocce backspin"]["bounce1_ms"] * 1e3:+.0f} /
    {_m["bocce topspin"]["bounce1_ms"] * 1e3:+.0f} µs). After the first bounce the story
    is less simple: $\\omega \\times w$ has a horizontal part, $\\omega_y w_z$, which pushes
    a rising ball backwards under backspin and forwards under topspin (and the other way
    round while it falls), and on a staircase small shifts decide which tread a hop lands
    on. Here the ping-pong ball ends {_m["pingpong backspin"]["final_dx_mm"]:+.0f} mm
    (backspin) and {_m["pingpong topspin"]["final_dx_mm"]:+.0f} mm (topspin) from where it
    ends without spin, the bocce ball {_m["bocce backspin"]["final_dx_mm"]:+.0f} /
    {_m["bocce topspin"]["final_dx_mm"]:+.0f} mm. (Spin is held constant, and the contact
    model has no spin transfer at impacts: a real ball's spin changes at every bounce.)
    """),
        mo.image(src=(OUT / "05_magnus.png").read_bytes()),
    ])
    return MAGNUS, SPIN


@app.cell
def _(AIR_BOUNCES, AIR_US, BALLS, DELAY_RATIO, DROP_DELAY_MS, DROP_REL_ERR, DROP_T,
      DROP_T_EXACT, H, K, MAGNUS, OUT, SPIN, START, STAIRS_DELAY_MS, STAIRS_SHORT_MM,
      TRACES_AFTER_AIR, TRACES_AFTER_VACUUM, TRACES_AT_START, VACUUM_BOUNCES, VACUUM_US, VT,
      estim_ode, json, mo, report, time):
    AIR_TRACES_TOTAL = estim_ode.TRACE_COUNT - TRACES_AT_START
    _summary = {
        "balls": list(BALLS),
        "vacuum_bounces": dict(zip(BALLS, VACUUM_BOUNCES, strict=True)),
        "air_bounces": dict(zip(BALLS, AIR_BOUNCES, strict=True)),
        "k_per_m": dict(zip(BALLS, K.tolist(), strict=True)),
        "terminal_speed": dict(zip(BALLS, VT.tolist(), strict=True)),
        "stairs_bounce1_delay_ms": STAIRS_DELAY_MS,
        "stairs_delay_ratio_pingpong_bocce": DELAY_RATIO,
        "stairs_final_x_short_mm": STAIRS_SHORT_MM,
        "drop_height": H,
        "drop_t": dict(zip(BALLS, DROP_T.tolist(), strict=True)),
        "drop_t_closed_form": dict(zip(BALLS, DROP_T_EXACT.tolist(), strict=True)),
        "drop_delay_ms": dict(zip(BALLS, DROP_DELAY_MS.tolist(), strict=True)),
        "drop_rel_error_max": float(DROP_REL_ERR.max()),
        "spin_rad_s": SPIN,
        "magnus": MAGNUS,
        "effect_report": report.to_json(),
        "ode_traces": {"after_vacuum": TRACES_AFTER_VACUUM, "after_first_air": TRACES_AFTER_AIR,
                       "total": AIR_TRACES_TOTAL},
        "vacuum_us": VACUUM_US,
        "air_us": AIR_US,
        "total_s": time.perf_counter() - START,
    }
    # One ODE program served every air run: still air, quadratic-only drop, spin and the
    # effect report.
    assert AIR_TRACES_TOTAL == 1, AIR_TRACES_TOTAL
    (OUT / "05_effects.json").write_text(json.dumps(_summary, indent=2) + "\n")
    print("05_effects:", json.dumps({k: v for k, v in _summary.items() if k != "effect_report"}))
    _pp, _bo = BALLS.index("pingpong"), BALLS.index("bocce")
    mo.md(f"""
    ## Summary

    Drag matters for a light, big ball and hardly for a heavy one: the ping-pong ball's
    drag constant is {K[_pp] / K[_bo]:.0f}× the bocce ball's, and so (to first order) is
    the delay drag puts on its first bounce ({STAIRS_DELAY_MS["pingpong"]:.2f} ms against
    {STAIRS_DELAY_MS["bocce"] * 1e3:.0f} µs on the stairs). The ODE path reproduces the
    closed-form drop with drag to {DROP_REL_ERR.max():.0e}. Spin of {SPIN:g} rad/s moves
    the ping-pong ball's first bounce by
    {MAGNUS["pingpong backspin"]["bounce1_ms"]:+.1f} / {MAGNUS["pingpong topspin"]["bounce1_ms"]:+.1f} ms
    (backspin / topspin). A scene without air never traces the ODE solver and costs
    {VACUUM_US:.0f} µs a call against {AIR_US / 1e3:.1f} ms in air; every air run here
    (still air, the drops, spin, the effect report) used {AIR_TRACES_TOTAL} compiled ODE
    program. What the ODE path's
    accuracy costs: `04_accuracy_cost.py`.
    """)
    return


if __name__ == "__main__":
    app.run()
