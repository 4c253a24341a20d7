"""The parameter registry (estim.fitting._registry) against closed forms, and the fit's
starts in the ball's plane of travel (estim.fitting._initial.release_start) against the
known release state of synthetic throws.

Fast: no fit runs here (the fits of 3-D tracks are in test_fit.py); the throws are two
single-ball simulations on the drop scene.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ROOT

import estim
from estim.fitting import _fit
from estim.fitting import _registry as registry
from estim.fitting._initial import initial_guess, release_start

DROP = ROOT / "data" / "scenes" / "drop.xml"
TABLE = ROOT / "data" / "scenes" / "table_tennis.xml"
# The names a fit has always used (fit.json keys, `estim fit --also`, ``fixed=``).
OLD_NAMES = ("e", "mu_t", "vx0", "x0", "z0", "vz0", "t0", "y0", "vy0", "drag_coefficient", "spin_y")
G = 9.81


# --------------------------------------------------------------------------- the registry


def test_old_names_are_components():
    assert set(OLD_NAMES) <= set(registry.NAMES)
    assert len(set(registry.NAMES)) == len(registry.NAMES)
    for name in registry.NAMES:
        assert name in registry.component(name).components


def _closed_form(name):
    """(phi -> theta, theta -> phi, d phi / d theta at phi) written out for each transform."""
    if name in ("e", "mu_t", "mu"):  # sigmoid into (0, 1)
        return (lambda p: math.log(p / (1.0 - p)), lambda t: 1.0 / (1.0 + math.exp(-t)),
                lambda p: p * (1.0 - p))
    if name in ("drag_coefficient", "lift_factor", "pixel_scale"):  # exp into (0, inf)
        return math.log, math.exp, lambda p: p
    return (lambda p: p), (lambda t: t), (lambda p: 1.0)


def _samples(name):
    if name in ("e", "mu_t", "mu"):
        return [1e-4, 0.05, 0.3, 0.5, 0.82, 0.999]
    if name in ("drag_coefficient", "lift_factor", "pixel_scale"):
        return [1e-3, 0.2, 0.47, 1.0, 3.5]
    return [-7.5, -0.2, 0.0, 0.3, 1.15, 40.0]


@pytest.mark.parametrize("name", registry.NAMES)
def test_round_trip_against_the_closed_form(name):
    """to_theta and to_physical of every component, NumPy and JAX, against the closed form
    of its transform; the slope against the closed-form derivative and a central
    difference of T."""
    to_theta, to_phi, slope = _closed_form(name)
    fixed = registry.pack(registry.defaults(estim.Ball("b", 0.02, 0.0027, (0.0, 0.1, 0.5))))
    for v in _samples(name):
        phi = fixed.copy()
        phi[registry.index([name])[0]] = v
        theta = registry.to_theta(phi, (name,))
        np.testing.assert_allclose(theta, [to_theta(v)], rtol=1e-12, atol=1e-15)
        back = registry.to_physical(theta, (name,), fixed)
        np.testing.assert_allclose(back[registry.index([name])], [v], rtol=1e-12, atol=1e-15)
        others = np.ones(len(phi), bool)
        others[registry.index([name])] = False
        np.testing.assert_array_equal(back[others], fixed[others])  # the rest stays fixed
        # The same numbers from the JAX path (as inside the fit's compiled program).
        theta_j = registry.to_theta(jnp.asarray(phi), (name,))
        np.testing.assert_allclose(np.asarray(theta_j), theta, rtol=1e-13, atol=1e-15)
        back_j = registry.to_physical(theta_j, (name,), jnp.asarray(fixed))
        np.testing.assert_allclose(np.asarray(back_j), back, rtol=1e-13, atol=1e-15)
        # d phi / d theta: the closed form, and T's central difference (h = 1e-6).
        s = registry.slopes(phi, (name,))[0]
        assert s == pytest.approx(slope(v), rel=1e-12)
        h = 1e-6
        fd = (to_phi(theta[0] + h) - to_phi(theta[0] - h)) / (2 * h)
        assert s == pytest.approx(fd, rel=1e-6, abs=1e-12)
        # and autodiff through the JAX path agrees
        ad = jax.grad(lambda t: registry.to_physical(t, (name,), jnp.asarray(fixed))[registry.index([name])[0]])(
            jnp.asarray(theta))
        assert float(ad[0]) == pytest.approx(slope(v), rel=1e-12, abs=1e-300)


def test_starts_on_the_edge_of_a_range_stay_finite():
    """A start of e = 1 (the logit is infinite) is moved just inside, as a drag coefficient
    of 0 (the log is -inf): the fit starts from a finite theta."""
    phi = registry.pack(registry.defaults(estim.Ball("b", 0.02, 0.0027, (0.0, 0.0, 0.5))))
    phi[registry.index(["e", "mu_t", "drag_coefficient"])] = (1.0, 0.0, 0.0)
    theta = registry.to_theta(phi, ("e", "mu_t", "drag_coefficient"))
    # (1 - 1e-6 is not a binary fraction: 1 - (1 - 1e-6) differs from 1e-6 by 1e-17)
    np.testing.assert_allclose(theta, [math.log((1 - 1e-6) / 1e-6), math.log(1e-6 / (1 - 1e-6)), math.log(1e-6)],
                               rtol=1e-9)


def test_ranges_refused_for_fixed_values():
    assert registry.component("e").transform.refuse(1.5) == "must lie in [0, 1]"
    assert registry.component("mu_t").transform.refuse(0.0) is None  # closed range when fixed
    assert registry.component("drag_coefficient").transform.refuse(0.0) == "must be > 0"
    assert registry.component("vy0").transform.refuse(-3.0) is None


def test_expand_and_unknown_names():
    assert registry.expand(["e", "spin", "vx0", "velocity"]) == (
        "e", "spin_x", "spin_y", "spin_z", "vx0", "vy0", "vz0")
    with pytest.raises(ValueError, match="unknown parameter 'spin_w'"):
        registry.expand(["spin_w"])
    with pytest.raises(ValueError, match="unknown parameter 'omega'"):
        registry.component("omega")


def test_params_fields_from_the_registry():
    """Each component lands in its field and vector component of Params (with the air's
    entries left at Params' defaults for a scene without air)."""
    values = {n: 0.01 * (i + 1) for i, n in enumerate(registry.NAMES)}
    values["compression"] = 0.001  # (less than the radius)
    p = registry.to_params(values, radius=0.02, mass=0.0027)
    assert float(p.e) == values["e"] and float(p.mu_t) == values["mu_t"]
    assert float(p.compression) == 0.001 and float(p.contact_radius) == 0.019
    np.testing.assert_array_equal(p.position, [values["x0"], values["y0"], values["z0"]])
    np.testing.assert_array_equal(p.velocity, [values["vx0"], values["vy0"], values["vz0"]])
    np.testing.assert_array_equal(p.spin, [values["spin_x"], values["spin_y"], values["spin_z"]])
    assert float(p.drag_coefficient) == values["drag_coefficient"]
    assert float(p.radius) == 0.02 and float(p.mass) == 0.0027
    vacuum = registry.to_params(values, radius=0.02, scene=estim.load_scene(DROP))
    assert vacuum.mass is None and float(vacuum.drag_coefficient) == 0.47
    np.testing.assert_array_equal(vacuum.spin, [0.0, 0.0, 0.0])
    assert float(vacuum.mu_t) == values["mu_t"] and float(vacuum.mu) == 0.25  # mu: idle there
    table = registry.to_params(values, radius=0.02, mass=0.0027, inertia=2 / 3, scene=estim.load_scene(TABLE))
    assert float(table.mu) == values["mu"] and float(table.mu_t) == 0.95 and float(table.inertia) == 2 / 3
    assert float(table.drag_coefficient) == values["drag_coefficient"]
    # with_values replaces single components and keeps the rest
    q = registry.with_values(p, {"vy0": -2.0, "e": 0.5, "spin_z": 7.0})
    np.testing.assert_array_equal(q.velocity, [values["vx0"], -2.0, values["vz0"]])
    np.testing.assert_array_equal(q.spin, [values["spin_x"], values["spin_y"], 7.0])
    assert float(q.e) == 0.5 and float(q.mu_t) == values["mu_t"]


def test_what_acts_follows_the_law_and_the_air():
    """The law's coefficients act where its ``coefficients`` reads them (traced, not
    declared); the spin acts in air or under a law that couples it; a fit refuses what does
    not act, naming where it would; the default fit follows the law (an opt-in entry, the
    restitution's slope, only where asked)."""
    assert estim.FrictionLaw().reads() == {"e", "mu", "radius", "inertia", "e_slope", "compression"}
    drop, table = estim.load_scene(DROP), estim.load_scene(TABLE)
    assert {"e", "mu_t"} <= registry.acting(drop) and not {"mu", "spin_x", "drag_coefficient"} & registry.acting(drop)
    assert {"e", "mu", "spin_x", "spin_z", "drag_coefficient", "lift_factor"} <= registry.acting(table)
    assert "mu_t" not in registry.acting(table) and "e_slope" in registry.acting(table)
    assert "e_slope" not in registry.acting(drop) and "compression" in registry.acting(drop)
    vacuum_table = table.with_air(None)
    assert {"mu", "spin_y"} <= registry.acting(vacuum_table) and "drag_coefficient" not in registry.acting(vacuum_table)
    with pytest.raises(ValueError, match=r"mu_t acts only under a contact law that reads it \(factor; a scene "
                       r"declares its law with <custom><text name=\"estim:law\" data=\"factor\"/>"):
        registry.check_acting(table, ("e", "mu_t"))
    # The message names the law that reads the parameter, and how a scene declares it.
    with pytest.raises(ValueError, match=r"e_slope acts only .*\(friction; .*data=\"friction\""):
        registry.check_acting(drop, ("e", "e_slope"))
    with pytest.raises(ValueError, match=r"spin_y acts only in a scene with air .* or under a contact law"):
        registry.check_acting(drop, ("spin_y",))
    assert registry.default_free(drop, lateral=False) == ("e", "mu_t", "vx0", "x0", "z0")
    assert registry.default_free(drop, lateral=True)[-2:] == ("y0", "vy0")
    assert registry.default_free(table, lateral=True) == (
        "e", "mu", "x0", "y0", "z0", "vx0", "vy0", "vz0", "spin_x", "spin_y", "spin_z")
    # A side view's pixel track: the law's coefficients and the release in the view's plane.
    assert registry.side_view_free(drop) == ("e", "mu_t", "vx0", "vz0", "x0", "z0")
    assert registry.side_view_free(table) == ("e", "mu", "vx0", "vz0", "x0", "z0")


def test_starting_values_hold_the_data_or_the_default():
    """A fitted component starts from the data; a fixed one is held at the data's start
    (the release point, the horizontal speed) or at its default (vz0 = 0: a release from
    the hand), and a component the data does not give (y of a side view) at its default."""
    ball = estim.Ball("b", 0.02, 0.0027, (0.0, 0.25, 0.5))
    start = initial_guess(*_side_view(), G)
    held = registry.starting_values(ball, start, ("e", "mu_t", "vx0", "x0", "z0"))
    assert held["vz0"] == 0.0 and held["y0"] == 0.25 and held["vy0"] == 0.0
    assert held["vx0"] == start.vx0 and held["x0"] == start.x0 and held["e"] == start.e
    assert held["drag_coefficient"] == 0.47 and held["t0"] == 0.0 and held["spin_y"] == 0.0
    free = registry.starting_values(ball, start, ("e", "vz0"))
    assert free["vz0"] == start.vz0 and free["x0"] == start.x0


def _side_view():
    t = np.arange(0.0, 0.3, 1 / 120)
    return t, 0.1 + 0.8 * t, 0.5 + 0.4 * t - 0.5 * G * t * t


def test_caption_and_table_columns():
    values = {"e": 0.58, "mu_t": 0.95, "vx0": 0.5, "vy0": 1.25, "x0": 0.0, "drag_coefficient": 0.5}
    assert registry.describe(values) == "e = 0.580   mu_t = 0.950   vx0 = 0.500 m/s"
    assert registry.describe(values, ("vy0", "x0", "drag_coefficient"), sep=", ") == (
        "e = 0.580, mu_t = 0.950, vx0 = 0.500 m/s, vy0 = 1.250 m/s, drag_coefficient = 0.500")
    assert registry.component("vx0").label("vx0") == "vx0 (m/s)"


# --------------------------------------------------------------------------- starts


def _throw(velocity, position=(0.05, -0.6, 0.5), e=0.82, mu_t=0.9, t_end=1.2, noise=1e-3, seed=3):
    """A ping-pong ball thrown on the drop scene's table (z = 0), 120 fps, Gaussian noise."""
    scene = estim.load_scene(DROP)
    p = estim.Params.for_ball(scene, "pingpong", e=e, mu_t=mu_t, position=position, velocity=velocity)
    t = np.arange(0.0, t_end + 1e-9, 1 / 120)
    exact = np.asarray(estim.simulate(scene, p, t_end, ts=jnp.asarray(t)).position)
    return t, exact + np.random.default_rng(seed).normal(0.0, noise, exact.shape)


@pytest.mark.parametrize("velocity", [(0.0, 0.9, 0.0), (0.54, 0.72, 0.0), (-0.3, -0.4, 0.0)])
def test_start_in_the_plane_of_travel(velocity):
    """A throw along y (and two diagonal ones): the start reads the release state in 3D,
    e and mu_t from the bounces (mu_t from the speed along the direction of travel: a
    projection on x would see no speed and read no mu_t), the direction of travel."""
    position = (0.05, -0.6, 0.5) if velocity[1] > 0 else (0.3, 0.4, 0.5)
    t, obs = _throw(velocity, position)
    s = release_start(t, obs, (0.0, 0.0, -G))
    assert len(s.bounces) == 2
    assert s.e == pytest.approx(0.82, abs=0.01)
    assert s.mu_t == pytest.approx(0.9, abs=0.01)
    np.testing.assert_allclose(s.position, position, atol=2e-3)
    np.testing.assert_allclose(s.velocity, velocity, atol=0.01)
    u = np.asarray(velocity) / np.linalg.norm(velocity)
    np.testing.assert_allclose(s.direction, u, atol=2e-3)
    assert s.noise == pytest.approx(1e-3, rel=0.15)


@pytest.mark.parametrize("curved", [False, True])
def test_start_reads_the_noise_across_lost_rows(curved):
    """The throw with a fifth of its rows lost (NaN, at random): the start reads the noise
    it reads from every row, 1 mm to 15% (the differences across a lost row are divided
    differences, estim.tracks._flights.robust_noise), and the same bounces."""
    t, obs = _throw((0.54, 0.72, 0.0))
    lost = obs.copy()
    lost[np.random.default_rng(4).random(t.size) < 0.2] = np.nan
    whole = release_start(t, obs, (0.0, 0.0, -G), curved=curved)
    s = release_start(t, lost, (0.0, 0.0, -G), curved=curved)
    assert whole.noise == pytest.approx(1e-3, rel=0.15)
    assert s.noise == pytest.approx(1e-3, rel=0.15)
    assert len(s.bounces) == len(whole.bounces) == 2


def test_start_follows_the_gravity_vector():
    """The same throw in a frame turned by a rotation R (data R p, gravity R g): the starts
    turn with it (positions and velocities R times the upright ones, e and mu_t the same),
    to rounding."""
    t, obs = _throw((0.54, 0.72, 0.0))
    upright = release_start(t, obs, (0.0, 0.0, -G))
    a, b = 0.7, -0.4  # a rotation about x, then about z
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    rz = np.array([[math.cos(b), -math.sin(b), 0], [math.sin(b), math.cos(b), 0], [0, 0, 1]])
    rot = rz @ rx
    turned = release_start(t, obs @ rot.T, rot @ np.array([0.0, 0.0, -G]))
    assert turned.e == pytest.approx(upright.e, rel=1e-9)
    assert turned.mu_t == pytest.approx(upright.mu_t, rel=1e-9)
    np.testing.assert_allclose(turned.position, rot @ np.asarray(upright.position), atol=1e-9)
    np.testing.assert_allclose(turned.velocity, rot @ np.asarray(upright.velocity), atol=1e-9)
    np.testing.assert_allclose(turned.direction, rot @ np.asarray(upright.direction), atol=1e-9)


def test_side_view_start_is_the_x_z_reading():
    """A track without y is read in the x-z plane exactly as before (``initial_guess``),
    and needs gravity along -z."""
    t, x, z = _side_view()
    pos = np.stack([x, np.full_like(t, np.nan), z], axis=1)
    s = release_start(t, pos, (0.0, 0.0, -G))
    assert s == initial_guess(t, x, z, G)
    assert s.y0 is None and s.vy0 is None and s.direction == (1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="needs gravity along -z"):
        release_start(t, pos, (0.0, -G, 0.0))


# --------------------------------------------------------------------------- starts under the friction law


def _shot(scene, spin, mu=0.18, t_end=0.5, noise=0.0):
    """A table-tennis drive (one bounce on the far half), sampled at 180 Hz."""
    p = estim.Params.for_ball(scene, "pingpong", e=0.88, mu_t=1.0, mu=mu, position=(0.2, -1.6, 0.2),
                              velocity=(-0.3, 8.0, 2.0), spin=spin)
    t = np.arange(0.0, t_end, 1 / 180)
    pos = np.asarray(estim.simulate(scene, p, t_end, ts=t).position)
    return t, pos + np.random.default_rng(3).normal(0.0, noise, pos.shape)


def test_spin_for_lift_inverts_the_magnus_law():
    """Eq. (3) of estim.model._air forward (drag included, which the inverse must ignore),
    then inverted: the spin across the velocity comes back, on both pieces of C_L(S)."""
    from estim.model._air import Air, air_acceleration, spin_for_lift

    air, v = Air(1.2, 1.8e-5, (0.5, 0.0, 0.0)), np.array([0.3, 8.0, 1.0])
    w_rel = v - np.asarray(air.wind)
    for spin in ((0.0, 30.0, -10.0), (-200.0, 5.0, 30.0), (40.0, -300.0, 5.0)):
        spin = np.asarray(spin) - (np.asarray(spin) @ w_rel) / (w_rel @ w_rel) * w_rel  # across w
        a = np.asarray(air_acceleration(air, 0.02, 0.0027, 0.4, spin, v, 0.9))
        np.testing.assert_allclose(spin_for_lift(air, 0.02, 0.0027, v, a, 0.9), spin, rtol=1e-9, atol=1e-9)


def test_spin_and_friction_starts_of_a_shot():
    """On a shot simulated with known spin and mu (2 mm noise): the spin start read off the
    first flight's curvature is within 10% of the spin across the velocity, and mu's start
    from the velocity jump at the bounce within 0.03 (the ball slides throughout); with a
    mu so large that the ball grips, the start is a lower bound."""
    from estim.fitting._initial import spin_start

    scene = estim.load_scene(TABLE)
    spec = scene.ball("pingpong")
    spin = np.array([-120.0, 0.0, 15.0])
    t, pos = _shot(scene, spin, noise=0.002)
    init = release_start(t, pos, (0.0, 0.0, -G))
    assert len(init.bounces) == 1 and init.mu == pytest.approx(0.18, abs=0.03)
    start = np.asarray(spin_start(init, t, pos, (0.0, 0.0, -G), scene.air, spec.radius, spec.mass))
    v = np.array([-0.3, 8.0, 2.0])
    across = spin - (spin @ v) / (v @ v) * v
    assert np.linalg.norm(start - across) <= 0.1 * np.linalg.norm(across)
    t, pos = _shot(scene, spin, mu=0.7)
    assert release_start(t, pos, (0.0, 0.0, -G)).mu < 0.7


def test_a_track_that_starts_on_a_tread_is_released_from_it():
    """A golf ball released on step2's top of the seed's staircase, sliding at (0.4, 0.05)
    m/s: 1 s on the tread, off its end, down the stairs (60 fps, 2 mm noise). The start
    reads that run (``Initial.rest``: its times, the release point and speed the
    simulation was given), the fit finds the tread under it (``_on_surface``: step2, the
    centre one radius above its top) and releases the ball from there, z0 and vz0 held.
    The same track 30 cm higher (a ball held still in the air) has the run but no surface
    under it: its start stays the first flight's. Without the run, the first flight's
    parabola carried back to t = 0 started the ball 4.9 m below the tread, thrown up at
    9.8 m/s, and the fit ended 2.4 m off in z0 (tests/test_fit.py fits this track)."""
    t, obs, scene = _tread_track()
    s = release_start(t, obs, (0.0, 0.0, -G))
    assert s.rest is not None and s.rest.start == 0.0
    assert s.rest.stop == pytest.approx(1.0, abs=0.06)  # it leaves the edge 0.4 m on at 0.4 m/s
    np.testing.assert_allclose(s.rest.position, (0.5, 0.1, 1.25), atol=2e-3)
    np.testing.assert_allclose(s.rest.velocity, (0.4, 0.05, 0.0), atol=5e-3)
    spec = scene.ball("golf")
    free = ("e", "mu_t", "x0", "y0", "z0", "vx0", "vy0")
    assert _fit._on_surface(scene, spec, s, free, {}) == ("step2", 1.25)
    released = s.released_from_rest(1.25)
    assert released.position == (*s.rest.position[:2], 1.25) and released.velocity == s.rest.velocity
    assert _fit._on_surface(scene, spec, s, free, {"z0": 1.3}) is None  # the caller's z0 wins
    higher = release_start(t, obs + (0.0, 0.0, 0.3), (0.0, 0.0, -G))
    assert higher.rest is not None and _fit._on_surface(scene, spec, higher, free, {}) is None
    assert higher.z0 == pytest.approx(s.z0 + 0.3, abs=1e-9)  # the flight's start


def _tread_track():
    scene = estim.load_scene(ROOT / "data" / "scenes" / "stairs.xml")
    p = estim.Params.for_ball(scene, "golf", e=0.5, mu_t=0.9, position=(0.5, 0.1, 1.25), velocity=(0.4, 0.05, 0.0))
    t = np.arange(0.0, 2.5, 1 / 60)
    exact = np.asarray(estim.simulate(scene, p, 2.5, ts=jnp.asarray(t)).position)
    return t, exact + np.random.default_rng(0).normal(0.0, 2e-3, exact.shape), scene
