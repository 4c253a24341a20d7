"""The effect-size report (``estim.effect_sizes``, ``estim effects``).

Every run here has the shapes of ``estim effects`` on the seed scene (three balls, the
default sample times), so the module compiles one closed-form and one ODE program: the
effects differ only in the values of their air, never in structure.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import STAIRS_XML

import estim
from estim.app._cli import main

SEED = {"bocce": 0.55, "golf": 0.70, "pingpong": 0.85}
G = 9.81
EFFECTS = ["still air", "quadratic drag", "linear drag", "Magnus", "wind"]


@pytest.fixture(scope="module")
def seed_report():
    """``estim effects --json`` on the seed stairs (defaults: scene positions, vx0 1.15)."""
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["effects", "--scene", str(STAIRS_XML), "--json"]) == 0
    return json.loads(buf.getvalue())


def stack(rows):
    return jax.tree.map(lambda *x: jnp.stack(x), *rows)


def test_json_structure(seed_report):
    r = seed_report
    assert r["balls"] == list(SEED)
    assert [x["effect"] for x in r["effects"]] == EFFECTS  # stairs.xml has no air of its own
    assert r["params"]["e"] == list(SEED.values())
    assert r["settings"]["density"] == 1.204 and r["settings"]["viscosity"] == 1.81e-5
    assert r["settings"]["balls"]["pingpong"]["mass"] == 0.005
    keys = {"final_mm", "final_dx_mm", "bounce1_ms", "bounce2_ms", "max_deviation_mm",
            "bounces_baseline", "bounces"}
    for eff in r["effects"]:
        assert eff["baseline"] == ("still air" if eff["effect"] == "wind" else "vacuum")
        assert set(eff["balls"]) == set(SEED)
        for ball in eff["balls"].values():
            assert set(ball) == keys
            assert ball["max_deviation_mm"] >= ball["final_mm"] - 1e-9
    vacuum_bounces = {b: v["bounces_baseline"] for b, v in r["effects"][0]["balls"].items()}
    assert vacuum_bounces == {"bocce": 9, "golf": 6, "pingpong": 4}  # the closed-form seed


def test_drag_matters_for_pingpong_not_bocce(seed_report):
    """The 5 g ping-pong ball (r 40 mm) against the 0.92 kg bocce ball (r 80 mm): the
    drag deceleration rho C_D pi r^2 v^2 / (2 m) is ~46x larger for the ping-pong ball, and
    so is the delay of its first bounce."""
    quad = next(x for x in seed_report["effects"] if x["effect"] == "quadratic drag")["balls"]
    ratio = quad["pingpong"]["bounce1_ms"] / quad["bocce"]["bounce1_ms"]
    assert 30 < ratio < 60, ratio
    assert quad["bocce"]["bounce1_ms"] < 0.1 < 3 < quad["pingpong"]["bounce1_ms"]
    assert quad["pingpong"]["final_mm"] > 5 * quad["bocce"]["final_mm"]
    # Linear (Stokes) drag is negligible in air next to quadratic drag.
    lin = next(x for x in seed_report["effects"] if x["effect"] == "linear drag")["balls"]
    for ball in SEED:
        assert abs(lin[ball]["bounce1_ms"]) < 0.01 * abs(quad[ball]["bounce1_ms"])


def test_vertical_drop_matches_closed_form(stairs):
    """Dropped from rest h above step 1, with quadratic drag the first contact comes at
    t = (vt/g) arccosh(exp(g h / vt^2)), vt = sqrt(2 m g / (rho C_D pi r^2)), instead of
    sqrt(2 h / g): the report's first-bounce delay is the difference."""
    h = 0.9
    params = stack([estim.Params.for_ball(stairs, n, e=SEED[n], mu_t=0.98,
                                          position=(0.0, stairs.ball(n).position[1], 1.40 + stairs.ball(n).radius + h))
                    for n in SEED])
    report = estim.effect_sizes(stairs, params, 2.3, names=list(SEED))
    r, m = np.asarray(params.radius), np.asarray(params.mass)
    vt = np.sqrt(2 * m * G / (1.204 * 0.47 * np.pi * r**2))
    delay = vt / G * np.arccosh(np.exp(G * h / vt**2)) - np.sqrt(2 * h / G)
    got = np.array([report.row("quadratic drag", n)["bounce1_ms"] for n in SEED]) * 1e-3
    np.testing.assert_allclose(got, delay, rtol=1e-6, atol=1e-10)


def test_zero_density_and_viscosity_give_zero_effects(stairs):
    params = stack([estim.Params.for_ball(stairs, n, e=SEED[n], mu_t=0.98, velocity=(1.15, 0.0, 0.0))
                    for n in SEED])
    report = estim.effect_sizes(stairs, params, 2.3, names=list(SEED), density=0.0, viscosity=0.0)
    for row in report.rows:
        # On the ODE path without force the flights are parabolas, which every Runge-Kutta
        # method integrates exactly: the same trajectories as the closed form, to rounding.
        assert row["max_deviation_mm"] < 1e-6, row
        assert abs(row["bounce1_ms"]) < 1e-8 and abs(row["bounce2_ms"]) < 1e-8, row
        assert row["bounces"] == row["bounces_baseline"]
    text = report.format_table()
    assert text.splitlines()[0].split()[:2] == ["effect", "ball"]
    assert len(text.splitlines()) == 1 + len(EFFECTS) * 3


@pytest.mark.parametrize("args, words", [
    (["--ball", "nope"], "unknown ball"),
    (["--e", "1.5"], "--e must lie in [0, 1]"),
    (["--t-end", "0"], "--t-end must be > 0"),
    (["--density", "-1"], "--density must be >= 0"),
])
def test_bad_input_exits_2(capsys, args, words):
    assert main(["effects", "--scene", str(STAIRS_XML), *args]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err


def test_non_finite_option_is_an_argparse_error(capsys):
    with pytest.raises(SystemExit) as info:
        main(["effects", "--spin", "nan"])
    assert info.value.code == 2
    assert "finite" in capsys.readouterr().err


def test_docs_table_is_what_the_report_measures(seed_report):
    """docs/pages/effects.md quotes the seed report's table: every number there must be
    what ``estim effects`` measures now (to the 3 significant digits printed)."""
    from pathlib import Path

    page = (Path(__file__).resolve().parent.parent / "docs" / "pages" / "effects.md").read_text()
    body = page.split("<!-- effects-table:start", 1)[1].split("<!-- effects-table:end -->", 1)[0]
    rows = [[c.strip() for c in line.strip().strip("|").split("|")]
            for line in body.splitlines() if line.startswith("| ") and not line.startswith("| effect")]
    effects = {x["effect"]: x["balls"] for x in seed_report["effects"]}
    assert len(rows) == sum(len(b) for b in effects.values())
    keys = ["final_mm", "final_dx_mm", "bounce1_ms", "bounce2_ms", "max_deviation_mm"]
    for effect, ball, *cells, bounces in rows:
        got = effects[effect][ball]
        for key, cell in zip(keys, cells, strict=True):
            if cell == "-":
                assert got[key] is None, (effect, ball, key)
            else:
                np.testing.assert_allclose(float(cell), got[key], rtol=6e-3, err_msg=f"{effect} {ball} {key}")
        assert bounces == f"{got['bounces_baseline']} -> {got['bounces']}", (effect, ball)
