"""The air path's contact guarantee (estim.forward._ode): steps as long as the tolerance
allows away from solids, and still no contact skipped.

The truths:

- the step bound (4) of ``estim.model._air.step_bounds`` against an independent
  integration (diffrax Dopri8 at rtol 1e-13) of the same flights;
- the first contact of random fast, spinning throws in still air with wind against a
  diffrax integration with a step cap of 0.2 ms and an event on the distance to every solid
  (the L1 contact region of ``estim.model._scene``, eq. (1), written out here in numpy
  terms), so that a contact estim's long steps skipped would show as an earlier contact
  there;
- the dense solution sampled finely never inside a solid.
"""

import diffrax
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import optimistix as optx
import pytest
from conftest import ROOT

import estim
from estim.forward._constants import STEP_EXIT
from estim.model._air import Air, acceleration, step_bounds

G = 9.81
# A table-tennis ball (ITTF: 40 mm, 2.7 g), the lightest and most air-driven of balls.
RADIUS, MASS = 0.02, 0.0027


@pytest.fixture(scope="module")
def windy():
    scene = estim.load_scene(ROOT / "data" / "scenes" / "stairs_air.xml")
    return scene.with_air(Air(density=1.204, viscosity=1.81e-5, wind=(-3.0, 2.0, 0.5)))


def _throws(n, seed):
    """Random throws above the staircase: speeds up to 25 m/s in any direction (into
    risers, up the stairs, down at the treads), spins up to 400 rad/s."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.25, 2.6, n)
    top = 1.4 - 0.2 * np.clip(np.floor((x - RADIUS + 0.3) / 0.6), 0, 4)  # the higher tread within r
    pos = np.stack([x, rng.uniform(-0.4, 0.4, n), top + RADIUS + rng.uniform(0.01, 0.6, n)], axis=1)
    d = rng.normal(size=(n, 3))
    vel = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.5, 25.0, n)[:, None]
    spin = rng.normal(size=(n, 3)) * 150.0
    return estim.Params(np.full(n, 0.8), np.full(n, 0.9), np.full(n, RADIUS), pos, vel, mass=np.full(n, MASS),
                        drag_coefficient=np.full(n, 0.5), spin=spin, mu=np.zeros(n), inertia=np.full(n, 0.4),
                        lift_factor=np.ones(n), e_slope=np.zeros(n), compression=np.zeros(n))


def test_step_bound_holds_against_an_independent_integration(windy):
    """|q(tau) - q_par(tau)| <= L A tau^3 / 6 along flights of 1 ms to 0.3 s."""
    params = _throws(24, seed=1)
    air = windy.air
    taus = jnp.linspace(0.0, 1.0, 41)

    def one(prm, h):
        def f(t, y, args):
            return jnp.concatenate([y[3:], acceleration(air, G, prm.radius, prm.mass, prm.drag_coefficient,
                                                        prm.spin, y[3:])])

        y0 = jnp.concatenate([prm.position, prm.velocity])
        sol = diffrax.diffeqsolve(diffrax.ODETerm(f), diffrax.Dopri8(), 0.0, h, h / 50, y0,
                                  saveat=diffrax.SaveAt(ts=taus * h),
                                  stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-15),
                                  max_steps=100_000)
        a0 = f(0.0, y0, None)[3:]
        t = taus * h
        par = prm.position + prm.velocity * t[:, None] + 0.5 * a0 * t[:, None] ** 2
        dev = jnp.linalg.norm(sol.ys[:, :3] - par, axis=1)
        a_max, lip = step_bounds(air, G, prm.radius, prm.mass, prm.drag_coefficient, prm.spin, prm.velocity, h)
        return dev, lip * a_max * t**3 / 6.0

    for h in (1e-3, 1e-2, 0.1, 0.3):
        dev, bound = jax.jit(jax.vmap(lambda p, h=h: one(p, h)))(params)
        dev, bound = np.asarray(dev), np.asarray(bound)
        assert np.all(dev <= bound * (1 + 1e-9) + 1e-13), (h, np.max(dev - bound))
        # ... and not vacuous: the bound is within a factor 1000 of the deviation at the end.
        assert np.all(bound[:, -1] < 1e3 * dev[:, -1] + 1e-12), h


def _fine_first_contact(scene, params, t_end):
    """First contact time of each throw by a plain diffrax loop with steps of at most
    0.2 ms and an event on ``min over solids (L1 excess) - r``, which is negative exactly
    inside estim's contact region of a box (eq. (1) of estim.model._scene) or below a
    plane."""
    c, h = scene.box_centre, scene.box_half
    n, s = scene.plane_normal, scene.plane_offset

    def one(prm):
        def f(t, y, args):
            return jnp.concatenate([y[3:], acceleration(scene.air, G, prm.radius, prm.mass, prm.drag_coefficient,
                                                        prm.spin, y[3:])])

        def gap(t, y, args, **kw):
            q = y[:3]
            excess = jnp.sum(jnp.maximum(jnp.abs(q - c) - h, 0.0), axis=1)
            planes = q @ n.T - s
            return jnp.minimum(jnp.min(excess), jnp.min(planes)) - prm.radius

        y0 = jnp.concatenate([prm.position, prm.velocity])
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(f), diffrax.Tsit5(), 0.0, t_end, 1e-4, y0,
            stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-13, dtmax=2e-4),
            event=diffrax.Event(gap, root_finder=optx.Newton(rtol=1e-13, atol=1e-14)), max_steps=20_000,
            throw=False)
        return jnp.where(sol.event_mask, sol.ts[-1], jnp.inf)

    return np.asarray(jax.jit(jax.vmap(one))(params))


def test_no_contact_skipped_on_fast_spinning_throws(windy):
    """Random fast throws with spin in wind: estim's first contact (default settings, long
    steps away from solids) is the fine loop's, to 1e-8 s, and its face is on the solid the
    fine loop's path touches."""
    params = _throws(64, seed=2)
    t_end = 1.0
    traj = estim.simulate(windy, params, t_end, max_events=4)
    first = np.where(np.asarray(traj.events.count) > 0, np.asarray(traj.events.t[:, 0]), np.inf)
    fine = _fine_first_contact(windy, params, t_end)
    hit = np.isfinite(fine)
    assert hit.sum() >= 40  # most throws reach a solid within t_end
    np.testing.assert_array_equal(np.isfinite(first), hit)
    assert np.max(np.abs(first[hit] - fine[hit])) < 1e-8
    # The solver took long steps: far fewer than the fine loop's 0.2 ms cap would need.
    steps = np.asarray(jnp.sum(traj.solution.steps.kind < 5, axis=-1))
    assert np.median(steps) < 0.1 * t_end / 2e-4


