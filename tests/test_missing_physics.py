"""Physics the scene lacks (``estim.fitting._missing_physics``): air drag against an
independent closed form, and the advice for light and heavy balls.

Every call here runs one ball with the default sample times on the drop scene, so the
module compiles one closed-form and one ODE program (a few seconds, in the first test).
"""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import ROOT

import estim
from estim.fitting import _registry as registry
from estim.fitting._fit import attach_effects, explain_misfit
from estim.fitting._missing_physics import (
    EXPLAINS,
    SPREAD,
    format_effects,
    format_note,
    held_coefficients,
    missing_physics,
    model_effects,
    one_restitution,
)

DROP_XML = ROOT / "data" / "scenes" / "drop.xml"
TABLE_XML = ROOT / "data" / "scenes" / "table_tennis.xml"
G = 9.81
C_D = 0.47


@pytest.fixture(scope="module")
def drop():
    return estim.load_scene(DROP_XML)


def _ball(scene, z0=0.5, radius=None, mass=None):
    """The scene's ping-pong ball released from rest at height z0 (centre), or a ball of
    the given radius and mass there."""
    p = estim.Params.for_ball(scene, "pingpong", e=0.85, mu_t=0.9, position=(0.0, 0.0, z0))
    if radius is None:
        return p
    return estim.Params(p.e, p.mu_t, radius, p.position, p.velocity, mass=mass)


def test_drag_lag_of_a_dropped_ball_is_the_closed_form(drop):
    """Dropped from rest, under quadratic drag alone (viscosity 0), the ball falls as
    z(t) = z0 - ln(cosh(t sqrt(g k))) / k, k = rho C_D pi r^2 / (2 m) (Taylor, Classical
    Mechanics, sec. 2.4). Before the first bounce its lag behind the parabola grows with
    t, so the largest deviation over [0, T] is the lag at T."""
    z0, t_span, rho = 2.0, 0.5, 1.204  # the vacuum fall to the table lasts 0.63 s
    ball = _ball(drop, z0)
    r, m = float(ball.radius), float(ball.mass)
    k = rho * C_D * math.pi * r**2 / (2 * m)
    lag = G * t_span**2 / 2 - math.log(math.cosh(t_span * math.sqrt(G * k))) / k
    # 61 mm for 2.7 g; the first terms of its series in x^2 = g k T^2 (ln cosh x = x^2/2 -
    # x^4/12 + x^6/45 - 17 x^8/2520 + ...) agree
    x2 = G * k * t_span**2
    assert lag == pytest.approx((x2**2 / 12 - x2**3 / 45 + 17 * x2**4 / 2520) / k, rel=2e-3)

    (entry,) = missing_physics(drop, ball, t_span, 1e-3, "pingpong", density=rho, viscosity=0.0)
    assert entry["effect"] == "air drag"
    assert entry["max_deviation_mm"] == pytest.approx(lag * 1e3, rel=1e-6)
    assert entry["noise_levels"] == pytest.approx(lag / 1e-3, rel=1e-6)
    assert entry["explains"] is True
    assert entry["air"] == {"density": rho, "viscosity": 0.0}
    assert 'viscosity="0"' in entry["advice"]


def test_a_scene_with_air_has_the_effect_already(drop):
    air = drop.with_air(estim.Air(1.204, 1.81e-5))
    assert missing_physics(air, _ball(drop), 1.0, 1e-3, "pingpong") == []
    assert missing_physics(air, _ball(drop), 1.0, 1e-3, "pingpong", spin=50.0) == []


