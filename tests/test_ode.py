"""The ODE path (scenes with air): against closed forms, the closed-form path, MuJoCo and
finite differences.

Every call here uses a batch of three balls and the default sample times, so the whole file
compiles the ODE program once per scene structure (vacuum / air) and once for jacfwd.
"""

import collections

import diffrax
import jax
import jax.extend
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import ROOT

import estim
from estim.forward import _ode

SEED = {"bocce": 0.55, "golf": 0.70, "pingpong": 0.85}
G = 9.81


@pytest.fixture(scope="module")
def stairs():
    return estim.load_scene(ROOT / "data" / "scenes" / "stairs.xml")


@pytest.fixture(scope="module")
def stairs_air():
    return estim.load_scene(ROOT / "data" / "scenes" / "stairs_air.xml")


def seed_params(scene, vx0=1.15, e=None, mu_t=0.98, **kw):
    """The three balls of the seed, released as in the seed notebook."""
    rows = []
    for name, e_seed in SEED.items():
        b = scene.ball(name)
        rows.append(estim.Params.for_ball(
            scene, name, e=e_seed if e is None else e, mu_t=mu_t, velocity=(vx0, 0.0, 0.0),
            position=(-0.20, 0.0, 1.40 + b.radius + 0.25), **kw))
    return jax.tree.map(lambda *x: jnp.stack(x), *rows)


def test_scene_without_air_never_traces_the_ode_solver(stairs, stairs_air):
    before = _ode.TRACE_COUNT
    traj = estim.simulate(stairs, seed_params(stairs), 2.3)
    assert np.asarray(traj.events.count).tolist() == [9, 6, 4]  # the closed-form seed numbers
    assert _ode.TRACE_COUNT == before
    # ... while a scene with air does (traced only, not compiled, with a fresh step budget).
    params = seed_params(stairs_air)
    jax.make_jaxpr(lambda: estim.simulate(stairs_air, params, 2.3, max_steps=77))()
    assert _ode.TRACE_COUNT == before + 1


def test_ode_path_without_air_matches_closed_form(stairs):
    """Forced onto the ODE path, a vacuum gives parabolas, which every Runge-Kutta method of
    order >= 2 integrates exactly: the two paths agree to rounding."""
    params = seed_params(stairs)
    exact = estim.simulate(stairs, params, 2.3)
    ode = estim.simulate(stairs, params, 2.3, solver=diffrax.Tsit5())
    assert np.asarray(ode.events.count).tolist() == [9, 6, 4]
    np.testing.assert_allclose(ode.final.position, exact.final.position, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ode.events.t[:, :4], exact.events.t[:, :4], rtol=0, atol=1e-10)
    # Dense output at the contact times and in between.
    ts = jnp.linspace(0.0, 2.3, 47)
    np.testing.assert_allclose(ode.evaluate(ts)[0], exact.evaluate(ts)[0], rtol=0, atol=1e-9)


def test_zeno_example_rests_on_ode_path(stairs):
    """The Zeno golf ball of the issue: at rest on the second tread at x ~ 0.733, t ~ 1.298,
    on the ODE path too (the series is summed in closed form, not stepped through)."""
    params = seed_params(stairs, vx0=0.801, e=0.518, mu_t=0.966)
    exact = estim.simulate(stairs, params, 2.3)
    ode = estim.simulate(stairs, params, 2.3, solver=diffrax.Tsit5())
    np.testing.assert_allclose(ode.final.position[1], exact.final.position[1], rtol=0, atol=1e-9)
    assert ode.final.position[1, 0] == pytest.approx(0.7334, abs=1e-4)
    settle = np.asarray(ode.events.kind[1]) == 1
    assert settle.any() and float(ode.events.t[1][settle][0]) == pytest.approx(1.2978, abs=1e-4)
    assert np.all(np.asarray(ode.complete))