def test_dense_solution_never_inside_a_solid(windy):
    """Sampled every 0.1 ms over 1.5 s, no throw's centre is inside a solid's contact region
    by more than 1e-9 m (the L1 excess of eq. (1), estim.model._scene)."""
    params = _throws(16, seed=3)
    ts = np.linspace(0.0, 1.5, 15_001)
    traj = estim.simulate(windy, params, 1.5, ts=ts, keep=("samples",))
    q = np.asarray(traj.position)  # (balls, times, 3)
    c, h = np.asarray(windy.box_centre), np.asarray(windy.box_half)
    excess = np.maximum(np.abs(q[:, :, None, :] - c) - h, 0.0).sum(axis=-1).min(axis=-1)
    ground = q[:, :, 2]
    depth = RADIUS - np.minimum(excess, ground)
    assert np.max(depth) < 1e-9, np.max(depth)


@pytest.mark.parametrize("delta", [1e-9, 1e-7, 1e-5, -1e-7, -1e-5])
def test_fall_grazing_a_tread_edge(delta):
    """A ball dropped in still air (quadratic drag only: it falls straight down) with its
    centre ``r + delta`` beyond the edge of tread 1 (exact edges). With delta > 0 it passes
    the tread and lands on tread 2; with delta < 0 it meets tread 1's round edge where its
    distance from the edge line, ``sqrt((r + delta)^2 + (z - top)^2)``, reaches r. The truth
    is the closed form of the fall, ``z(t) = z0 - ln cosh(t sqrt(g k)) / k``."""
    scene = estim.load_scene(ROOT / "data" / "scenes" / "stairs_exact.xml").with_air(Air(density=1.204))
    z0, x = 1.7, 0.3 + RADIUS + delta
    prm = estim.Params(0.8, 0.9, RADIUS, (x, 0.0, z0), (0.0, 0.0, 0.0), mass=MASS, drag_coefficient=0.5)
    traj = estim.simulate(scene, prm, 0.8, max_events=4)
    k = 1.204 * 0.5 * np.pi * RADIUS**2 / (2 * MASS)
    landing = 1.4 + np.sqrt(RADIUS**2 - (RADIUS + delta) ** 2) if delta < 0 else 1.2 + RADIUS
    t_true = np.arccosh(np.exp(k * (z0 - landing))) / np.sqrt(G * k)
    assert int(traj.events.count) >= 1
    assert abs(float(traj.events.t[0]) - t_true) < 1e-9
    assert scene.face_label(int(traj.events.face[0]))[0] == ("step1" if delta < 0 else "step2")


