"""The spin-coupled bounce (``estim.forward.laws.FrictionLaw``) against independent truths:
the frictionless limit, rolling in and out, Garwin's closed forms for a ball without spin,
the conservation of angular momentum about the contact point, energy, finite differences on
both sides of the slide/grip switch; its declaration in MJCF; and ``simulate`` with it (the
ODE path carrying the spin) against a bounce worked out by hand."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import ROOT

import estim
from estim.forward._constants import STEP_UNUSED, STEP_ZENO
from estim.forward.laws import (
    AbstractContactLaw,
    FactorLaw,
    FrictionCoefficients,
    FrictionLaw,
    law_of,
    series,
)

LAW = FrictionLaw()
SHELL, SOLID = 2.0 / 3.0, 0.4
R = 0.02
TABLE_TENNIS = ROOT / "data" / "scenes" / "table_tennis.xml"
DROP = ROOT / "data" / "scenes" / "drop.xml"


def coefficients(e=0.9, mu=0.25, inertia=SHELL, radius=R, e_slope=0.0):
    return FrictionCoefficients(*(jnp.asarray(x, dtype=jnp.float64) for x in (e, mu, radius, inertia, e_slope)))


def random_impacts(n, seed):
    """``n`` impacts on random faces: velocity into the face, any spin, any e, mu, inertia."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    v = rng.normal(scale=4.0, size=(n, 3))
    v -= (np.einsum("ij,ij->i", v, normals) + rng.uniform(0.5, 5.0, n))[:, None] * normals  # into the face
    w = rng.normal(scale=200.0, size=(n, 3))
    return normals, v, w, rng.uniform(0.0, 1.0, n), rng.uniform(0.0, 1.0, n), rng.uniform(0.2, 1.0, n)