def quadratic_fall(scene, params, drop):
    """First contact of a ball released from rest ``drop`` m above its contact height, under
    gravity and quadratic drag only: z = z0 - (vt^2/g) ln cosh(g t / vt) with terminal
    speed vt = sqrt(2 m g / (rho C_D A))."""
    rho = float(scene.air.density)
    area = np.pi * np.asarray(params.radius) ** 2
    vt = np.sqrt(2 * np.asarray(params.mass) * G / (rho * np.asarray(params.drag_coefficient) * area))
    t = vt / G * np.arccosh(np.exp(G * drop / vt**2))
    return t, vt * np.tanh(G * t / vt)


def test_vertical_fall_with_quadratic_drag_matches_closed_form(stairs):
    scene = stairs.with_air(estim.Air(density=1.204))
    drop = 0.9
    rows = [estim.Params.for_ball(scene, n, e=0.5, mu_t=0.9,
                                  position=(0.0, 0.0, 1.40 + scene.ball(n).radius + drop))
            for n in SEED]
    params = jax.tree.map(lambda *x: jnp.stack(x), *rows)
    traj = estim.simulate(scene, params, 0.8, rtol=1e-11, atol=1e-12)
    t_c, v_c = quadratic_fall(scene, params, drop)
    np.testing.assert_allclose(traj.events.t[:, 0], t_c, rtol=1e-9)
    np.testing.assert_allclose(-traj.events.velocity_pre[:, 0, 2], v_c, rtol=1e-9)
    # Drag matters for the 5 g ping-pong ball, hardly for the 0.92 kg bocce ball.
    t_vac = np.sqrt(2 * drop / G)
    assert (t_c[2] - t_vac) > 20 * (t_c[0] - t_vac) > 0


def test_vertical_fall_with_linear_drag_matches_closed_form(stairs):
    """z = z0 - (g/k) t + (g/k^2)(1 - exp(-k t)), k = 6 pi eta r / m (Stokes)."""
    eta = 5e-3  # a viscous fluid, so that the effect is large
    scene = stairs.with_air(estim.Air(viscosity=eta))
    drop = 0.9
    rows = [estim.Params.for_ball(scene, n, e=0.5, mu_t=0.9,
                                  position=(0.0, 0.0, 1.40 + scene.ball(n).radius + drop))
            for n in SEED]
    params = jax.tree.map(lambda *x: jnp.stack(x), *rows)
    traj = estim.simulate(scene, params, 1.5, rtol=1e-11, atol=1e-12)
    k = 6 * np.pi * eta * np.asarray(params.radius) / np.asarray(params.mass)
    t = np.full(3, np.sqrt(2 * drop / G))
    for _ in range(50):  # Newton on the closed form
        fall = G / k * t - G / k**2 * (1 - np.exp(-k * t)) - drop
        speed = G / k * (1 - np.exp(-k * t))
        t = t - fall / speed
    np.testing.assert_allclose(traj.events.t[:, 0], t, rtol=1e-9)
    np.testing.assert_allclose(-traj.events.velocity_pre[:, 0, 2], speed, rtol=1e-8)