def test_a_ping_pong_ball_over_one_second_needs_air(drop):
    ball = _ball(drop)
    (entry,) = missing_physics(drop, ball, 1.0, 1e-3, "pingpong")
    # falling 0.48 m to the table (its first flight) lags about k g^2 t^4 / 12 ~ 10 mm
    assert 5 < entry["max_deviation_mm"] < 20
    assert entry["noise_levels"] >= EXPLAINS and entry["explains"] is True
    assert entry["ball"] == "pingpong" and entry["mass_kg"] == pytest.approx(0.0027)
    assert entry["advice"] == ('add <option density="1.2" viscosity="1.81e-5"/> to the scene '
                               "and fit drag_coefficient (--also drag_coefficient)")
    note = format_note(entry, 0.0027)
    assert note.startswith("air drag would move this 2.7 g ball by ")
    assert " mm in its first flight, " in note and " noise levels: add " in note
    assert note.endswith("(--also drag_coefficient)")
    # the mass comes from the scene's ball when the parameters have none
    bare = estim.Params(ball.e, ball.mu_t, ball.radius, ball.position, ball.velocity)
    (same,) = missing_physics(drop, bare, 1.0, 1e-3, "pingpong")
    assert same["max_deviation_mm"] == pytest.approx(entry["max_deviation_mm"], rel=1e-12)


def test_a_bocce_ball_over_a_short_track_needs_none(drop):
    """0.92 kg, r = 0.08 m: k = 0.0062 /m, a lag of k g^2 t^4 / 12 ~ 0.2 mm at 0.25 s."""
    ball = _ball(drop, radius=0.08, mass=0.92)
    (entry,) = missing_physics(drop, ball, 0.25, 1e-3, "bocce")
    k = 1.204 * C_D * math.pi * 0.08**2 / (2 * 0.92)
    assert entry["max_deviation_mm"] == pytest.approx(k * G**2 * 0.25**4 / 12 * 1e3, rel=0.02)  # + Stokes
    assert entry["noise_levels"] < 1 and entry["explains"] is False
    assert format_note(entry, 0.92).startswith("air drag would move this 920 g ball by 0.19 mm in its first flight, 0.19 noise levels")


def test_a_stated_spin_adds_a_magnus_entry(drop):
    """Backspin about the axis across the release direction (+x for a drop): omega = s x x z
    = -s y, and omega x w for a falling ball (w = -v z) points along +x."""
    drag, magnus = missing_physics(drop, _ball(drop), 1.0, 1e-3, "pingpong", spin=50.0)
    assert drag["effect"] == "air drag"
    assert magnus["effect"] == "a spinning ball (Magnus, 50 rad/s backspin)"
    assert magnus["explains"] is True and magnus["max_deviation_mm"] > 3
    assert magnus["advice"].endswith("fit the spin (--also spin)")
    assert format_note(magnus, 0.0027).startswith("a spinning ball (Magnus, 50 rad/s backspin) would move this 2.7 g ball")
    # the same drag entry as without a spin
    (alone,) = missing_physics(drop, _ball(drop), 1.0, 1e-3, "pingpong")
    assert drag["max_deviation_mm"] == pytest.approx(alone["max_deviation_mm"], rel=1e-12)


def test_bad_input(drop):
    ball = _ball(drop)
    batch = estim.Params(np.full(2, 0.8), 0.9, 0.02, np.zeros((2, 3)) + [0, 0, 0.5], np.zeros(3), mass=0.0027)
    with pytest.raises(ValueError, match="one ball"):
        missing_physics(drop, batch, 1.0, 1e-3, "pingpong")
    for kwargs in ({"noise_m": 0.0}, {"noise_m": float("nan")}, {"t_span": -1.0}):
        args = {"t_span": 1.0, "noise_m": 1e-3} | kwargs
        with pytest.raises(ValueError, match=next(iter(kwargs))):
            missing_physics(drop, ball, args["t_span"], args["noise_m"], "pingpong")
    with pytest.raises(ValueError, match="no force"):
        missing_physics(drop, ball, 1.0, 1e-3, "pingpong", density=0.0, viscosity=0.0)