def _fast_throws(n, restitutions, seed, spin=300.0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.25, 2.6, n)
    top = 1.4 - 0.2 * np.clip(np.floor((x - RADIUS + 0.3) / 0.6), 0, 4)
    pos = np.stack([x, rng.uniform(-0.4, 0.4, n), top + RADIUS + rng.uniform(0.001, 0.3, n)], axis=1)
    d = rng.normal(size=(n, 3))
    vel = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(30.0, 120.0, n)[:, None]
    return estim.Params(rng.choice(restitutions, n), rng.uniform(0.0, 1.0, n), np.full(n, RADIUS), pos, vel,
                        mass=np.full(n, MASS), drag_coefficient=np.full(n, 0.5), spin=rng.normal(size=(n, 3)) * spin)


def _complete_and_outside(scene, params, t_end):
    """Every ball completes (no step budget exhausted, no hang), no value is NaN, and no
    sample every 0.5 ms is inside a solid by more than 1e-9 m."""
    ts = np.linspace(0.0, t_end, int(round(t_end / 5e-4)) + 1)
    traj = estim.simulate(scene, params, t_end, ts=ts, throw=False, max_steps=4096, keep=("samples",))
    assert np.all(np.asarray(traj.complete)), np.flatnonzero(~np.asarray(traj.complete))
    q = np.asarray(traj.position)
    assert np.all(np.isfinite(q))
    c, h = np.asarray(scene.box_centre), np.asarray(scene.box_half)
    excess = np.maximum(np.abs(q[:, :, None, :] - c) - h, 0.0).sum(axis=-1).min(axis=-1)
    assert np.max(RADIUS - np.minimum(excess, q[:, :, 2])) < 1e-9


def test_very_fast_bouncing_balls_stay_outside(windy):
    """Throws at 30-120 m/s, e in {0.5, 0.98, 1}, spin ~300 rad/s per axis, in wind, 2 s."""
    _complete_and_outside(windy, _fast_throws(24, [0.5, 0.98, 1.0], seed=5), 2.0)


def test_very_fast_balls_that_stop_bouncing_stay_outside(windy):
    """The same speeds with e in {0, 0.02}: the balls soon slide, along treads, the ground
    and against risers, in still air without spin (nothing pushes a sliding ball into a
    wall it meets; for that case see the next test)."""
    still = windy.with_air(Air(density=1.204, viscosity=1.81e-5))
    _complete_and_outside(still, _fast_throws(24, [0.0, 0.02], seed=6, spin=0.0), 2.0)


def test_wind_holds_a_ball_against_a_riser():
    """A ball dropped with e = 0 onto tread 5, 5 cm from the riser of step 4, with a wind of
    3 m/s towards the riser: it slides to the riser and the wind holds it there, sliding
    along tread and riser at once (which the ODE path does by removing the push into the
    riser from the acceleration). Truth: it ends at rest touching both, x = 2.1 + r and
    z = 0.6 + r, with y unchanged; it never enters either solid."""
    scene = estim.load_scene(ROOT / "data" / "scenes" / "stairs.xml").with_air(
        Air(density=1.204, viscosity=1.81e-5, wind=(-3.0, 0.0, 0.0)))
    params = estim.Params([0.0], [0.5], [RADIUS], [(2.1 + RADIUS + 0.05, 0.1, 0.6 + RADIUS + 0.01)],
                          [(0.0, 0.0, 0.0)], mass=[MASS], drag_coefficient=[0.5], spin=[(0.0, 0.0, 0.0)])
    _complete_and_outside(scene, params, 1.5)
    final = estim.simulate(scene, params, 1.5, keep=()).final
    np.testing.assert_allclose(np.asarray(final.position)[0], [2.1 + RADIUS, 0.1, 0.6 + RADIUS], atol=1e-9)
    np.testing.assert_allclose(np.asarray(final.velocity)[0], 0.0, atol=1e-9)