def test_magnus_flight_matches_closed_form(stairs):
    """With spin omega along y, no drag and low spin ratio (C_L = 1.5 S), the velocity obeys
    v' = g + W x v, W = (3 rho A r / (4 m)) omega: in the xz-plane u = vx + i vz rotates,
    u(t) = (u0 + g/W) exp(-i W t) - g/W, and x + i z integrates it."""
    scene = stairs.with_air(estim.Air(density=1.204))
    omega = 3.0
    rows = [estim.Params.for_ball(scene, n, e=0.5, mu_t=0.9, velocity=(3.0, 0.0, 1.0),
                                  position=(-0.2, 0.0, 2.2), drag_coefficient=0.0,
                                  spin=(0.0, s * omega, 0.0))
            for n, s in zip(SEED, (1.0, -1.0, 1.0), strict=True)]
    params = jax.tree.map(lambda *x: jnp.stack(x), *rows)
    traj = estim.simulate(scene, params, 1.0, rtol=1e-11, atol=1e-12)
    r, m = np.asarray(params.radius), np.asarray(params.mass)
    w = 3 * 1.204 * np.pi * r**2 * r / (4 * m) * omega * np.array([1.0, -1.0, 1.0])
    ts = np.linspace(0.0, 0.15, 7)  # before any contact
    u0 = 3.0 + 1.0j
    z = (-0.2 + 2.2j) + (u0 + G / w[:, None]) * (1 - np.exp(-1j * w[:, None] * ts)) / (1j * w[:, None]) - G / w[:, None] * ts
    assert float(traj.events.t[:, 0].min()) > 0.15
    speed = 3.0  # |v| >= vx ~ 3 m/s: the spin ratio r omega / |v| stays below 0.1, C_L = 1.5 S
    assert np.all(r * omega / speed < 0.1)
    pos = np.asarray(traj.evaluate(jnp.asarray(ts))[0])
    np.testing.assert_allclose(pos[..., 0], z.real, rtol=0, atol=1e-9)
    np.testing.assert_allclose(pos[..., 2], z.imag, rtol=0, atol=1e-9)
    # Moving along +x, spin along -y is backspin and lifts; along +y, topspin, dips.
    z_vacuum = 2.2 + u0.imag * ts[-1] - 0.5 * G * ts[-1] ** 2
    assert pos[1, -1, 2] > z_vacuum > pos[0, -1, 2]


def test_air_matches_mujoco_fluid_model():
    """MuJoCo's inertia-box fluid model for a sphere is estim's quadratic drag with
    C_D = 2.4 / pi (per axis) and Stokes drag times sqrt(12/5) / 2 (see estim.model._air):
    check both against MuJoCo's own acceleration for a ball moving along x."""
    r, m, v = 0.02, 0.0027, 5.0
    for density, viscosity in ((1.2, 0.0), (0.0, 1.8e-5)):
        xml = f"""<mujoco><option gravity="0 0 0" density="{density}" viscosity="{viscosity}"/>
        <worldbody><body><freejoint/><geom type="sphere" size="{r}" mass="{m}"/></body>
        </worldbody></mujoco>"""
        model = mujoco.MjModel.from_xml_string(xml)
        data = mujoco.MjData(model)
        data.qvel[:3] = [v, 0, 0]
        mujoco.mj_forward(model, data)
        air = estim.Air(density=density, viscosity=viscosity * np.sqrt(12 / 5) / 2)
        a = estim.air_acceleration(air, r, m, 2.4 / np.pi, jnp.zeros(3), jnp.array([v, 0.0, 0.0]))
        np.testing.assert_allclose(float(a[0]), data.qacc[0], rtol=1e-12)