def test_a_held_drag_coefficient_is_probed_a_quarter_off(drop):
    """In a scene with air, a drag coefficient the fit held is probed SPREAD (25%) larger:
    dropped from rest under quadratic drag alone, the ball falls as z(t) = z0 -
    ln(cosh(t sqrt(g k))) / k (Taylor, sec. 2.4), so the entry is the distance between the
    falls with k and 1.25 k at the end of the span (it grows with t before the first
    bounce)."""
    z0, t_span, rho = 2.0, 0.5, 1.204
    air = drop.with_air(estim.Air(rho, 0.0))
    ball = _ball(air, z0)
    r, m = float(ball.radius), float(ball.mass)

    def fall(c_d):
        k = rho * c_d * math.pi * r**2 / (2 * m)
        return math.log(math.cosh(t_span * math.sqrt(G * k))) / k

    (entry,) = held_coefficients(air, ball, t_span, 1e-3, "pingpong", ("drag_coefficient",))
    assert SPREAD == 0.25
    assert entry["effect"] == "a drag_coefficient 25% above the 0.47 held"
    assert entry["max_deviation_mm"] == pytest.approx((fall(C_D) - fall(1.25 * C_D)) * 1e3, rel=1e-6)
    assert entry["explains"] is (entry["noise_levels"] >= EXPLAINS)
    assert entry["advice"] == "fit it (--also drag_coefficient)"
    assert entry["air"] == {"density": rho, "viscosity": 0.0}
    assert format_note(entry, m).startswith("a drag_coefficient 25% above the 0.47 held would move this 2.7 g ball by")


def test_a_held_lift_factor_is_probed_only_for_a_spinning_ball(drop):
    """The lift (Magnus) acceleration is proportional to the lift factor, so for a small
    effect the ball moves SPREAD times as far as the whole Magnus effect does (spinning
    against not spinning, in the same air): to a few percent, the second-order coupling
    with drag. Without spin the factor does nothing and is not probed; nor are the
    coefficients of a scene without air, or ones the fit did not hold."""
    air = drop.with_air(estim.Air(1.204, 1.8e-5))
    still = _ball(air)
    spinning = dataclasses.replace(still, spin=np.array([0.0, -50.0, 0.0]))
    drag, lift = held_coefficients(air, spinning, 1.0, 1e-3, "pingpong")
    assert drag["effect"].startswith("a drag_coefficient") and lift["effect"] == "a lift_factor 25% above the 1 held"
    _, magnus = missing_physics(drop, still, 1.0, 1e-3, "pingpong", density=1.204, viscosity=1.8e-5, spin=50.0)
    assert lift["max_deviation_mm"] == pytest.approx(SPREAD * magnus["max_deviation_mm"], rel=0.05)
    assert [x["effect"] for x in held_coefficients(air, still, 1.0, 1e-3, "pingpong")] == [drag["effect"]]
    assert held_coefficients(air, spinning, 1.0, 1e-3, "pingpong", ()) == []
    assert held_coefficients(drop, spinning, 1.0, 1e-3, "pingpong") == []
    with pytest.raises(ValueError, match="among"):
        held_coefficients(air, spinning, 1.0, 1e-3, "pingpong", ("e",))


def _shot(scene, mu, spin=(0.0, 0.0, 0.0)):
    """A ping-pong ball thrown along +y at 3 m/s from 0.3 m over the table (its top at z = 0),
    bouncing once on it at t_b = sqrt(2 h / g), h = 0.3 - r, with impact speed g t_b."""
    ball = estim.Params.for_ball(scene, "pingpong", e=0.88, mu_t=0.0, mu=mu, position=(0.0, -1.3, 0.3),
                                 velocity=(0.0, 3.0, 0.0), spin=spin)
    t_b = math.sqrt(2 * (0.3 - float(ball.radius)) / G)
    return ball, t_b