def test_slide_along_a_riser_to_its_end():
    """As above with the wind (-3, 2, 0.5) m/s, two balls with e = 0. One, thrown at 58 m/s
    onto tread 5, is slid by the wind to the riser of step 4, then along tread and riser at
    once towards y = 0.6, where the two end together; there it leaves both and falls beside
    the stairs. The other, dropped 1 mm onto the ground 1 cm from step 5's last riser, is
    slid along ground and riser to y = 0.6, where the riser ends, and slides on along the
    ground. Truths: along the groove the centre stays where it touches both faces and only
    the air's push along y moves it, so the time it reaches y = 0.6 is that of the
    one-dimensional ODE ``y'' = a_y(0, y', 0)`` (diffrax Dopri8 from the riser's event);
    after it the first flies untouched and the second slides on the ground, as Dopri8
    integrates them from there to 2 s (the second with the air's push along the ground
    only). (Both used to meet, at the instant they left one face, the face they had not
    left, slide off it, meet the other, and so on at that instant until the step budget
    ran out.)"""
    air = Air(density=1.204, viscosity=1.81e-5, wind=(-3.0, 2.0, 0.5))
    scene = estim.load_scene(ROOT / "data" / "scenes" / "stairs.xml").with_air(air)
    groove = np.array([[2.1 + RADIUS, 0.6 + RADIUS], [2.7 + RADIUS, RADIUS]])  # (x, z) in each groove
    params = estim.Params([0.0, 0.0], [0.5, 0.5], [RADIUS] * 2,
                          [(2.5977, -0.0507, 0.6928), (2.7 + RADIUS + 0.01, 0.3, RADIUS + 0.001)],
                          [(-27.71, -41.76, -30.09), (0.0, 0.0, 0.0)], mass=[MASS] * 2, drag_coefficient=[0.5] * 2,
                          spin=[(0.0, 0.0, 0.0)] * 2)
    _complete_and_outside(scene, params, 2.0)
    ts = np.linspace(0.0, 2.0, 4001)
    traj = estim.simulate(scene, params, 2.0, ts=ts, throw=False, max_steps=4096, keep=("samples", "events"))

    def acc(v):
        return acceleration(air, G, RADIUS, MASS, 0.5, jnp.zeros(3), v)

    def solve(f, t0, y0, **kw):
        return diffrax.diffeqsolve(diffrax.ODETerm(f), diffrax.Dopri8(), t0, 2.0, 1e-3, y0,
                                   stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-15), **kw)

    at_end = diffrax.Event(lambda t, y, args, **kw: y[0] - 0.6, root_finder=optx.Newton(rtol=1e-14, atol=1e-14))
    fly = lambda t, y, args: jnp.concatenate([y[3:], acc(y[3:])])  # noqa: E731
    slide = lambda t, y, args: jnp.concatenate([y[3:], acc(y[3:]).at[2].set(0.0)])  # noqa: E731
    for b, (wall, support, after) in enumerate([(("step4", "+x"), ("step5", "+z"), fly),
                                                (("step5", "+x"), ("ground", "plane"), slide)]):
        n = int(traj.events.count[b])
        labels = [scene.face_label(int(f)) for f in np.asarray(traj.events.face[b])[:n]]
        assert labels[-1] == wall and set(labels) == {support, wall}, labels
        t_wall = float(traj.events.t[b, n - 1])
        y_wall, vy_wall = float(traj.events.position[b, n - 1, 1]), float(traj.events.velocity_post[b, n - 1, 1])
        along = solve(lambda t, y, args: jnp.stack([y[1], acc(jnp.array([0.0, y[1], 0.0]))[1]]), t_wall,
                      jnp.array([y_wall, vy_wall]), event=at_end)
        t_off, vy_off = float(along.ts[-1]), float(along.ys[-1, 1])
        q = np.asarray(traj.position[b])
        inside = (ts > t_wall) & (ts < t_off)
        assert inside.sum() > 1000
        np.testing.assert_allclose(q[inside][:, [0, 2]], np.broadcast_to(groove[b], (inside.sum(), 2)), atol=1e-9)
        later = ts > t_off
        y0 = jnp.array([groove[b, 0], 0.6, groove[b, 1], 0.0, vy_off, 0.0])
        truth = solve(after, t_off, y0, saveat=diffrax.SaveAt(ts=ts[later]))
        assert np.max(np.abs(q[later] - np.asarray(truth.ys[:, :3]))) < 1e-6, b
        assert q[-1, 1] > 0.6 + RADIUS  # beside the stairs