def test_magnus_flight_matches_mujocos_ellipsoid_fluid_model(stairs):
    """MuJoCo's ellipsoid fluid model with only its Magnus term (``fluidcoef="0 0 0 0 1"``),
    net of the sphere's added mass, is estim's Magnus force with ``f_L kappa = 4/3``
    (estim.model._air): at spin ratios below 0.1 (kappa = 1.5) a lift factor of 8/9. A
    spinning throw, 0.4 s, MuJoCo's own RK4 at 20 us against estim's ODE path: the same
    flight to 1e-6 m, where the Magnus force moves the ball by 7 cm."""
    r, m, t_end = 0.02, 0.0027, 0.4
    v0, w0 = np.array([6.0, 0.0, 1.0]), np.array([0.0, -20.0, 5.0])  # r |w| / |v| < 0.1
    xml = f"""<mujoco><option timestep="2e-5" density="1.2" viscosity="0" integrator="RK4"/>
    <worldbody><body pos="0 0 1"><freejoint/><geom type="sphere" size="{r}" mass="{m}" shellinertia="true"
    fluidshape="ellipsoid" fluidcoef="0 0 0 0 1" contype="0" conaffinity="0"/></body></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    data.qvel[:] = [*v0, *w0]  # (the free joint's angular velocity is in the body frame, here the world's)
    for _ in range(round(t_end / model.opt.timestep)):
        mujoco.mj_step(model, data)
    np.testing.assert_allclose(data.qvel[3:], w0, atol=1e-9)  # no torque: the spin is constant
    scene = stairs.with_air(estim.Air(density=1.2))
    release = dict(radius=r, position=(-3.0, 0.0, 3.0), velocity=v0, mass=m, drag_coefficient=0.0)
    spun = estim.simulate(scene, estim.Params(0.5, 1.0, spin=w0, lift_factor=8 / 9, **release), t_end,
                          rtol=1e-10, atol=1e-12)
    plain = estim.simulate(scene, estim.Params(0.5, 1.0, **release), t_end)
    moved = np.asarray(spun.final.position) - np.asarray(plain.final.position)
    assert np.linalg.norm(moved) > 0.07
    np.testing.assert_allclose(np.asarray(spun.final.position) - [-3.0, 0.0, 2.0], data.qpos[:3], rtol=0, atol=1e-6)


def test_drag_changes_the_stairs_and_event_times_converge(stairs, stairs_air):
    params = seed_params(stairs_air)
    vac = estim.simulate(stairs, seed_params(stairs), 2.3)
    ref = estim.simulate(stairs_air, params, 2.3, rtol=1e-12, atol=1e-13)
    assert np.all(np.asarray(ref.complete))
    shift = np.abs(np.asarray(ref.events.t[:, 1] - vac.events.t[:, 1]))
    assert shift[2] > shift[0]  # the light ball feels the air more
    errors = []
    for rtol in (1e-5, 1e-7, 1e-9):
        traj = estim.simulate(stairs_air, params, 2.3, rtol=rtol, atol=rtol * 0.1)
        errors.append(float(np.max(np.abs(np.asarray(traj.events.t[:, :3] - ref.events.t[:, :3])))))
    assert errors[2] <= errors[1] <= errors[0] + 1e-12, errors
    assert errors[2] < 1e-8, errors


def test_drag_gradients_match_finite_differences(stairs_air):
    """d(final x, second bounce time)/d(e, mu_t, vx0, C_D), ping-pong ball, by jacfwd through
    the ODE path and by central differences at tight tolerances."""
    base = seed_params(stairs_air)

    def out(theta):
        params = estim.Params(
            base.e.at[2].set(theta[0]), base.mu_t.at[2].set(theta[1]), base.radius,
            base.position, base.velocity.at[2, 0].set(theta[2]), mass=base.mass,
            drag_coefficient=base.drag_coefficient.at[2].set(theta[3]), spin=base.spin,
        )
        traj = estim.simulate(stairs_air, params, 2.3, rtol=1e-12, atol=1e-13)
        return jnp.stack([traj.final.position[2, 0], traj.events.t[2, 1]])

    theta = jnp.array([0.85, 0.98, 1.15, 0.47])
    jac = np.asarray(jax.jacfwd(out)(theta))
    assert np.all(np.isfinite(jac))
    eps = 1e-6
    fd = np.stack([(out(theta.at[i].add(eps)) - out(theta.at[i].add(-eps))) / (2 * eps)
                   for i in range(4)], axis=1)
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-7)


def _scan_lengths(jaxpr) -> collections.Counter:
    """How many scans of each length a jaxpr holds, sub-jaxprs (loops, branches) included."""
    lengths = collections.Counter()
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "scan":
            lengths[eqn.params["length"]] += 1
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            lengths += _scan_lengths(sub)
    return lengths


def test_the_primal_runs_the_plan_alone_and_derivatives_replay_it(stairs_air):
    """A primal call reuses the nodes the step loop recorded (no replay, a scan over the
    ``MAX_STEPS / REPLAY_CHUNK`` chunks of steps, in its program); a derivative replays the steps, whose values are the plan's to rounding
    (an event step's end moves by a Newton step of the plan's residual)."""
    params = seed_params(stairs_air)
    primal = jax.make_jaxpr(lambda p: estim.simulate(stairs_air, p, 2.3).record)(params)
    tangent = jax.make_jaxpr(lambda p: jax.jvp(lambda q: estim.simulate(stairs_air, q, 2.3).record, (p,), (p,)))(params)
    chunks = _ode.MAX_STEPS // _ode.REPLAY_CHUNK
    assert _scan_lengths(primal.jaxpr)[chunks] == 0
    assert _scan_lengths(tangent.jaxpr)[chunks] == 1

    settings = _ode.OdeSettings(diffrax.Tsit5(), jnp.asarray(_ode.RTOL), jnp.asarray(_ode.ATOL),
                                jnp.asarray(_ode.SLACK), _ode.MAX_STEPS)
    ball = jax.tree.map(lambda x: x[1], params)
    pl = _ode.plan(stairs_air, ball, 2.3, settings)
    end, nodes = _ode.replay(stairs_air, ball, 2.3, pl.steps, settings, pl.n_steps)
    assert int(pl.n_steps) > 50 and int(np.sum(np.asarray(pl.steps.kind) == _ode.STEP_CONTACT)) >= 5
    n = int(pl.n_steps)
    used = jax.tree.map(lambda x: x[:n], (pl.nodes, nodes))
    for got, want in zip(jax.tree.leaves((pl.end.position, pl.end.velocity, used[0])),
                         jax.tree.leaves((end.position, end.velocity, used[1])), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)
    # The values a derivative returns are the primal's, exactly (under the same compile
    # options: XLA's level 0, which a first call at top level has, rounds differently).
    def final(p):
        return estim.simulate(stairs_air, p, 2.3).final.position

    value = jax.jit(lambda p: jax.jvp(final, (p,), (p,))[0])(params)
    np.testing.assert_array_equal(value, jax.jit(final)(params))


def test_a_top_level_call_runs_the_step_loop_and_what_follows_as_two_programs_compiled_at_once(stairs_air):
    """At top level the ODE path is two programs (``_simulate._ode_plans``, the step loops,
    and ``_ode_finish``, samples, events and packing), both compiled on the first call, the
    step loop's on a thread while the second is traced from its shapes alone; their rows
    are those of the one program that a user's jit gets, compiled with the same options,
    to rounding (the two compile into different fusions)."""
    from estim.forward import _simulate

    params = seed_params(stairs_air, vx0=1.05)  # (a signature of its own: compiled here)
    ts = np.linspace(0.0, 2.3, 31)
    args = []
    apart = _simulate._solve_ode_apart

    def spy(*a):
        args.append(a)
        return apart(*a)

    _simulate._solve_ode_apart = spy
    try:
        traj = estim.simulate(stairs_air, params, 2.3, ts=ts)
    finally:
        _simulate._solve_ode_apart = apart
    (scene, prm, t_end, ts_, settings, max_events, checks, keep), = args
    # Both programs were compiled ahead: a second call compiles neither again.
    assert _simulate._ode_plans.ahead(scene, prm, t_end, settings) is None
    plans = _simulate._ode_plans(scene, prm, t_end, settings)
    assert _simulate._ode_finish.ahead(scene, prm, t_end, ts_, settings, plans, max_events=max_events,
                                       checks=checks, keep=keep) is None
    one = _simulate.solve_ode(scene, prm, t_end, ts_, settings, max_events, checks, keep)
    np.testing.assert_array_equal(traj.flags, one.flags)
    np.testing.assert_allclose(traj.record, one.record, rtol=1e-14, atol=1e-15)
    assert np.asarray(traj.events.count).tolist() == np.asarray(one.events.count).tolist()
    assert np.all(np.asarray(traj.complete))