def test_the_bounce_effects_in_a_vacuum_are_garwins_closed_forms():
    """In a vacuum under the friction law, the effects the model has are the bounce's. A
    ball without spin sliding through its bounce (mu (1 + e) v_n < alpha / (1 + alpha) v_t)
    loses ``mu (1 + e) v_n`` of its speed along the table there (Garwin 1969), and nothing
    else differs from a frictionless bounce until the next one: the largest deviation over a
    span T is that loss times (T - t_b). Backspin that keeps it sliding the same way
    (the slip ``v_t - r w x n`` along v_t) changes nothing of its motion (the sliding impulse
    has the slip's direction, not its size): the spin's effect at the bounce is 0; topspin
    that makes it grip does change it."""
    scene = estim.load_scene(TABLE_XML).with_air(None)
    g = float(scene.gravity)
    mu, e, noise = 0.1, 0.88, 1e-3
    ball, t_b = _shot(scene, mu)
    v_n = g * t_b
    alpha = float(ball.inertia)
    assert mu * (1 + e) * v_n < alpha / (1 + alpha) * 3.0  # it slides
    t_span = t_b + 0.15  # before the second bounce (after 2 e v_n / g = 0.42 s)
    (entry,) = model_effects(scene, ball, t_span, noise)
    assert (entry["effect"], entry["switched_off"]) == ("friction at the bounce", "mu = 0")
    lost = mu * (1 + e) * v_n
    assert entry["max_deviation_mm"] == pytest.approx(lost * (t_span - t_b) * 1e3, rel=1e-6)
    assert entry["noise_levels"] == pytest.approx(lost * (t_span - t_b) / noise, rel=1e-6)
    assert entry["verdict"] == "measured"

    back, _ = _shot(scene, mu, spin=(20.0, 0.0, 0.0))  # slip 3 + 20 r > 0 along +y: slides
    spin, friction = model_effects(scene, back, t_span, noise)
    assert spin["effect"] == "spin at the bounce" and friction["effect"] == "friction at the bounce"
    assert spin["max_deviation_mm"] < 1e-9 and spin["verdict"] == "below the noise"
    top, _ = _shot(scene, 0.5, spin=(-140.0, 0.0, 0.0))  # slip 3 - 140 r = 0.2 m/s: it grips
    spin, _ = model_effects(scene, top, t_span, noise)
    assert spin["verdict"] == "measured"
    line = format_effects([spin, {**friction, "noise_levels": 0.4, "verdict": "below the noise"}])
    assert line.startswith("effects, in noise levels over the track: spin at the bounce ")
    assert line.endswith("friction at the bounce 0.4 (below the noise: this track cannot tell it from its absence)")


def test_the_effects_of_a_shot_in_air():
    """In the table-tennis scene's still air, a spinning shot has all five effects; the
    seed's law in a vacuum has none; the quadratic drag's size is its closed form over a
    short span before the bounce, where the bounce's friction does nothing yet (a ball released at rest, no viscosity: the drop's lag
    ``g T^2 / 2 - ln(cosh(T sqrt(g k))) / k``)."""
    table = estim.load_scene(TABLE_XML)
    ball, t_b = _shot(table, 0.2, spin=(-50.0, 0.0, 10.0))
    names = [m["effect"] for m in model_effects(table, ball, 0.5, 2e-3)]
    assert names == ["quadratic drag", "linear drag", "Magnus", "spin at the bounce", "friction at the bounce"]
    assert model_effects(estim.load_scene(DROP_XML), _ball(estim.load_scene(DROP_XML)), 0.5, 1e-3) == []

    rho = float(table.air.density)
    still = table.with_air(estim.Air(rho, 0.0))
    drop = dataclasses.replace(ball, velocity=ball.velocity * 0.0, spin=ball.spin * 0.0)
    t_span = 0.2
    entry, friction = model_effects(still, drop, t_span, 1e-3)
    assert friction["effect"] == "friction at the bounce" and friction["max_deviation_mm"] == 0.0  # no bounce yet
    r, m = float(drop.radius), float(drop.mass)
    k = rho * float(drop.drag_coefficient) * math.pi * r**2 / (2 * m)
    lag = G * t_span**2 / 2 - math.log(math.cosh(t_span * math.sqrt(G * k))) / k
    assert entry["effect"] == "quadratic drag"
    assert entry["max_deviation_mm"] == pytest.approx(lag * 1e3, rel=1e-6)