def test_a_ball_rolls_over_an_edge_in_a_tail_wind():
    """A ping-pong ball sliding off tread 2 (exact edges) at 0.1 m/s, slower than sqrt(g r),
    with a 1.5 m/s tail wind: it rolls over the edge on the ODE path (the vector field held
    on the surface), touching the tread at every sample of the roll (MuJoCo's geometry,
    |distance| < 1e-9 m), leaves it where the surface's push vanishes, ``-(a . n) -
    |v|^2 / r = 0`` (a: gravity and the air, the free acceleration), earlier than in a
    vacuum (the wind pushes it off), and lands on tread 3. The landing's derivatives
    against central differences."""
    path = ROOT / "data" / "scenes" / "stairs_exact.xml"
    air = Air(density=1.204, viscosity=1.81e-5, wind=(1.5, 0.0, 0.0))
    scene = estim.load_scene(path).with_air(air)
    top, edge = 1.2, 0.9

    def params(vx):
        return estim.Params(0.8, 0.9, RADIUS, jnp.array([0.85, 0.0, top + RADIUS]), jnp.stack([vx, 0.0, 0.0]),
                            mass=MASS, drag_coefficient=0.5)

    ts = np.linspace(0.0, 1.5, 3001)
    traj = estim.simulate(scene, params(jnp.float64(0.1)), 1.5, ts=ts, keep=("samples", "events", "solution"))
    n = int(traj.events.count)
    labels = [scene.face_label(int(f)) for f in np.asarray(traj.events.face)[:n]]
    assert labels[1:3] == [("step2", "+x+z"), ("step3", "+z")], labels
    sol = traj.solution
    detach = np.flatnonzero(np.asarray(sol.steps.kind) == 6)  # STEP_DETACH
    assert detach.size == 1
    t_edge, t_off = float(traj.events.t[1]), float(sol.nodes.t1[detach[0]])
    p_off, v_off = np.asarray(sol.nodes.p1[detach[0]]), np.asarray(sol.nodes.v1[detach[0]])
    # Touching the tread all along the roll (MuJoCo's sphere-box distance).
    xml = open(path).read().replace(
        "</worldbody>", f'<body name="probe" mocap="true"><geom name="probe" type="sphere" size="{RADIUS}" '
        'contype="0" conaffinity="0"/></body></worldbody>')
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    probe, step2 = (mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name) for name in ("probe", "step2"))
    rolling = (ts > t_edge) & (ts < t_off)
    assert rolling.sum() > 20
    for q in np.asarray(traj.position)[rolling]:
        d.geom_xpos[probe] = q
        assert abs(mujoco.mj_geomDistance(m, d, probe, step2, 1.0, np.zeros(6))) < 1e-9, q
    # It leaves where the surface stops pushing.
    arm = p_off - np.array([edge, p_off[1], top])
    normal = arm / np.linalg.norm(arm)
    a_free = np.asarray(acceleration(air, G, RADIUS, MASS, 0.5, jnp.zeros(3), jnp.asarray(v_off)))
    across2 = v_off[0] ** 2 + v_off[2] ** 2
    assert abs(-a_free @ normal - across2 / RADIUS) < 1e-7 * G
    assert np.linalg.norm(arm) == pytest.approx(RADIUS, abs=1e-12)
    vacuum = (0.1**2 / (G * RADIUS) + 2.0) / 3.0  # cos theta* without air
    assert arm[2] / RADIUS > vacuum  # (the wind pushes it off sooner)

    def landing(vx):
        ev = estim.simulate(scene, params(vx), 1.5, max_events=8).events
        return jnp.stack([ev.t[2], ev.position[2, 0]])  # (the landing on tread 3)

    vx = jnp.float64(0.1)
    jac = np.asarray(jax.jacfwd(landing)(vx))
    eps = 1e-5
    fd = (np.asarray(landing(vx + eps)) - np.asarray(landing(vx - eps))) / (2 * eps)
    np.testing.assert_allclose(jac, fd, rtol=1e-4)


