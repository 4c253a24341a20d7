"""What accuracy costs: the closed form against the ODE path, and the ODE path's settings.

Run headless with ``python notebooks/04_accuracy_cost.py`` (figures go to
``$ESTIM_NOTEBOOK_OUT``, default ``notebooks/out/``), or open it with
``marimo edit notebooks/04_accuracy_cost.py``. The notebook measures a small
work-precision study on this machine (``ESTIM_NOTEBOOK_FAST=1``: one solver, Tsit5, which
compiles six programs; otherwise Tsit5, Dopri5 and Dopri8) and, where the full study of
``estim bench accuracy`` is committed (``docs/pages/accuracy.json``, written by
``docs/scripts/accuracy.py``), shows it too.
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
    from matplotlib.figure import Figure

    # The study itself is estim's `estim bench accuracy` (estim.app._bench, not exported as
    # public API): the same code, so these numbers are comparable with the committed ones.
    from estim.app import _bench as bench

    START = time.perf_counter()

    def sci(x):
        """An error in short scientific notation (0 stays 0)."""
        return "0" if x == 0 else f"{x:.1e}"

    def choose(rows, targets, slack_rows=()):
        """Per target final-position error, the cheapest setting (fewest steps; ties: the
        loosest) of each family that meets it with the reference's event counts. Families:
        each solver with rtol varied (slack 1e-6 m), and Tsit5 at the default rtol with the
        contact slack varied. Returns ``({target: {family: pick}}, table rows)``."""
        families = {f"{s}, rtol varied": [(r, f"rtol {r['rtol']:.0e}", r["rtol"])
                                          for r in rows if r["solver"] == s]
                    for s in dict.fromkeys(r["solver"] for r in rows)}
        if slack_rows:
            families["Tsit5 at the default rtol, slack varied"] = [
                (r, f"slack {r['contact_slack']:.0e} m", r["contact_slack"])
                for r in slack_rows if r["max_steps"] == 2048]
        picks, table = {}, []
        for target in targets:
            key = f"{target:.0e}"
            picks[key] = {}
            for family, cands in families.items():
                ok = [c for c in cands if c[0]["events_match"] and c[0]["final_position_error"] <= target]
                if not ok:
                    table.append([key, family, "none measured", "-", "-", "-"])
                    continue
                r, label, _ = min(ok, key=lambda c: (c[0]["steps"], -c[2]))
                picks[key][family] = {"setting": label, **{k: r[k] for k in (
                    "rtol", "final_position_error", "steps", "forward_ms")}}
                table.append([key, family, label, sci(r["final_position_error"]), r["steps"],
                              f"{r['forward_ms']:.3g}"])
        return picks, table
    return FAST, Figure, OUT, ROOT, START, bench, choose, json, md_table, mo, np, sci, time


@app.cell
def _(mo):
    mo.md(r"""
    # What accuracy costs

    estim has two ways to move a ball between contacts. In a scene without air every
    flight is a parabola: estim solves it **in closed form**, and the contact times are
    roots of quadratics, exact to rounding. In a scene with air (drag, Magnus; see
    `05_effects.py`) there is no closed form: estim integrates the flight with an explicit
    Runge-Kutta method from diffrax (**the ODE path**), under error control (`rtol`,
    `atol`) and a *contact slack* that keeps it from stepping over a contact. This
    notebook measures what each costs and what it buys, on the seed scene: three balls
    (bocce, golf, ping-pong) thrown down the five-step staircase for 2.3 s.

    Every number below is measured in this run, by the code of `estim bench accuracy`
    (`estim.app._bench.run_accuracy`): for each setting, the errors of the event times, of the
    final positions (three balls) and of the golf ball's gradient
    $\partial x_\text{final} / \partial(e, \mu_t, v_{x0})$ (`jax.grad`) against a
    reference, the median time of a forward call (three balls) and of a gradient, and the
    accepted steps. Throughout, `atol = rtol / 10`.
    """)
    return


@app.cell
def _(FAST, OUT, bench, json, mo, time):
    # The live study: small enough to compile quickly. The tolerances and the contact
    # slack are traced values, so extra rtols and slacks cost run time, not compiles; each
    # solver costs four compiles (forward and gradient, vacuum and air), the closed form two.
    if FAST:
        LIVE_SOLVERS, LIVE_REFERENCE, LIVE_REPEATS = ("Tsit5",), ("Tsit5", 1e-12), 3
    else:
        LIVE_SOLVERS, LIVE_REFERENCE, LIVE_REPEATS = ("Tsit5", "Dopri5", "Dopri8"), ("Dopri8", 1e-13), 5
    LIVE_RTOLS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11)
    LIVE_SLACKS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7)
    LOG = []

    def _say(msg):
        LOG.append(msg)
        print("  " + msg, flush=True)

    _t = time.perf_counter()
    live = bench.run_accuracy(quick=True, repeats=LIVE_REPEATS, solvers=LIVE_SOLVERS, rtols=LIVE_RTOLS,
                              reference=LIVE_REFERENCE, slacks=LIVE_SLACKS, say=_say)
    LIVE_S = time.perf_counter() - _t
    (OUT / "04_accuracy_live.json").write_text(json.dumps(live, indent=1) + "\n")
    _compile = sum(float(m.rsplit(": ", 1)[1].rstrip(" s")) for m in LOG if m.endswith(" s"))
    mo.md(f"""
    ## The live study

    {", ".join(LIVE_SOLVERS)} at rtol {LIVE_RTOLS[0]:.0e} to {LIVE_RTOLS[-1]:.0e}, contact
    slacks {", ".join(f"{s:.0e}" for s in LIVE_SLACKS)} m, reference
    {LIVE_REFERENCE[0]} at rtol {LIVE_REFERENCE[1]:.0e}, times the median of
    {LIVE_REPEATS} rounds: {LIVE_S:.0f} s in all here, of which {_compile:.0f} s went into the
    first call of each setting (mostly JAX compiling; with the compilation cache warm, a
    rerun skips most of it). {live["machine"]["cpu_count"]} CPU cores, jax
    {live["machine"]["jax"]} ({live["machine"]["backend"]}), load average
    {live["machine"]["load_average"][0]:.1f} at the end: timings on a shared machine move
    by tens of percent, ratios within one run much less.
    """)
    return LIVE_REFERENCE, LIVE_RTOLS, LIVE_S, LIVE_SLACKS, LIVE_SOLVERS, live


@app.cell
def _(live, md_table, mo, np, sci):
    # (a) Without air: the closed form is exact; the ODE path forced on gives the same answer.
    _rows = live["vacuum"]["rows"]
    closed = _rows[0]
    assert closed["solver"] == "closed form" and closed["events"] == [9, 6, 4]
    _ode = [r for r in _rows if r["rtol"] is not None]
    VAC_MAX_ERROR = max(max(r["event_time_error"], r["final_position_error"], r["gradient_error"]) for r in _ode)
    # Every Runge-Kutta method integrates a parabola exactly: the errors are rounding.
    assert VAC_MAX_ERROR < 1e-9, VAC_MAX_ERROR
    assert all(r["events_match"] and r["complete"] for r in _ode)
    # Every ODE setting here does the same work (same steps), so the spread of their
    # times is this run's timing noise; the median is the estimate.
    VAC_FORWARD_RATIO = [float(np.percentile([r["forward_ratio"] for r in _ode], q)) for q in (0, 50, 100)]
    VAC_GRADIENT_RATIO = [float(np.percentile([r["gradient_ratio"] for r in _ode], q)) for q in (0, 50, 100)]
    _steps = sorted({r["steps"] for r in _ode})
    if len(_steps) == 1:
        _steps_note = (f"Its local error estimate is zero, so the tolerance changes nothing: every setting "
                       f"takes {_steps[0]} steps for the three balls' {sum(closed['events'])} events (steps "
                       "end at contacts).")
    else:
        _steps_note = f"The step counts over the settings: {', '.join(map(str, _steps))}."
    _table = [[r["solver"], "-" if r["rtol"] is None else f"{r['rtol']:.0e}",
               sci(r["final_position_error"]), sci(r["gradient_error"]), f"{r['forward_ms']:.3g}",
               f"{r['forward_ratio']:.3g}", f"{r['gradient_ms']:.3g}", f"{r['gradient_ratio']:.3g}",
               "-" if r["steps"] is None else r["steps"]] for r in _rows]
    mo.vstack([
        mo.md(f"""
    ## (a) Without air the closed form is exact, and {VAC_FORWARD_RATIO[1]:.0f}× cheaper

    The seed scene in a vacuum (`data/scenes/stairs.xml`): the closed form against the ODE
    path, forced on with `estim.simulate(..., solver=...)`. Both give the same answer: the
    ODE path's largest error over every setting is {sci(VAC_MAX_ERROR)} (event times,
    final positions, gradient), rounding, because every Runge-Kutta method of order two or
    more integrates a parabola exactly. {_steps_note} What
    differs is the cost: a forward call on the ODE path takes
    **{VAC_FORWARD_RATIO[1]:.0f}×** the closed form's time (median over the settings;
    {VAC_FORWARD_RATIO[0]:.0f} to {VAC_FORWARD_RATIO[2]:.0f}× between them, which do the
    same work, so that spread is this machine's timing noise), a gradient
    **{VAC_GRADIENT_RATIO[1]:.0f}×** ({VAC_GRADIENT_RATIO[0]:.0f} to
    {VAC_GRADIENT_RATIO[2]:.0f}×).
    """),
        md_table(["solver", "rtol", "final position error (m)", "gradient error", "forward (ms)",
                  "× closed form", "gradient (ms)", "× closed form", "steps"], _table),
        mo.md("""
    So estim never uses the ODE path unless the scene has air: the closed form is both the
    exact answer and the fast one.
    """),
    ])
    return VAC_FORWARD_RATIO, VAC_GRADIENT_RATIO, VAC_MAX_ERROR, closed


@app.cell
def _(Figure, LIVE_REFERENCE, LIVE_SOLVERS, OUT, bench, live, md_table, mo, np, sci):
    # (b) In still air: error against time, per solver and rtol.
    _air = live["air"]
    _ref = _air["reference"]
    bench.plot_accuracy(live, str(OUT / "04_accuracy_live.png"))
    AIR_ROWS = _air["rows"]
    DEFAULT = next(r for r in AIR_ROWS if r["solver"] == "Tsit5" and r["rtol"] == bench.DEFAULT_SETTING["rtol"])
    assert DEFAULT["forward_ratio"] == 1.0 and DEFAULT["complete"]
    # Step counts of Tsit5 against rtol (loosest first).
    _tsit = sorted((r for r in AIR_ROWS if r["solver"] == "Tsit5"), key=lambda r: -r["rtol"])
    TSIT5_STEPS = {f"{r['rtol']:.0e}": r["steps"] for r in _tsit}
    # Where the step count stops falling as rtol loosens: the tightest rtol whose step count
    # is within 10% of the fewest (the steps around the contacts, which rtol does not set).
    _floor = min(r["steps"] for r in _tsit)
    PLATEAU_RTOL = min(r["rtol"] for r in _tsit if r["steps"] <= 1.1 * _floor)

    _fig = Figure(figsize=(10, 4.2), layout="tight")
    _a1, _a2 = _fig.subplots(1, 2)
    for _i, _s in enumerate(LIVE_SOLVERS):
        _r = sorted((r for r in AIR_ROWS if r["solver"] == _s), key=lambda r: r["rtol"])
        _rt = [r["rtol"] for r in _r]
        _a1.loglog(_rt, [r["steps"] for r in _r], "o-", color=f"C{_i}", ms=4, label=_s)
        _a2.loglog(_rt, [max(r["final_position_error"], 1e-17) for r in _r], "o-", color=f"C{_i}", ms=4,
                   label=f"{_s}: final position")
        _a2.loglog(_rt, [max(r["event_time_error"], 1e-17) for r in _r], "s:", color=f"C{_i}", ms=3,
                   label=f"{_s}: event times (s)")
    _a1.axvline(bench.DEFAULT_SETTING["rtol"], color="0.5", lw=0.8, ls="--")
    _a1.set_xlabel("rtol  (atol = rtol / 10)")
    _a1.set_ylabel("accepted steps, three balls")
    _a1.set_title("Steps stop falling at loose rtol (contact slack 1 µm)", fontsize=9)
    _a2.axvline(bench.DEFAULT_SETTING["rtol"], color="0.5", lw=0.8, ls="--")
    _a2.loglog(_rt, _rt, color="0.7", lw=0.8, label="error = rtol")
    _a2.set_xlabel(f"rtol  (dashed: estim's default {bench.DEFAULT_SETTING['rtol']:.0e})")
    _a2.set_ylabel(f"error against {LIVE_REFERENCE[0]} at rtol {LIVE_REFERENCE[1]:.0e}")
    _a2.set_title("Error in still air", fontsize=9)
    for _ax in (_a1, _a2):
        _ax.grid(alpha=0.3, which="both")
        _ax.legend(fontsize=7)
    _fig.savefig(OUT / "04_steps_error.png", dpi=110)

    _table = [[r["solver"], f"{r['rtol']:.0e}", sci(r["event_time_error"]) + ("" if r["events_match"] else " †"),
               sci(r["final_position_error"]), sci(r["gradient_error"]), f"{r['forward_ms']:.3g}",
               f"{r['forward_ratio']:.2f}", f"{r['gradient_ms']:.3g}", r["steps"]] for r in AIR_ROWS]
    _tightest = min(AIR_ROWS, key=lambda r: (r["final_position_error"], r["forward_ms"]))
    if _tightest["solver"] == _ref["solver"]:
        # Against a reference of the same method, small errors show consistency more than
        # accuracy: the tightest run of another method is the independent check.
        _other = min((r for r in AIR_ROWS if r["solver"] != _ref["solver"]),
                     key=lambda r: r["final_position_error"], default=None)
        _ref_note = ("" if _other is None else
                     f" (That is measured against {_ref['solver']} itself, so it shows consistency more than "
                     f"accuracy; the independent check is {_other['solver']} at rtol {_other['rtol']:.0e}, "
                     f"{sci(_other['final_position_error'])} m from the reference.)")
    else:
        _ref_note = ""
    # Settings with (nearly) the same steps do the same work: the spread of their times is noise.
    _same = [r["forward_ms"] for r in _tsit if r["steps"] <= 1.1 * _floor]
    NOISE = max(_same) / min(_same) - 1
    mo.vstack([
        mo.md(f"""
    ## (b) In still air: error against time

    The same balls in `data/scenes/stairs_air.xml` (density 1.204 kg/m³, viscosity
    1.81e-5 Pa s), where the ODE path is the only path. There is no exact answer, so the
    reference is {_ref["solver"]} at rtol {_ref["rtol"]:.0e} ({_ref["steps"]} steps,
    forward {_ref["forward_ms"]:.3g} ms). *× default*: forward time over estim's default,
    Tsit5 at rtol {bench.DEFAULT_SETTING["rtol"]:.0e}, in the same run.
    """),
        md_table(["solver", "rtol", "event times (s)", "final position (m)", "gradient", "forward (ms)",
                  "× default", "gradient (ms)", "steps"], _table),
        mo.md(f"""
    (†: the event counts differ from the reference's.) The two figures below: the study's
    work-precision plot (`estim bench accuracy`'s own, error against time; zero errors
    drawn at 1e-17) and, for the still air, steps and errors against rtol.

    **Away from solids rtol sets the step; near them the contact slack does.** A step
    whose path provably stays clear of every solid (a rigorous bound on how far the air
    takes the ball from the parabola its contacts are predicted on) is as long as the error
    control allows; a step near a solid is accepted only if the integrated path stays
    within `contact_slack` (1 µm by default) of that parabola, so that no contact deeper
    than that is skipped. Tsit5's step count falls as rtol loosens until rtol
    {PLATEAU_RTOL:.0e}; from there to {_tsit[0]["rtol"]:.0e} it stays within 10% of
    {_floor} steps, those around the contacts ({", ".join(f"{k}: {v}" for k, v in TSIT5_STEPS.items())}).
    Looser than that buys no speed; and the errors there are not the rtol's either but
    what the steps left leave: {sci(_tsit[0]["final_position_error"])} m in the
    final positions at rtol {_tsit[0]["rtol"]:.0e}. The most accurate setting measured here
    is {_tightest["solver"]} at rtol {_tightest["rtol"]:.0e}
    ({sci(_tightest["final_position_error"])} m, {_tightest["forward_ratio"]:.2f}× the
    default's time).{_ref_note} Note the times: the {len(_same)} Tsit5 settings that take
    {_floor} to {int(1.1 * _floor)} steps do nearly the same work, yet their forward times spread from {min(_same):.3g} to
    {max(_same):.3g} ms ({NOISE:.0%}): that is the timing noise of this run, so read the
    times as ±{NOISE / 2:.0%} and the steps as exact.
    """),
        mo.image(src=(OUT / "04_accuracy_live.png").read_bytes()),
        mo.image(src=(OUT / "04_steps_error.png").read_bytes()),
    ])
    return AIR_ROWS, DEFAULT, NOISE, PLATEAU_RTOL, TSIT5_STEPS


@app.cell
def _(AIR_ROWS, DEFAULT, NOISE, PLATEAU_RTOL, choose, live, md_table, mo, np, sci):
    # (c) Around the default: the contact slack at Tsit5 and the default rtol; then how to choose.
    SLACK_ROWS = live["air"]["settings_rows"]
    _table = [[f"{r['contact_slack']:.0e}", r["steps"], sci(r["event_time_error"]) + ("" if r["events_match"] else " †"),
               sci(r["final_position_error"]), sci(r["gradient_error"]), f"{r['forward_ms']:.3g}",
               f"{r['forward_ratio']:.2f}", "yes" if r["complete"] else "no"] for r in SLACK_ROWS]
    _by = {r["contact_slack"]: r for r in SLACK_ROWS}
    _loose, _tight = max(_by), min(_by)
    SLACK_STEPS = {f"{k:.0e}": v["steps"] for k, v in sorted(_by.items(), reverse=True)}
    SLACK_ERRORS = {f"{k:.0e}": v["final_position_error"] for k, v in sorted(_by.items(), reverse=True)}
    # A looser slack allows longer steps: the step count never grows as the slack loosens.
    _s = [v["steps"] for _, v in sorted(_by.items())]
    assert all(a >= b for a, b in zip(_s, _s[1:], strict=False)), SLACK_STEPS
    _err_ratio = _by[_loose]["final_position_error"] / max(_by[_tight]["final_position_error"], 1e-300)

    # What a step costs: a straight line through (steps, forward time) of every setting.
    _all = [r for r in AIR_ROWS if r["solver"] == "Tsit5"] + [r for r in SLACK_ROWS if r["contact_slack"] != 1e-6]
    _n = np.array([r["steps"] for r in _all], dtype=float)
    _ms = np.array([r["forward_ms"] for r in _all])
    PER_STEP_MS, FIXED_MS = (float(x) for x in np.polyfit(_n, _ms, 1))
    _span = PER_STEP_MS * (_n.max() - _n.min()) / _ms.mean()
    if abs(_span) < NOISE:
        _cost_note = (f"That is within this run's timing noise (±{NOISE / 2:.0%}): here most of a call's "
                      "time is fixed cost, not steps, so a tighter setting costs far less than its step "
                      "count suggests, and a looser one saves little.")
    else:
        _share = FIXED_MS / (FIXED_MS + PER_STEP_MS * DEFAULT["steps"])
        _cost_note = (f"Steps cost time, but at the default's {DEFAULT['steps']} steps the fixed part is "
                      f"{_share:.0%} of a call, so halving the steps saves far less than half the time."
                      if _share > 0.5 else "So the steps are a fair measure of the cost here.")
    CHOICES, _choice_rows = choose(AIR_ROWS, (1e-6, 1e-9, 1e-11), SLACK_ROWS)
    # Steps compare settings of one solver only: the cheapest Tsit5 setting per target.
    _best = {k: min(((f, x) for f, x in v.items() if f.startswith("Tsit5")), key=lambda kv: kv[1]["steps"])
             for k, v in CHOICES.items() if any(f.startswith("Tsit5") for f in v)}
    if any("slack" in fam for fam, _ in _best.values()):
        _slack_note = ("Where the cheapest setting is a looser slack, that is because the slack, not "
                       "rtol, bounds the steps near contacts: loosening it cuts steps where loosening "
                       "rtol does not.")
    else:
        _slack_note = "No looser slack was the cheapest way to any target here."
    _budget = ("is never reached here" if all(r["complete"] for r in SLACK_ROWS)
               else "is reached where the table says *no*")
    if DEFAULT["rtol"] >= PLATEAU_RTOL:
        _default_steps = (f"At the default the step is still the slack's ({DEFAULT['steps']} steps, as at "
                          "every looser rtol measured), so the accuracy of the default rtol costs nothing over "
                          "any looser tolerance: loosening rtol would buy no speed, and tightening the "
                          "slack, not rtol, is what makes the default more accurate.")
    else:
        _default_steps = (f"The default takes {DEFAULT['steps']} steps; from rtol {PLATEAU_RTOL:.0e} up "
                          "only the steps near contacts, which the slack bounds, are left.")
    mo.vstack([
        mo.md(f"""
    ## (c) The contact slack, and how to choose a setting

    Tsit5 at rtol {DEFAULT["rtol"]:.0e} with the contact slack varied (the step budget, `max_steps` 2048,
    {_budget}):
    """),
        md_table(["contact_slack (m)", "steps", "event times (s)", "final position (m)", "gradient",
                  "forward (ms)", "× default", "complete"], _table),
        mo.md(f"""
    The slack sets the step count at the default tolerance: from {_tight:.0e} m to
    {_loose:.0e} m the three balls take {" → ".join(str(v) for v in reversed(list(SLACK_STEPS.values())))}
    steps, and the final positions move from {sci(_by[_tight]["final_position_error"])} m to
    {sci(_by[_loose]["final_position_error"])} m from the reference ({_err_ratio:.2g}×).

    What does a step cost? A straight line through the forward times of all {len(_all)}
    still-air Tsit5 settings against their steps ({_n.min():.0f} to {_n.max():.0f}) gives
    {FIXED_MS:.0f} ms + {PER_STEP_MS * 1e3:.0f} µs per step: from the fewest steps to the
    most adds {_span:.0%} to a call. {_cost_note}

    **How to choose.** Decide how large an error you can accept, and take the cheapest
    setting that meets it: with one solver, the fewest steps (the steps are exact, the
    times noisy); between solvers compare times, since a method of higher order takes
    fewer, dearer steps. The cheapest measured setting per target, varying rtol or the
    slack (still air, final positions):
    """),
        md_table(["final position error ≤ (m)", "varying", "setting", "its error (m)", "steps",
                  "forward (ms)"], _choice_rows),
        mo.md(f"""
    With Tsit5: {" ".join(f"within {k} m, {v[1]['setting']} ({v[0]}), {v[1]['steps']} steps;" for k, v in _best.items())[:-1]}.
    {_slack_note} A looser slack is also a deeper contact that may go
    unseen (a ball grazing a tread's edge by less than the slack flies on as if it had
    missed it), so loosen it only for a scene without such near-misses, and check the
    event counts against a tight run.

    **estim's default** is Tsit5 at rtol {DEFAULT["rtol"]:.0e}, atol {DEFAULT["atol"]:.0e}, contact slack 1e-6 m. Here it
    puts the final positions within {sci(DEFAULT["final_position_error"])} m and the event
    times within {sci(DEFAULT["event_time_error"])} s of the reference, and the gradient
    within {sci(DEFAULT["gradient_error"])}: far below anything a camera measures (a pixel
    is a millimetre or so), so fits see no solver error, at {DEFAULT["forward_ms"]:.3g} ms
    a forward call and {DEFAULT["gradient_ms"]:.3g} ms a gradient here. The contact slack
    of 1 µm keeps any contact deeper than a micrometre from being skipped whatever the
    tolerances. {_default_steps}
    """),
    ])
    return CHOICES, FIXED_MS, PER_STEP_MS, SLACK_ERRORS, SLACK_STEPS


@app.cell
def _(OUT, ROOT, bench, choose, json, md_table, mo, np, sci):
    # The full study, committed with the docs (docs/scripts/accuracy.py writes it); it may not
    # exist yet in a checkout, or come from another version of the study.
    COMMITTED_PATH = ROOT / "docs" / "pages" / "accuracy.json"
    COMMITTED = {"present": COMMITTED_PATH.is_file()}
    _items = [mo.md("## The full study, as committed")]
    if COMMITTED["present"]:
        try:
            _full = json.loads(COMMITTED_PATH.read_text())
            _text = bench.format_accuracy(_full)
            bench.plot_accuracy(_full, str(OUT / "04_accuracy_committed.png"))
            _vac = [r for r in _full["vacuum"]["rows"] if r["rtol"] is not None]
            _air = _full["air"]["rows"]
            _d = next(r for r in _air if r["solver"] == "Tsit5" and r["rtol"] == bench.DEFAULT_SETTING["rtol"])
            COMMITTED.update({
                "solvers": sorted({r["solver"] for r in _air}),
                "vacuum_forward_ratio": [float(np.percentile([r["forward_ratio"] for r in _vac], q))
                                         for q in (0, 50, 100)],
                "default_final_position_error": _d["final_position_error"],
                "machine": _full.get("machine", {}),
            })
            COMMITTED["choices"], _choice_rows = choose(_air, (1e-6, 1e-9, 1e-11),
                                                        _full["air"].get("settings_rows", []))
            _m = COMMITTED["machine"]
            _items += [
                mo.md(f"""
    `docs/pages/accuracy.json`, measured with `estim bench accuracy` (solvers
    {", ".join(COMMITTED["solvers"])}, {_full["repeats"]} rounds, on
    {_m.get("cpu_count", "?")} CPU cores, jax {_m.get("jax", "?")}), shown with the
    study's own table and plot. Without air the ODE path costs about
    {COMMITTED["vacuum_forward_ratio"][1]:.0f}× the closed form there (median;
    {COMMITTED["vacuum_forward_ratio"][0]:.0f} to {COMMITTED["vacuum_forward_ratio"][2]:.0f}×); in still air estim's default is within
    {sci(_d["final_position_error"])} m of the reference in final position. Its timings
    are the committing machine's; the live study above is this one's.
    """),
                mo.md(_text),
                mo.image(src=(OUT / "04_accuracy_committed.png").read_bytes()),
                mo.md("How to choose, from the full study (as in (c): the cheapest setting per "
                      "target and family):"),
                md_table(["final position error ≤ (m)", "varying", "setting", "its error (m)", "steps",
                          "forward (ms)"], _choice_rows),
            ]
        except (KeyError, TypeError, ValueError, StopIteration) as _err:
            COMMITTED["error"] = f"{type(_err).__name__}: {_err}"
            print(f"Committed study unreadable: {COMMITTED['error']}")
            _items.append(mo.md(f"""
    `docs/pages/accuracy.json` exists but this notebook cannot read it
    ({COMMITTED["error"]}): it was written by another version of the study. Rerun
    `python docs/scripts/accuracy.py` to regenerate it.
    """))
    else:
        print("Committed study not found: docs/pages/accuracy.json (run `python docs/scripts/accuracy.py`)")
        _items.append(mo.md("""
    `docs/pages/accuracy.json` is not in this checkout yet. `python docs/scripts/accuracy.py`
    measures the full study of `estim bench accuracy` (Tsit5, Dopri5 and Dopri8 at rtol 1e-3
    to 1e-12 against Dopri8 at 1e-13, the contact slack and `max_steps` around the default;
    several minutes on a 2-core machine) and writes it, with its table and plot, into `docs/pages/`; this
    section then shows it.
    """))
    mo.vstack(_items)
    return (COMMITTED,)


@app.cell
def _(CHOICES, COMMITTED, DEFAULT, FIXED_MS, LIVE_REFERENCE, LIVE_S, LIVE_SOLVERS, NOISE, OUT,
      PER_STEP_MS, PLATEAU_RTOL,
      SLACK_ERRORS, SLACK_STEPS, START, TSIT5_STEPS, VAC_FORWARD_RATIO, VAC_GRADIENT_RATIO, VAC_MAX_ERROR,
      closed, json, live, mo, time):
    _summary = {
        "solvers": list(LIVE_SOLVERS),
        "reference": list(LIVE_REFERENCE),
        "vacuum_events": closed["events"],
        "vacuum_max_error": VAC_MAX_ERROR,
        "vacuum_forward_ratio": VAC_FORWARD_RATIO,
        "vacuum_gradient_ratio": VAC_GRADIENT_RATIO,
        "closed_form_gradient": live["vacuum"]["closed_form_gradient"],
        "air_default": {k: DEFAULT[k] for k in ("event_time_error", "final_position_error", "gradient_error",
                                                "forward_ms", "gradient_ms", "steps", "events", "gradient")},
        "air_reference": live["air"]["reference"],
        "tsit5_steps_by_rtol": TSIT5_STEPS,
        "steps_plateau_rtol": PLATEAU_RTOL,
        "slack_steps": SLACK_STEPS,
        "slack_final_position_error": SLACK_ERRORS,
        "choices": CHOICES,
        "timing_noise": NOISE,
        "forward_ms_fit": {"fixed_ms": FIXED_MS, "per_step_ms": PER_STEP_MS},
        "committed": COMMITTED,
        "live_s": LIVE_S,
        "total_s": time.perf_counter() - START,
    }
    (OUT / "04_accuracy_cost.json").write_text(json.dumps(_summary, indent=2) + "\n")
    print("04_accuracy_cost:", json.dumps({k: v for k, v in _summary.items() if k != "committed"}))
    mo.md(f"""
    ## Summary

    Without air the closed form is exact and the ODE path, which agrees with it to
    {VAC_MAX_ERROR:.0e}, costs about {VAC_FORWARD_RATIO[1]:.0f}× as much per forward
    call: estim uses it only when the scene has air. In still air, estim's default (Tsit5,
    rtol {DEFAULT["rtol"]:.0e}, atol {DEFAULT["atol"]:.0e}, contact slack 1 µm) is within
    {DEFAULT["final_position_error"]:.0e} m of a tight reference, and loosening rtol past
    {PLATEAU_RTOL:.0e} saves no steps, because the steps left are those near contacts,
    which the contact slack bounds. The
    forces themselves, and when a scene needs them: `05_effects.py`.
    """)
    return


if __name__ == "__main__":
    app.run()