@pytest.mark.parametrize("release", [(0.0, 0.0, -0.03), (0.0, 0.0, 0.25)])
def test_a_fit_released_inside_a_solid_is_said_so_not_simulated(drop, release):
    """A fit above its noise floor is explained by simulating the fitted ball; one whose
    release lies inside the table (a fit of one camera's pixels can run there: nothing in
    the fit's program keeps it out) made that simulation refuse it, and the shot was left
    without an answer. Its report now says where the release lies instead, and has no
    effects (``attach_effects`` refused it too); a release above the table is explained
    as before."""
    ball = drop.ball("pingpong")
    values = {**registry.defaults(ball), **dict(zip(("x0", "y0", "z0"), release, strict=True))}
    report = SimpleNamespace(values=values, at_noise_floor=False, rms_m=3e-3, noise_m=1e-3, notes=[],
                             missing_physics=[], ball="pingpong", model_position=np.zeros((3, 3)), effects=None,
                             contacts=(), n_outliers=0)
    problem = SimpleNamespace(mask=np.ones((3, 3), bool), t=np.array([0.0, 0.25, 0.5]), radius=ball.radius,
                              mass=ball.mass, inertia=ball.inertia, cameras=None)
    explain_misfit(drop, report, problem, ("e",))
    attach_effects(drop, report, problem)
    inside = release[2] < ball.radius
    assert any("lies inside 'table'" in n for n in report.notes) is inside
    # (Above the table: the air the drop scene lacks, over half a second of a ping-pong ball.)
    assert (report.missing_physics == []) is inside and report.effects is not None


def test_a_diagnostic_that_cannot_simulate_leaves_the_fit_standing(drop):
    """The diagnostics of a finished fit simulate its ball again (and probes of it); where
    such a simulation cannot complete, the fit stood without an answer (a held-coefficient
    probe of a camera fit's candidate raised and took ``fit_image`` down). A ball that
    bounces forever on the floor (e = 1, released a millimetre up) over 100 s needs more
    ODE steps than any default allows: the probes say so in a note, and nothing else of
    the report changes."""
    ball = drop.ball("pingpong")
    values = {**registry.defaults(ball), "x0": 0.0, "y0": 0.0, "z0": ball.radius + 1e-3, "e": 1.0}
    report = SimpleNamespace(values=dict(values), at_noise_floor=False, rms_m=3e-3, noise_m=1e-3, notes=[],
                             missing_physics=[], ball="pingpong", model_position=np.zeros((3, 3)), effects=None,
                             contacts=(("floor", "plane"),) * 3, n_outliers=0)
    problem = SimpleNamespace(mask=np.ones((3, 3), bool), t=np.array([0.0, 50.0, 100.0]), radius=ball.radius,
                              mass=ball.mass, inertia=ball.inertia, cameras=None)
    params = registry.to_params(values, radius=ball.radius, mass=ball.mass, inertia=ball.inertia, scene=drop)
    with pytest.raises(RuntimeError, match="max_steps"):
        missing_physics(drop, params, 100.0, 1e-3, "pingpong")
    explain_misfit(drop, report, problem, ("e",))
    assert report.missing_physics == [] and report.values == values
    assert len(report.notes) == 1 and report.notes[0].startswith("the missing-physics probes did not run (a ball "
                                                                 "needed more ODE steps than max_steps")


def test_one_restitution_is_said_only_for_surfaces_the_scene_declares_different(drop):
    """The table-tennis scene declares its table, floor and net surfaces of their own: a
    path that bounces on the table and then the floor is said to have one e for both (the
    surfaces in the order met, each once); one on the table alone is not. A scene that
    declares none (the seed's stairs: five treads and the ground, all one surface) never is."""
    table = estim.load_scene(TABLE_XML)
    assert one_restitution(table, (("table", "+z"),) * 2, "pingpong", 0.85, 0) == []
    (entry,) = one_restitution(table, (("table", "+z"), ("table", "+z"), ("floor", "plane"), ("floor", "plane"),
                                       ("table", "-y")), "pingpong", 0.402, 12)
    assert entry["surfaces"] == ["table", "floor"] and entry["explains"]
    assert "e = 0.402" in entry["advice"] and "12 row(s) set aside" in entry["advice"]
    assert one_restitution(table, (("net", "-y"), ("table", "+z")), "pingpong", 0.85, 0)[0]["surfaces"] == ["net", "table"]
    stairs = estim.load_scene(ROOT / "data" / "scenes" / "stairs.xml")
    assert stairs.surfaces == () and one_restitution(
        stairs, tuple((n, "+z") for n in stairs.names), "golf", 0.7, 0) == []