def test_a_ball_thrown_off_the_face_it_slid_on_leaves_it():
    """A table-tennis ball with e = 0 and mu = 1 (a fit's wild start) flies into the net,
    whose Magnus push holds it there: it slides down the net onto the table, whose friction
    throws it off the net at 0.38 m/s, rolls across the table and falls off its side onto
    the floor. It used to slide on "on" the net 30 cm from it, and at the table's edge left
    the table and met it again, at one instant, until its steps ran out (a fit's probe of
    its drag then failed). Truths: it completes and never enters a solid; its last contact
    before the floor is the table's top; and from where it leaves the table's side, its fall
    to the floor (z = -0.76 + r) is that of an independent integration of the air's
    acceleration with its spin (diffrax Dopri8)."""
    scene = estim.load_scene(ROOT / "data" / "scenes" / "table_tennis.xml")
    params = estim.Params.for_ball(scene, "pingpong", e=0.0, mu_t=0.95, mu=1.0, drag_coefficient=0.5875,
                                   position=np.array([-1.4, -2.174, 0.097]), velocity=np.array([4.39, 8.505, 1.647]),
                                   spin=np.array([29.1, -0.25, -43.5]))
    ts = np.linspace(0.0, 2.0, 4001)
    traj = estim.simulate(scene, params, 2.0, ts=ts, throw=False)
    assert bool(traj.complete)
    q = np.asarray(traj.position)
    c, h = np.asarray(scene.box_centre), np.asarray(scene.box_half)
    excess = np.maximum(np.abs(q[:, None, :] - c) - h, 0.0).sum(axis=-1).min(axis=-1)
    assert np.all(np.isfinite(q)) and np.max(RADIUS - np.minimum(excess, q[:, 2] + 0.76)) < 1e-9
    n = int(traj.events.count)
    labels = [scene.face_label(int(f)) for f in np.asarray(traj.events.face)[:n]]
    assert labels[0] == ("net", "-y") and labels[-2:] == [("table", "+z"), ("floor", "plane")], labels
    steps, nodes = traj.solution.steps, traj.solution.nodes
    off = int(np.flatnonzero(np.asarray(steps.kind) == STEP_EXIT)[-1])  # (off the table's side)
    p_off = np.asarray(nodes.p1)[off]
    assert p_off[0] == pytest.approx(0.7625) and p_off[2] == pytest.approx(RADIUS)
    t_off, spin = float(np.asarray(nodes.t1)[off]), jnp.asarray(np.asarray(nodes.w1_post)[off])

    def fly(t, y, args):
        return jnp.concatenate([y[3:], acceleration(scene.air, G, RADIUS, MASS, 0.5875, spin, y[3:])])

    floor = diffrax.Event(lambda t, y, args, **kw: y[2] - (-0.76 + RADIUS), root_finder=optx.Newton(rtol=1e-14,
                                                                                                     atol=1e-14))
    truth = diffrax.diffeqsolve(diffrax.ODETerm(fly), diffrax.Dopri8(), t_off, 2.0, 1e-3,
                                jnp.concatenate([jnp.asarray(p_off), jnp.asarray(np.asarray(nodes.v1_post)[off])]),
                                stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-15), event=floor)
    assert float(traj.events.t[n - 1]) == pytest.approx(float(truth.ts[-1]), abs=1e-6)
    np.testing.assert_allclose(np.asarray(traj.events.position)[n - 1], np.asarray(truth.ys[-1, :3]), atol=1e-6)