def test_without_friction_the_tangential_velocity_and_the_spin_are_kept():
    n, v, w, e, _, alpha = random_impacts(50, 0)
    for k in range(50):
        v1, w1 = LAW.impact(v[k], w[k], n[k], coefficients(e[k], 0.0, alpha[k]))
        vn = v[k] @ n[k]
        np.testing.assert_allclose(v1, v[k] - vn * n[k] - e[k] * vn * n[k], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(w1, w[k])


@pytest.mark.parametrize("alpha", [SOLID, SHELL])
def test_a_ball_that_arrives_rolling_leaves_rolling_unchanged(alpha):
    """Rolling (v_t = r w x n) means no slip: no tangential impulse, whatever mu."""
    n = np.array([0.0, 0.0, 1.0])
    w = np.array([-60.0, 25.0, 7.0])
    v = R * np.cross(w, n) + np.array([0.0, 0.0, -3.0])
    v1, w1 = LAW.impact(v, w, n, coefficients(0.8, 0.4, alpha))
    np.testing.assert_allclose(v1[:2], v[:2], rtol=0, atol=1e-13)
    np.testing.assert_allclose(v1[2], 2.4, rtol=1e-14)
    np.testing.assert_allclose(w1, w, rtol=0, atol=1e-12)


@pytest.mark.parametrize(("alpha", "ratio"), [(SOLID, 5.0 / 7.0), (SHELL, 3.0 / 5.0)])
def test_garwin_closed_forms_for_a_ball_without_spin(alpha, ratio):
    """Without spin: gripping leaves ``v_t / (1 + alpha)`` (5/7 for a solid sphere, 3/5 for a
    shell) and spin ``v_t / ((1 + alpha) r)``; sliding throughout loses ``mu (1 + e) |v_n|``
    of tangential speed (Garwin 1969)."""
    n = np.array([0.0, 0.0, 1.0])
    v = np.array([3.0, 0.0, -2.0])
    v1, w1 = LAW.impact(v, np.zeros(3), n, coefficients(0.7, 10.0, alpha))  # large mu: it grips
    np.testing.assert_allclose(v1, [3.0 * ratio, 0.0, 1.4], rtol=1e-14)
    np.testing.assert_allclose(w1, [0.0, 3.0 * ratio / R, 0.0], rtol=1e-13)
    mu = 0.1  # mu (1 + e) |v_n| = 0.34 < alpha / (1 + alpha) |s|: slides throughout
    v1, w1 = LAW.impact(v, np.zeros(3), n, coefficients(0.7, mu, alpha))
    np.testing.assert_allclose(v1, [3.0 - mu * 1.7 * 2.0, 0.0, 1.4], rtol=1e-14)
    np.testing.assert_allclose(w1, [0.0, mu * 1.7 * 2.0 / (alpha * R), 0.0], rtol=1e-13)


def test_angular_momentum_about_the_contact_point_is_kept_and_energy_never_rises():
    n, v, w, e, mu, alpha = random_impacts(200, 1)
    m = 0.0027
    for k in range(200):
        c = coefficients(e[k], mu[k], alpha[k])
        v1, w1 = (np.asarray(x) for x in LAW.impact(v[k], w[k], n[k], c))
        inertia = alpha[k] * m * R**2

        def momentum(vel, spin, k=k, inertia=inertia):
            return inertia * spin + m * R * np.cross(n[k], vel)

        def energy(vel, spin, inertia=inertia):
            return 0.5 * m * vel @ vel + 0.5 * inertia * spin @ spin

        np.testing.assert_allclose(momentum(v1, w1), momentum(v[k], w[k]), rtol=1e-12, atol=1e-15)
        assert energy(v1, w1) <= energy(v[k], w[k]) * (1 + 1e-14)
        slip = v1 - (v1 @ n[k]) * n[k] - R * np.cross(w1, n[k])
        slip0 = v[k] - (v[k] @ n[k]) * n[k] - R * np.cross(w[k], n[k])
        # The slip keeps its direction and does not grow: it stops, or shrinks by the
        # Coulomb impulse.
        assert np.linalg.norm(slip) <= np.linalg.norm(slip0) * (1 + 1e-12)
        assert slip @ slip0 >= -1e-12 * (slip0 @ slip0)


@pytest.mark.parametrize("mu", [0.05, 0.6])  # slides throughout / grips
def test_derivatives_match_finite_differences_on_both_sides_of_the_switch(mu):
    n = jnp.array([0.0, 0.0, 1.0])
    x0 = jnp.array([2.5, -0.7, -3.0, 40.0, -35.0, 12.0, 0.85, mu, SHELL])

    def out(x):
        v1, w1 = LAW.impact(x[:3], x[3:6], n, coefficients(x[6], x[7], x[8]))
        return jnp.concatenate([v1, w1 * R])

    # Which side of the switch: mu (1 + e) |v_n| against alpha / (1 + alpha) |slip|.
    slip = np.asarray(x0[:2]) - R * np.cross(np.asarray(x0[3:6]), [0, 0, 1.0])[:2]
    slides = mu * 1.85 * 3.0 < SHELL / (1 + SHELL) * np.linalg.norm(slip)
    assert slides == (mu == 0.05)
    jac = jax.jacfwd(out)(x0)
    np.testing.assert_allclose(jax.jacrev(out)(x0), jac, rtol=1e-12, atol=1e-12)
    h = 1e-6
    for i in range(9):
        dx = jnp.zeros(9).at[i].set(h)
        fd = (out(x0 + dx) - out(x0 - dx)) / (2 * h)
        np.testing.assert_allclose(jac[:, i], fd, rtol=1e-6, atol=1e-8)


def test_zero_slip_has_finite_derivatives():
    """At zero slip (|s| = 0) the law is regular: no NaN in values or derivatives."""
    n = jnp.array([0.0, 0.0, 1.0])
    w = jnp.array([-50.0, 10.0, 3.0])
    v = R * jnp.cross(w, n) + jnp.array([0.0, 0.0, -2.0])

    def out(x):
        return jnp.concatenate(LAW.impact(x[:3], x[3:], n, coefficients()))

    jac = jax.jacfwd(out)(jnp.concatenate([v, w]))
    assert np.all(np.isfinite(jac))
    assert np.all(np.isfinite(jax.jacrev(out)(jnp.concatenate([v, w]))))


def test_vanishing_bounces_leave_the_ball_rolling_with_its_angular_momentum():
    n = np.array([0.0, 0.0, 1.0])
    u, w = np.array([1.2, -0.4, 0.0]), np.array([30.0, 80.0, 5.0])
    v1, w1 = (np.asarray(x) for x in LAW.settle_spin(u, w, n, coefficients(mu=0.3, inertia=SOLID)))
    np.testing.assert_allclose(v1 - R * np.cross(w1, n), 0.0, atol=1e-14)  # rolling
    np.testing.assert_allclose(SOLID * R * w1 + np.cross(n, v1), SOLID * R * w + np.cross(n, u), rtol=1e-13)
    assert w1[2] == w[2]  # friction at a point leaves the spin about the normal


def test_a_scene_declares_its_law_and_the_ball_its_inertia():
    scene = estim.load_scene(TABLE_TENNIS)
    assert isinstance(law_of(scene), FrictionLaw)
    assert scene.ball("pingpong").inertia == pytest.approx(SHELL, rel=1e-12)  # shellinertia="true"
    assert isinstance(law_of(estim.load_scene(DROP)), FactorLaw)  # says nothing: the seed's law
    p = estim.Params.for_ball(scene, "pingpong", e=0.9, mu_t=1.0, mu=0.2)
    assert float(p.inertia) == pytest.approx(SHELL, rel=1e-12)


def test_an_unknown_law_or_impossible_friction_is_refused(tmp_path):
    text = DROP.read_text().replace("<worldbody>", '<custom><text name="estim:law" data="sticky"/></custom>\n<worldbody>')
    bad = tmp_path / "bad.xml"
    bad.write_text(text)
    with pytest.raises(ValueError, match="unknown contact law"):
        estim.load_scene(bad)
    scene = estim.load_scene(DROP)
    with pytest.raises(ValueError, match="Params.mu must be >= 0"):
        estim.Params.for_ball(scene, "pingpong", e=0.9, mu_t=1.0, mu=-0.1)
    with pytest.raises(ValueError, match="Params.inertia must lie in"):
        estim.Params(0.9, 1.0, R, (0, 0, 1.0), (0, 0, 0), inertia=1.5)
    with pytest.raises(ValueError, match="spin changes nothing"):
        estim.simulate(scene, estim.Params.for_ball(scene, "pingpong", e=0.9, mu_t=1.0, spin=(0, 5.0, 0)), 1.0)


def bounce_by_hand(h, u, spin, e, mu, alpha, t):
    """A ball released at height h above the plane z = 0 with horizontal velocity (u, 0, 0)
    and spin, in a vacuum: it lands at sqrt(2 h / g), the law's impact, a parabola after."""
    g = 9.81
    t1 = np.sqrt(2 * (h - R) / g)
    v_in = np.array([u, 0.0, -g * t1])
    v1, w1 = (np.asarray(x) for x in LAW.impact(v_in, np.asarray(spin, float), np.array([0.0, 0, 1]),
                                               coefficients(e, mu, alpha)))
    p1 = np.array([u * t1, 0.0, R])
    dt = t - t1
    return p1 + v1 * dt + 0.5 * np.array([0, 0, -g]) * dt**2, v1, w1


@pytest.mark.parametrize("spin", [(0.0, 150.0, 0.0), (0.0, -150.0, 20.0)])  # topspin, backspin
def test_simulate_bounces_with_the_spin_it_carries(spin):
    """The ODE path, in a vacuum, against the bounce worked out by hand: topspin throws the
    ball forward after the bounce, backspin holds it back; and d(position)/d(mu, spin)
    against finite differences."""
    scene = estim.load_scene(DROP).with_law("friction")
    h, u, e, mu = 0.3, 1.0, 0.9, 0.25
    params = estim.Params(e, 1.0, R, (0.0, 0.0, h), (u, 0.0, 0.0), spin=spin, mu=mu, inertia=SHELL)
    t = 0.35
    traj = estim.simulate(scene, params, t, ts=jnp.array([t]))
    want, v1, _ = bounce_by_hand(h, u, spin, e, mu, SHELL, t)
    np.testing.assert_allclose(np.asarray(traj.position[0]), want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(traj.events.velocity_post[0]), v1, rtol=0, atol=1e-9)
    assert (v1[0] > u) == (spin[1] > 0)

    def x_at(theta):
        p = estim.Params(e, 1.0, R, (0.0, 0.0, h), (u, 0.0, 0.0), spin=theta[1:], mu=theta[0], inertia=SHELL)
        return estim.simulate(scene, p, t, ts=jnp.array([t])).position[0]

    theta = jnp.array([mu, *spin])
    jac = jax.jacfwd(x_at)(theta)
    for i in range(4):
        d = 1e-5 * max(1.0, abs(float(theta[i])))
        fd = (bounce_by_hand(h, u, theta[1:].at[i - 1].add(d) if i else theta[1:], e,
                             mu + (d if i == 0 else 0.0), SHELL, t)[0]
              - bounce_by_hand(h, u, theta[1:].at[i - 1].add(-d) if i else theta[1:], e,
                               mu - (d if i == 0 else 0.0), SHELL, t)[0]) / (2 * d)
        np.testing.assert_allclose(np.asarray(jac[:, i]), fd, rtol=1e-6, atol=1e-9)


def test_the_command_line_simulates_the_friction_law_and_refuses_what_does_not_act(capsys):
    """``estim simulate`` sets the friction law's mu and the spin from the registry, and its
    result is ``estim.simulate``'s; mu_t, which the friction law does not read, is refused
    (as mu is in the seed's scene), and ``estim effects``, whose baseline is the factor law's
    closed form, refuses the scene, naming the law."""
    from estim.app._cli import main

    args = ["--ball", "pingpong", "--e", "0.9", "--mu", "0.2", "--vx0", "0", "--vy0", "6", "--vz0", "1", "--spin-x", "-100",
            "--t-end", "0.6"]
    assert main(["simulate", "--scene", str(TABLE_TENNIS), *args, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["params"]["mu"] == 0.2 and "mu_t" not in out["params"]
    scene = estim.load_scene(TABLE_TENNIS)
    p = estim.Params.for_ball(scene, "pingpong", e=0.9, mu_t=1.0, mu=0.2, velocity=(0.0, 6.0, 1.0),
                              spin=(-100.0, 0.0, 0.0))
    traj = estim.simulate(scene, p, 0.6)
    assert out["events"][0]["t"] == pytest.approx(float(traj.events.t[0]), abs=1e-12)
    assert main(["simulate", "--scene", str(TABLE_TENNIS), "--ball", "pingpong", "--e", "0.9", "--mu-t", "0.5"]) == 2
    assert "mu_t acts only under a contact law that reads it" in capsys.readouterr().err
    assert main(["simulate", "--scene", str(DROP), "--ball", "pingpong",
                 "--e", "0.9", "--mu", "0.5"]) == 2
    assert main(["effects", "--scene", str(TABLE_TENNIS)]) == 2
    assert "FrictionLaw" in capsys.readouterr().err


def mujoco_bounce(mu, vx, wy, damping):
    """A table-tennis ball (shell inertia) hitting MuJoCo's floor at 2 m/s with horizontal
    velocity vx and spin wy about y: MuJoCo's own frictional contact (elliptic cone, stiff
    friction: impratio 100; ``solref="0.0005 damping"``), stepped until the contact ends.
    Returns the velocity and the spin after it."""
    geom = f'friction="{mu} 0 0" condim="3" solref="0.0005 {damping}"'
    xml = f"""<mujoco><option timestep="2e-5" cone="elliptic" impratio="100"/><worldbody>
    <geom type="plane" size="2 2 0.1" {geom}/><body pos="0 0 {R + 5e-4}"><freejoint/>
    <geom type="sphere" size="{R}" mass="0.0027" shellinertia="true" {geom}/></body></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    data.qvel[:] = [vx, 0.0, -2.0, 0.0, wy, 0.0]
    touched = False
    for _ in range(20_000):
        mujoco.mj_step(model, data)
        touched |= data.ncon > 0
        if touched and data.ncon == 0:
            return data.qvel[:3].copy(), data.qvel[3:].copy()
    raise AssertionError("MuJoCo's contact did not end")


@pytest.mark.parametrize(("mu", "vx", "wy", "damping", "tol"), [
    (0.1, 2.0, 0.0, 0.3, 0.005),  # slides throughout
    (0.05, 0.5, 100.0, 0.3, 0.005),  # topspin faster than rolling: slides, pushed forward
    (0.15, 3.0, 150.0, 0.3, 0.01),  # arrives rolling (MuJoCo: the contact point inside r by the penetration)
    (2.0, 2.0, 0.0, 1.0, 0.01),  # grips
    (2.0, 1.0, -120.0, 1.0, 0.025),  # backspin, grips: the ball comes back
])
def test_the_bounce_agrees_with_mujocos_frictional_contact(mu, vx, wy, damping, tol):
    """MuJoCo's contact, the independent engine: given the restitution it shows (its normal
    speed after over before), the law's velocity and spin after the bounce are MuJoCo's, to
    ``tol`` (5 to 25 mm/s) in v_x and in r w_y, which the bounce changes by up to 1.4 m/s
    (MuJoCo rolls on a contact point inside r by its penetration). Where they
    part (not tested): on a bouncier contact MuJoCo's soft friction does not stop the slip
    that Coulomb's impulse stops (damping 0.1, e = 0.73: v_x 1.60 where gripping gives 1.20;
    docs/pages/contact-model.md)."""
    v, w = mujoco_bounce(mu, vx, wy, damping)
    e = v[2] / 2.0
    v1, w1 = (np.asarray(x) for x in LAW.impact(np.array([vx, 0.0, -2.0]), np.array([0.0, wy, 0.0]),
                                               np.array([0.0, 0.0, 1.0]), coefficients(e, mu, SHELL)))
    assert abs(v[0] - v1[0]) <= tol and abs(R * (w[1] - w1[1])) <= tol, (v, w, v1, w1)
    assert abs(v[1]) < 1e-9 and abs(w[0]) < 1e-6 and abs(w[2]) < 1e-6


def test_restitution_that_falls_with_impact_speed():
    """``e_slope``: e at an impact of normal speed v is ``e + e_slope (v - 2.446)``, kept in
    [0, 1]. A ball dropped on the table in a vacuum bounces straight up: its impact speeds
    follow the recursion ``v_(k+1) = e(v_k) v_k`` (the flight between keeps the speed), and
    the times between bounces are ``2 v / g``, checked over four bounces; e = 0.88 at the
    ITTF drop test's speed whatever the slope. A slope that would lift e above 1 is held at
    1: no bounce gains energy. The derivatives of the third bounce's time with respect to
    e and e_slope match central differences."""
    scene = estim.load_scene(TABLE_TENNIS).with_air(None)
    g = float(scene.gravity)
    c = coefficients(e=0.88, e_slope=-0.05)
    assert float(c.restitution(jnp.float64(-2.446))) == pytest.approx(0.88, abs=1e-12)

    def drop(e, e_slope, height=0.8):
        p = estim.Params.for_ball(scene, "pingpong", e=e, mu_t=0.0, mu=0.2, position=(0.1, -0.5, height + R),
                                  e_slope=e_slope)
        return estim.simulate(scene, p, 2.6)

    ev = drop(0.88, -0.05).events
    t, pre, post = (np.asarray(x) for x in (ev.t, ev.velocity_pre, ev.velocity_post))
    v = np.sqrt(2 * g * 0.8)
    t_k = np.sqrt(2 * 0.8 / g)
    for k in range(4):
        assert t[k] == pytest.approx(t_k, abs=1e-9) and -pre[k, 2] == pytest.approx(v, rel=1e-9)
        e_k = min(max(0.88 - 0.05 * (v - 2.446), 0.0), 1.0)
        assert post[k, 2] == pytest.approx(e_k * v, rel=1e-9)
        np.testing.assert_allclose(post[k, :2], 0.0, atol=1e-12)
        v = e_k * v
        t_k += 2 * v / g
    up = drop(0.95, 0.5, height=1.5).events  # e(5.4 m/s) would be 2.4
    assert float(up.velocity_post[0, 2]) == pytest.approx(-float(up.velocity_pre[0, 2]), rel=1e-12)

    def third(x):
        p = estim.Params.for_ball(scene, "pingpong", e=x[0], mu_t=0.0, mu=0.2, position=(0.1, -0.5, 0.8 + R),
                                  e_slope=x[1])
        return estim.simulate(scene, p, 2.6, keep="events").events.t[2]

    x0 = jnp.array([0.88, -0.05])
    jac = jax.jacfwd(third)(x0)
    h = 1e-6
    for i in range(2):
        dx = jnp.zeros(2).at[i].set(h)
        assert float(jac[i]) == pytest.approx(float(third(x0 + dx) - third(x0 - dx)) / (2 * h), rel=1e-6)


class BounceByBounceFrictionLaw(AbstractContactLaw):
    """The friction law without its closed-form series: every bounce a step of the ODE
    path, until the rebound falls below REST_SPEED and ``settle_spin`` ends the series."""

    @property
    def couples_spin(self):
        return True

    def coefficients(self, params):
        return LAW.coefficients(params)

    def reset(self, v, n, c):
        return LAW.reset(v, n, c)

    def rebound(self, v, n, c):
        return LAW.rebound(v, n, c)

    def settle(self, tangential, c):
        return LAW.settle(tangential, c)

    def impact(self, v, w, n, c):
        return LAW.impact(v, w, n, c)

    def settle_spin(self, tangential, w, n, c):
        return LAW.settle_spin(tangential, w, n, c)


def series_params(e, mu, **kw):
    """A ball dropped on the table with spin about every axis: its first bounce slides,
    and the series after it slides on for some bounces (mu = 0.01: three), to its end
    (0.006) or throughout without friction (0)."""
    return estim.Params(e, 1.0, R, (0.0, 0.0, 0.3), kw.pop("velocity", (0.05, -0.05, 0.0)),
                        spin=kw.pop("spin", (5.0, 20.0, 30.0)), mu=mu, inertia=SHELL, **kw)


def block_scene(tmp_path):
    """``drop.xml`` with a block on the table (x from -0.3 to -0.1 m, 2 cm high), behind
    the balls of ``series_params``, which move towards +x."""
    xml = DROP.read_text().replace(
        '<camera name="side"', '<geom name="block" type="box" pos="-0.2 0 0.01" size="0.1 0.5 0.01"/>\n    <camera name="side"')
    path = tmp_path / "block.xml"
    path.write_text(xml)
    return estim.load_scene(path)


def bounce_series(scene, params, t_end):
    """The friction law's run of ``params`` on ``scene`` and the bounce-by-bounce one, at 64
    times to t_end (one compiled program per law for every case)."""
    ts = jnp.linspace(0.0, t_end, 64)
    return tuple(estim.simulate(scene.with_law(law), params, t_end, ts=ts, max_events=256)
                 for law in ("friction", BounceByBounceFrictionLaw()))


@pytest.mark.parametrize(("e", "mu", "t_end"), [(0.8, 0.01, 4.0), (0.8, 0.006, 4.0), (0.8, 0.0, 4.0),
                                                (0.8, 0.01, 1.5), (1.0, 0.01, 1.5)])
def test_a_bounce_series_closes_in_closed_form(e, mu, t_end, tmp_path):
    """The ODE path sums the bounce series on the table in one step (the law's closed form,
    ``FrictionLaw.flight_start``, spin included), accumulating (t_end = 4 s) or cut
    at t_end: its bounces, spin included, and the samples are those of the same law run
    bounce by bounce, one step per flight, to rounding. Where the series slides to its end,
    the bounce-by-bounce run settles (``settle_spin``) once its rebound falls below
    REST_SPEED and the sum at the accumulation point, so their last positions differ by
    the tail of flights shorter than that (below 1e-10 m here)."""
    summed, stepped = bounce_series(block_scene(tmp_path), series_params(e, mu), t_end)
    assert bool(summed.complete) and bool(stepped.complete)
    kinds = np.asarray(summed.solution.steps.kind)
    assert np.sum(kinds == STEP_ZENO) == 1
    assert np.sum(kinds != STEP_UNUSED) < np.sum(np.asarray(stepped.solution.steps.kind) != STEP_UNUSED)
    n = int(summed.events.count) - (1 if t_end > 2 else 0)  # (then the settle)
    assert n >= 3 and int(stepped.events.count) >= n
    for name in ("t", "position", "velocity_pre", "velocity_post", "spin_pre", "spin_post"):
        np.testing.assert_allclose(getattr(summed.events, name)[:n], getattr(stepped.events, name)[:n],
                                   rtol=0, atol=1e-11, err_msg=name)
    np.testing.assert_allclose(summed.position, stepped.position, rtol=0, atol=1e-10)
    np.testing.assert_allclose(summed.velocity, stepped.velocity, rtol=0, atol=1e-10)
    np.testing.assert_allclose(summed.final.velocity, stepped.final.velocity, rtol=0, atol=1e-11)
    # The slip |v_t - r w x n| after each listed bounce falls by the law's steps and, under
    # friction, stops for good (mu = 0.01) or only at the settle (0.006).
    v, w = np.asarray(summed.events.velocity_post[:n]), np.asarray(summed.events.spin_post[:n])
    slip = np.linalg.norm(v[:, :2] - R * np.stack([w[:, 1], -w[:, 0]], axis=1), axis=1)
    if mu == 0.01 and e < 1 and t_end > 2:
        assert slip[0] > 0.2 and slip[3] > 0.04 and np.all(slip[5:] < 1e-12)
    if mu == 0.006 and t_end > 2:
        assert np.all(slip[:n] > 0.03) and float(summed.final.velocity[0]) == pytest.approx(
            (v[-1, 0] + SHELL * R * w[-1, 1]) / (1 + SHELL), abs=1e-12)


def test_a_series_that_would_meet_a_block_is_not_summed_through_it(tmp_path):
    """A block on the table in the path of the bounces (0.1 m behind the ball, which moves
    towards it): the series' triangle meets it (``slab_clear``), so the ODE path goes on
    bounce by bounce, the ball hits the block's side, and every bounce is the
    bounce-by-bounce run's."""
    scene = block_scene(tmp_path)
    summed, stepped = bounce_series(scene, series_params(0.8, 0.01, velocity=(-0.02, 0.0, 0.0), spin=(0.0, -5.0, 0.0)),
                                    4.0)
    faces = np.asarray(summed.events.face[: int(summed.events.count)])
    assert any(scene.face_label(int(f))[0] == "block" for f in faces)
    n = int(summed.events.count) - 1
    for name in ("t", "position", "velocity_post", "spin_post"):
        np.testing.assert_allclose(getattr(summed.events, name)[:n], getattr(stepped.events, name)[:n],
                                   rtol=0, atol=1e-10, err_msg=name)


def test_the_summed_series_derivatives_match_finite_differences_bounce_by_bounce(tmp_path):
    """d(position at t = 1.452 s, in the fourth flight of the series, after its bounces
    slide and then grip)/d(e, mu, spin, release velocity) of the summed series against
    central differences of the bounce-by-bounce run (an independent path: steps, event
    times by Newton's method, a reset per bounce)."""
    scene = block_scene(tmp_path)
    ts = jnp.linspace(0.0, 1.5, 64)

    def position(law, theta):
        p = series_params(theta[0], theta[1], spin=theta[2:5], velocity=(theta[5], theta[6], 0.0))
        return estim.simulate(scene.with_law(law), p, 1.5, ts=ts, max_events=256).position[61]

    theta = jnp.array([0.8, 0.01, 5.0, 20.0, 30.0, 0.05, -0.05])
    jac = jax.jacfwd(lambda x: position("friction", x))(theta)
    for i in range(theta.size):
        d = 1e-6 * max(1.0, abs(float(theta[i])))
        fd = (position(BounceByBounceFrictionLaw(), theta.at[i].add(d))
              - position(BounceByBounceFrictionLaw(), theta.at[i].add(-d))) / (2 * d)
        np.testing.assert_allclose(jac[:, i], fd, rtol=1e-5, atol=1e-7, err_msg=str(i))
    assert float(jnp.abs(jac[0, 1])) > 1e-2  # (mu moves the ball)


def test_the_series_closed_form_is_the_bounces_iterated():
    """``FrictionLaw.flight_start`` against its definition, on 300 random series on a
    horizontal face (any slip direction, spin about every axis, e from 0.05 to 0.999, mu
    from 0 to 1, solid to thin-shell inertia): the law's ``impact`` applied bounce after
    bounce, with the flights between them (time 2 v_n / g, the tangential velocity carried
    along), gives the time, displacement, velocity and spin at the start of flights 0 to 40;
    after 3,000 bounces and ``settle_spin``, the Zeno limit (j = inf)."""
    rng = np.random.default_rng(7)
    k, g = 300, 9.81
    n = jnp.array([0.0, 0.0, 1.0])
    u = np.concatenate([rng.normal(scale=1.0, size=(k, 2)), np.zeros((k, 1))], axis=1)
    w_n = rng.uniform(0.05, 3.0, k)
    spin = rng.normal(scale=60.0, size=(k, 3))
    e = np.where(rng.uniform(size=k) < 0.2, 0.999, rng.uniform(0.05, 0.95, k))
    mu = np.where(rng.uniform(size=k) < 0.1, 0.0, rng.uniform(0.0, 1.0, k))
    c = coefficients(e, mu, rng.uniform(0.2, 1.0, k), np.full(k, R), np.zeros(k))
    a = jnp.array([0.0, 0.0, -g])
    sers = jax.vmap(lambda v, w: series(v, n, a, w))(jnp.asarray(u + w_n[:, None] * np.asarray(n)), jnp.asarray(spin))
    start = jax.jit(jax.vmap(LAW.flight_start, in_axes=(0, None, 0)))
    impact = jax.jit(jax.vmap(LAW.impact, in_axes=(0, 0, None, 0)))
    t, x = np.zeros(k), np.zeros((k, 3))
    v, w = jnp.asarray(u + w_n[:, None] * np.asarray(n)), jnp.asarray(spin)
    for j in range(41):
        got = start(sers, jnp.float64(j), c)
        for name, want, have in zip(("t", "x", "v", "w"), (t, x, v, w), got, strict=True):
            np.testing.assert_allclose(have, want, rtol=1e-9, atol=1e-9, err_msg=f"{name} at j = {j}")
        flight = 2.0 * np.asarray(v[:, 2]) / g
        t, x = t + flight, x + np.asarray(v).copy() * flight[:, None] * [1.0, 1.0, 0.0]
        v, w = impact(v.at[:, 2].multiply(-1.0), w, n, c)
    v, w = jax.jit(lambda v, w: jax.lax.fori_loop(
        0, 3000 - 41, lambda _, vw: impact(vw[0].at[:, 2].multiply(-1.0), vw[1], n, c), (v, w)))(v, w)
    settle = jax.vmap(LAW.settle_spin, in_axes=(0, 0, None, 0))
    v_inf, w_inf = settle(v.at[:, 2].set(0.0), w, n, c)
    limit = e < 1
    _, _, v_got, w_got = start(sers, jnp.float64(jnp.inf), c)
    np.testing.assert_allclose(np.asarray(v_got)[limit][:, :2], np.asarray(v_inf)[limit][:, :2], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(w_got)[limit], np.asarray(w_inf)[limit], rtol=1e-9, atol=1e-8)
