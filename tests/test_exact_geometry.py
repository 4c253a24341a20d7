"""Exact geometry: a ball meets a box as a sphere meets a box (estim.model._scene).

The independent truth is MuJoCo's own geometry: ``mujoco.mj_geomDistance`` between a
sphere of the ball's radius at each contact and the solid estim names, and the nearest
point of that solid to the ball's centre, which gives MuJoCo's contact normal. Throws are
aimed at edges and corners of every box of four scenes (the staircase with exact edges,
the table drop, a table on a floor, a box rotated a quarter turn about z); the event times
and their derivatives are checked against finite differences and a closed form.
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import ROOT, G, box_distance, derivative_jit

import estim
from estim.forward._constants import ROLL
from estim.forward._curved import _sorted, entering_times
from estim.forward._roll import Roll, Spherical

PROBE = '<body name="probe" mocap="true"><geom name="probe" type="sphere" size="0.05" contype="0" conaffinity="0"/></body>'

TABLE = """<mujoco model="table">
  <option gravity="0 0 -9.81"/>
  <worldbody>
    <geom name="floor" type="plane" size="3 3 0.1"/>
    <geom name="table" type="box" pos="0.2 -0.1 0.71" size="1.37 0.7625 0.05"/>
    <geom name="post" type="box" pos="1.9 0.6 0.3" size="0.05 0.05 0.3" quat="0.7071068 0 0 0.7071068"/>
    <geom name="brick" type="box" pos="-1.6 0.5 0.1" size="0.2 0.05 0.1" euler="0 0 90"/>
  </worldbody>
</mujoco>
"""


def _scenes(tmp_path):
    table = tmp_path / "table.xml"
    table.write_text(TABLE)
    return {
        "stairs_exact": str(ROOT / "data" / "scenes" / "stairs_exact.xml"),
        "drop": str(ROOT / "data" / "scenes" / "drop.xml"),
        "table": str(table),
    }


class Measure:
    """MuJoCo's sphere-box distance and nearest point, with a probe sphere placed anywhere."""

    def __init__(self, path):
        xml = open(path).read().replace("</worldbody>", PROBE + "</worldbody>")
        # A scene file's includes and assets are not used by these scenes.
        self.m = mujoco.MjModel.from_xml_string(xml)
        self.d = mujoco.MjData(self.m)
        mujoco.mj_forward(self.m, self.d)
        self.probe = mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_GEOM, "probe")

    def geom(self, name):
        return mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_GEOM, name)

    def distance(self, q, r, geom):
        """Signed distance from a sphere of radius r centred at q to ``geom``, and the point
        of ``geom`` nearest to q."""
        self.m.geom_size[self.probe, 0] = r
        self.m.geom_rbound[self.probe] = r
        self.d.geom_xpos[self.probe] = q
        fromto = np.zeros(6)
        dist = mujoco.mj_geomDistance(self.m, self.d, self.probe, geom, 10.0, fromto)
        return dist, fromto[3:]


def _throws(scene, rng, n, g=G):
    """n throws, each aimed to meet an edge or a corner of a random box at a random point
    of it, from a random direction into it: the release state, the radius, the time."""
    curved = [f for f in range(scene.n_faces)
              if scene.face_solid[f] < scene.n_boxes and sum(map(abs, scene.face_direction[f])) >= 2]
    c, h = np.asarray(scene.box_centre), np.asarray(scene.box_half)
    out = []
    while len(out) < n:
        f = curved[rng.integers(len(curved))]
        b, m = scene.face_solid[f], np.array(scene.face_direction[f])
        r = rng.uniform(0.02, 0.1)
        anchor = c[b] + m * h[b] + (m == 0) * rng.uniform(-1, 1, 3) * h[b]
        normal = m * np.abs(rng.normal(size=3))
        normal /= np.linalg.norm(normal)
        q = anchor + r * normal
        tangent = rng.normal(size=3)
        tangent -= tangent @ normal * normal
        tangent /= np.linalg.norm(tangent)
        angle = rng.uniform(0.0, 1.4)
        v_c = -rng.uniform(0.3, 6.0) * (np.cos(angle) * normal + np.sin(angle) * tangent)
        t0 = rng.uniform(0.02, 0.3)
        a = np.array([0.0, 0.0, -g])
        v0 = v_c - a * t0
        p0 = q - v0 * t0 - 0.5 * a * t0 * t0
        out.append((p0, v0, r, t0))
    return out


def _outside(measure, solids, q, r):
    return min(measure.distance(q, r, g)[0] for g in solids)


@pytest.mark.slow
def test_contacts_touch_the_named_solid_as_mujoco_measures(tmp_path):
    """At least 1,000 throws at edges and corners over three scenes (the staircase with exact
    edges, the table drop, a table on a floor with a box rotated a quarter turn about z and
    one given by Euler angles): at every contact MuJoCo puts the ball touching the solid estim
    names (|distance| < 1e-9 m) with the same normal (to 1e-9), and at no sampled time is the
    ball inside any solid."""
    rng = np.random.default_rng(22)
    n_curved = 0
    for name, path in _scenes(tmp_path).items():
        scene = estim.load_scene(path)
        assert scene.geometry == "exact"
        measure = Measure(path)
        solids = [measure.geom(s) for s in scene.names]
        throws = [t for t in _throws(scene, rng, 450) if _outside(measure, solids, t[0], t[2]) > 1e-6][:400]
        p0, v0, r, t0 = (np.array(x) for x in zip(*throws, strict=True))
        t_end = 0.8
        ts = np.linspace(0.0, t_end, 41)
        params = estim.Params(0.6, 0.8, r, p0, v0)
        traj = estim.simulate(scene, params, t_end, ts=ts, max_events=64, throw=False)
        ev = traj.events
        # A ball that would roll over an edge that is not horizontal (the box given by Euler
        # angles) is not followed in closed form: it stops there, reported incomplete.
        complete = np.asarray(traj.complete)
        assert complete.mean() > 0.97, (name, np.flatnonzero(~complete))
        for i in np.flatnonzero(~complete):
            last = int(ev.face[i, int(ev.count[i]) - 1])
            assert sum(map(abs, scene.face_direction[last])) >= 2, (name, i)
        normals = np.asarray(estim.contact_normals(scene, ev.face, ev.position))
        for i in range(len(throws)):
            for k in range(int(ev.count[i])):
                q, face = np.asarray(ev.position[i, k]), int(ev.face[i, k])
                solid = scene.names[scene.face_solid[face]]
                dist, nearest = measure.distance(q, r[i], measure.geom(solid))
                assert abs(dist) < 1e-9, (name, i, k, solid, dist)
                expected = (q - nearest) / np.linalg.norm(q - nearest)
                np.testing.assert_allclose(normals[i, k], expected, rtol=0, atol=1e-9)
                n_curved += sum(map(abs, scene.face_direction[face])) >= 2
            for q in np.asarray(traj.position[i]) if complete[i] else ():
                assert _outside(measure, solids, q, r[i]) > -1e-9, (name, i)
    assert n_curved >= 1000, n_curved


def _edge_throw(scene, dx=0.0):
    """A ball falling onto the +x top edge of step2 of the exact staircase, 60 degrees
    round it from the top (its contact normal), slowly enough to meet it."""
    r = 0.05
    normal = np.array([np.sin(1.0), 0.0, np.cos(1.0)])
    q = np.array([0.9, 0.1, 1.2]) + r * normal
    t0, v_c = 0.2, np.array([-0.5, 0.0, -2.0])
    a = np.array([0.0, 0.0, -G])
    v0 = v_c - a * t0
    return estim.Params(0.7, 0.9, r, q - v0 * t0 - 0.5 * a * t0 * t0 + np.array([dx, 0, 0]), v0), t0, q


def test_edge_contact_time_and_bounce_in_closed_form():
    """A ball that meets a tread edge: the contact time is the one the throw was built with,
    the normal points from the edge to the centre, and the factor law reflects the
    velocity's normal part about it (e) and keeps mu_t of its tangential part."""
    scene = estim.load_scene(str(ROOT / "data" / "scenes" / "stairs_exact.xml"))
    params, t0, q = _edge_throw(scene)
    traj = estim.simulate(scene, params, 0.3)
    ev = traj.events
    assert scene.face_label(int(ev.face[0])) == ("step2", "+x+z")
    np.testing.assert_allclose(float(ev.t[0]), t0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(ev.position[0]), q, rtol=0, atol=1e-12)
    n = np.asarray(estim.contact_normals(scene, ev.face[0], ev.position[0]))
    np.testing.assert_allclose(n, [np.sin(1.0), 0.0, np.cos(1.0)], rtol=0, atol=1e-12)
    v = np.asarray(ev.velocity_pre[0])
    vn = v @ n * n
    np.testing.assert_allclose(np.asarray(ev.velocity_post[0]), -0.7 * vn + 0.9 * (v - vn), rtol=0, atol=1e-12)


@derivative_jit
def one_ball(scene, x, t_end, ts):
    """One ball, x = (e, mu_t, radius, position, velocity): its event times, positions at
    the two sample times ``ts``, final position and velocity, and their forward
    derivatives with respect to x (``jax.jacfwd``); then its segments' roll axes and
    whether it reached ``t_end`` (``throw=False``). One compiled program for the one-ball
    derivative tests of this module on the exact staircase, their finite differences
    included (a program of its own each compiled for 20-50 s, 2-core machine)."""

    def f(x):
        p = estim.Params(x[0], x[1], x[2], x[3:6], x[6:9])
        traj = estim.simulate(scene, p, t_end, ts=ts, throw=False)
        out = traj.events.t, traj.position, traj.final.position, traj.final.velocity
        return out, (out, traj.solution.segments.normal, traj.complete)

    jac, (out, axes, complete) = jax.jacfwd(f, has_aux=True)(x)
    return out, jac, axes, complete


def central_differences(scene, x, t_end, ts, output, ks, eps):
    """d output(x) / d x[k] for k in ks by central differences of the program's values
    (``output`` picks an array from its outputs): shape (*output, len(ks))."""
    def value(k, step):
        return np.asarray(output(one_ball(scene, x.at[k].add(step), t_end, ts)[0]))

    return np.stack([(value(k, eps) - value(k, -eps)) / (2 * eps) for k in ks], axis=-1)


EXACT_STAIRS = ROOT / "data" / "scenes" / "stairs_exact.xml"
TWO_TIMES = jnp.array([0.05, 0.12])  # the sample times of every one_ball call here


def test_edge_and_corner_event_times_and_their_derivatives_match_finite_differences():
    """d(event time)/d(release state, radius) at an edge and at a corner of step2: forward
    autodiff through the quartic's root (the implicit-function formula on a curved surface)
    against central differences of the root itself."""
    scene = estim.load_scene(str(EXACT_STAIRS))
    params, _, _ = _edge_throw(scene)
    corner = np.array([0.9, 0.6, 1.2]) + 0.05 * np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0)
    v_c = np.array([-0.8, -0.6, -1.5])
    a = np.array([0.0, 0.0, -G])
    v0 = v_c - a * 0.15
    corner_params = estim.Params(0.7, 0.9, 0.05, corner - v0 * 0.15 - 0.5 * a * 0.15**2, v0)
    t_end = jnp.asarray(0.4)
    for prm, label in ((params, "+x+z"), (corner_params, "+x+y+z")):
        x = jnp.concatenate([jnp.array([0.7, 0.9, 0.05]), jnp.asarray(prm.position), jnp.asarray(prm.velocity)])
        traj = estim.simulate(scene, prm, 0.4)
        assert scene.face_label(int(traj.events.face[0]))[1] == label
        _, (jt, _, _, _), _, complete = one_ball(scene, x, t_end, TWO_TIMES)
        assert complete
        fd = central_differences(scene, x, t_end, TWO_TIMES, lambda out: out[0][0], range(2, 9), 1e-6)
        np.testing.assert_allclose(np.asarray(jt[0, 2:]), fd, rtol=1e-6, atol=1e-8)


def test_quartic_roots_never_missed_against_dense_sampling():
    """entering_times against the sign changes of D on a fine grid, for random parabolas
    about a cylinder and a sphere, grazes included: the same number of entries, at the same
    times (to 1e-12 s), none missed (D's roots are also its own check: D = 0 there)."""
    rng = np.random.default_rng(5)
    n = 4000
    mask = np.where(rng.random((n, 1)) < 0.5, np.array([1.0, 0.0, 1.0]), 1.0)
    A = rng.normal(size=(n, 3)) * 0.3 * mask
    B = rng.normal(size=(n, 3)) * 2.0 * mask
    C = np.array([0.0, 0.0, -G / 2]) * mask + rng.normal(size=(n, 3)) * 0.3 * mask
    r = rng.uniform(0.01, 0.2, n)
    horizon = np.full(n, 1.0)
    roots = np.asarray(entering_times(jnp.asarray(A), jnp.asarray(B), jnp.asarray(C), jnp.asarray(r),
                                      jnp.zeros(n), jnp.asarray(horizon)))
    t = np.linspace(0.0, 1.0, 200001)
    D, P = np.empty_like(t), np.empty_like(t)
    for i in range(n):
        D[:] = -r[i] ** 2
        for k in range(3):  # (in place, a coordinate at a time: 5 times faster than the arrays of P)
            np.multiply(t, C[i, k], out=P)
            P += B[i, k]
            P *= t
            P += A[i, k]
            P *= P
            D += P
        falls = np.flatnonzero((D[:-1] > 0) & (D[1:] <= 0))
        found = roots[i][np.isfinite(roots[i])]
        assert len(found) == len(falls), (i, found, t[falls])
        np.testing.assert_allclose(found, t[falls], rtol=0, atol=1e-5 + 1e-12)
        for tau in found:
            q = A[i] + B[i] * tau + C[i] * tau**2
            assert abs(np.sum(q * q) - r[i] ** 2) < 1e-12


@pytest.mark.parametrize("path", ["closed_form", "ode"])
def test_a_ball_sliding_off_a_tread_rolls_over_its_edge(path):
    """A ball sliding off a tread top faster than sqrt(g r) flies off the edge; slower, it
    rolls over it: MuJoCo's geometry puts it touching the tread (|distance| < 1e-9 m) at
    every sample of the roll, it leaves the edge where cos theta = (v^2 / (g r) + 2) / 3 (a
    particle leaving a cylinder, from energy and the normal force: estim.forward._roll),
    at the time the integrated pendulum gives (``test_roll_matches_an_integrator``), and
    lands on the next tread; on both solver paths."""
    scene = estim.load_scene(str(ROOT / "data" / "scenes" / "stairs_exact.xml"))
    kw = {"solver": diffrax.Tsit5()} if path == "ode" else {}
    r, top, edge = 0.05, 1.2, 0.9
    fast = estim.Params(0.0, 1.0, r, np.array([0.5, 0.0, top + r]), np.array([1.0, 0.0, 0.0]))
    traj = estim.simulate(scene, fast, 1.0, **kw)
    labels = [scene.face_label(int(f)) for f in np.asarray(traj.events.face)[: int(traj.events.count)]]
    n = int(traj.events.count)
    kick = np.linalg.norm(np.asarray(traj.events.velocity_post - traj.events.velocity_pre)[:n], axis=1)
    assert labels[0] == ("step2", "+z") and ("step3", "+z") in labels, labels
    # No edge touched (the ODE path may list a touch of the edge as the ball leaves it, a
    # contact within its slack that changes the velocity by < 1e-6 m/s).
    assert all(len(face) == 2 or (path == "ode" and dv < 1e-6) for (_, face), dv in zip(labels, kick, strict=True)), labels
    v = 0.3
    slow = estim.Params(0.0, 1.0, r, np.array([0.5, 0.0, top + r]), np.array([v, 0.0, 0.0]))
    t_edge = (edge - 0.5) / v
    ts = np.linspace(0.0, 2.0, 2001)
    traj = estim.simulate(scene, slow, 2.0, ts=ts, keep=("samples", "events", "solution"), **kw)
    labels = [scene.face_label(int(f)) for f in np.asarray(traj.events.face)[: int(traj.events.count)]]
    assert labels[:3] == [("step2", "+z"), ("step2", "+x+z"), ("step3", "+z")], labels
    cos_star = (v * v / (G * r) + 2.0) / 3.0
    p = np.asarray(traj.position)
    rolling = (ts > t_edge) & (p[:, 2] > top + r * cos_star + 1e-9)
    leaves = np.flatnonzero(rolling)[-1] + 1
    assert rolling.sum() > 50 and np.all(rolling[np.flatnonzero(ts > t_edge)[0]:leaves])
    measure = Measure(str(ROOT / "data" / "scenes" / "stairs_exact.xml"))
    step2 = measure.geom("step2")
    for q in p[rolling]:
        assert abs(measure.distance(q, r, step2)[0]) < 1e-9, q
    # Where it leaves: on the circle about the edge at cos theta*, its velocity tangent there.
    t_roll = _pendulum_time(theta0=0.0, omega0=v / r, k=G / r)
    q = np.asarray(traj.solution.evaluate(jnp.asarray([t_edge + t_roll]))[0])[0]
    tol = 1e-12 if path == "closed_form" else 1e-8
    np.testing.assert_allclose(q, [edge + r * np.sqrt(1 - cos_star**2), 0.0, top + r * cos_star], rtol=0, atol=tol)


def test_a_roll_with_almost_no_speed_along_its_edge_has_finite_derivatives():
    """As above, rolling over step 2's edge at 0.5 m/s, with a speed along the edge of 0,
    1e-160 m/s (whose square underflows) or 4e-308 m/s (subnormal; the case random scenes
    found, ``tests/test_properties.py``). With mu_t = 1 no contact changes the velocity
    along y (every normal here is across y), so y(t) = vy0 t and ``dy(t_end) / dvy0 =
    t_end`` exactly; every derivative of the final state is finite. (The time to the edge's
    end, ``(end - along) / vy``, had an infinite derivative there, made NaN by the minimum
    with the roll's own end.)"""
    scene = estim.load_scene(str(EXACT_STAIRS))
    r, top, t_end = 0.05, 1.2, 1.5
    for vy in (0.0, 1e-160, 3.91994034e-308):
        x = jnp.array([0.5, 1.0, r, 0.5, 0.0, top + r, 0.5, vy, 0.0])
        _, (_, _, jp, jv), _, complete = one_ball(scene, x, jnp.asarray(t_end), TWO_TIMES)
        assert complete
        J = np.concatenate([np.asarray(jp), np.asarray(jv)])  # (final position and velocity, x)
        assert np.all(np.isfinite(J)), vy
        assert J[1, 7] == pytest.approx(t_end, abs=1e-12) and J[4, 7] == pytest.approx(1.0, abs=1e-12), vy


def _pendulum_time(theta0, omega0, k, dt=1e-5):
    """Time for theta'' = k sin theta from (theta0, omega0) to k cos theta = theta'^2 (a
    ball leaving a cylinder), by classical Runge-Kutta and bisection of the last step."""
    def f(y):
        return np.array([y[1], k * np.sin(y[0])])

    def rk4(y, h):
        k1 = f(y)
        k2 = f(y + h / 2 * k1)
        k3 = f(y + h / 2 * k2)
        k4 = f(y + h * k3)
        return y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    def left(y):
        return k * np.cos(y[0]) - y[1] ** 2 <= 0

    y, t = np.array([theta0, omega0]), 0.0
    while not left(rk4(y, dt)):
        y, t = rk4(y, dt), t + dt
    lo, hi = 0.0, dt
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if left(rk4(y, mid)) else (mid, hi)
    return t + hi


# The roll of test_roll_matches_an_integrator: over the +x edge of a tread at (0.3, y, 1.4)
# (up the x axis is +x), r 0.05, with 0.7 m/s along the edge; its programs are compiled once
# for every case (run op by op, its derivatives took 5-8 s a case).
ROLL_RADIUS, ROLL_PIVOT, ROLL_AXIS = 0.05, (0.3, 0.0, 1.4), (0.0, -1.0, 0.0)


def _roll(theta, omega) -> Roll:
    r = ROLL_RADIUS
    p = jnp.asarray(ROLL_PIVOT) + r * jnp.stack([jnp.sin(theta), 0.0, jnp.cos(theta)]) + jnp.array([0.0, 0.2, 0.0])
    v = r * omega * jnp.stack([jnp.cos(theta), 0.0, -jnp.sin(theta)]) + jnp.array([0.0, 0.7, 0.0])
    return Roll(jnp.asarray(ROLL_PIVOT), jnp.asarray(ROLL_AXIS), p, v, G)


@jax.jit
def _roll_span(theta, omega):
    roll = _roll(theta, omega)
    return roll.reaches_top, roll.duration


@jax.jit
def _roll_states(theta, omega, taus):
    return jax.vmap(_roll(theta, omega).state)(taus)


@jax.jit
def _roll_end(x):
    """The roll's duration and its state halfway through it."""
    roll = _roll(x[0], x[1])
    q, u = roll.state(0.5 * roll.duration)
    return jnp.concatenate([roll.duration[None], q, u])


_roll_end_jacfwd, _roll_end_jacrev = jax.jit(jax.jacfwd(_roll_end)), jax.jit(jax.jacrev(_roll_end))


@pytest.mark.parametrize("theta0, omega0", [(0.0, 1.0), (0.2, 0.5), (0.3, -3.0), (0.3, -8.0), (0.5, 0.0),
                                            (0.0, 1e-3), (0.1, 2 * np.sqrt(G / 0.05) * np.sin(0.05))])
def test_roll_matches_an_integrator(theta0, omega0):
    """The closed-form roll (elliptic integrals by Carlson's R_F, estim.forward._roll)
    against Runge-Kutta on theta'' = (g / r) sin theta: its duration to where the ball
    leaves the edge (or, rolling inwards faster than it can turn, is back on top), states
    inside it, energy along it; and its derivatives against central differences. The cases
    cover both signs of B = omega0^2 - 4 k sin^2(theta0 / 2) (B > 0: it could pass the
    top; B < 0: it turns), a turn, B = 0 to rounding, and a start from rest."""
    r, k = ROLL_RADIUS, G / ROLL_RADIUS
    reaches_top, duration = (x.item() for x in _roll_span(theta0, omega0))
    if reaches_top:
        return  # (rolls back onto the face: checked by test_hard_cases)
    assert duration == pytest.approx(_pendulum_time(theta0, omega0, k), abs=1e-11)
    taus = np.linspace(0.0, duration, 7)
    p, v = (np.asarray(x) for x in _roll_states(theta0, omega0, jnp.asarray(taus)))
    arm = p - np.asarray(ROLL_PIVOT)
    np.testing.assert_allclose(np.hypot(arm[:, 0], arm[:, 2]), r, rtol=0, atol=1e-15)
    np.testing.assert_allclose(arm[:, 1], 0.2 + 0.7 * taus, rtol=0, atol=1e-15)
    energy = G * p[:, 2] + 0.5 * np.sum(v * v, axis=1)
    np.testing.assert_allclose(energy, energy[0], rtol=1e-13)
    # The state at the end: cos theta* = (omega0^2 / k + 2 cos theta0) / 3.
    cos_star = (omega0**2 / k + 2 * np.cos(theta0)) / 3
    assert arm[-1, 2] / r == pytest.approx(cos_star, abs=1e-12)

    x = jnp.array([theta0, omega0])
    if abs(omega0**2 - 4 * k * np.sin(theta0 / 2) ** 2) < 1e-6:
        return  # (B ~ 0: derivatives lose eps / |B| to cancellation, estim.forward._roll)
    jac = np.asarray(_roll_end_jacfwd(x))
    rev = np.asarray(_roll_end_jacrev(x))
    eps = 1e-6 * np.maximum(np.abs(np.asarray(x)), 1e-3)
    fd = np.stack([(np.asarray(_roll_end(x + h * e)) - np.asarray(_roll_end(x - h * e))) / (2 * h)
                   for h, e in zip(eps, np.eye(2), strict=True)], axis=1)
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(rev, jac, rtol=1e-10, atol=1e-12)


def sliding_off_treads(n: int, seed: int) -> estim.Params:
    """n balls (r 0.02-0.1 m, e 0-0.9, mu_t 0.5-1) released sliding on a random tread top of
    ``stairs_exact.xml`` in a random horizontal direction at up to 1.3 sqrt(g r)."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(0.02, 0.1, n)
    step = rng.integers(0, 5, n)
    x = np.maximum(0.6 * step + 0.9 * rng.uniform(-0.3, 0.3, n), 0.6 * step - 0.3 + r + 1e-3)
    angle = rng.uniform(0, 2 * np.pi, n)
    speed = rng.uniform(0.0, 1.3, n) * np.sqrt(G * r)
    pos = np.stack([x, rng.uniform(-0.5, 0.5, n), 1.4 - 0.2 * step + r], axis=1)
    vel = np.stack([speed * np.cos(angle), speed * np.sin(angle), np.zeros(n)], axis=1)
    return estim.Params(rng.uniform(0, 0.9, n), rng.uniform(0.5, 1.0, n), r, pos, vel)


@pytest.mark.parametrize("path", ["closed_form", "ode"])
def test_random_slides_off_treads_roll_and_stay_outside(path):
    """64 balls (r 0.02-0.1 m, e 0-0.9, mu_t 0.5-1) released sliding on a random tread top
    in a random horizontal direction at up to 1.3 sqrt(g r), for 3 s: across edges,
    along them, onto corners. Every value finite; every ball that completes stays outside
    every solid (Euclidean distance, to 1e-9 m) and never gains energy (to rounding on the
    closed form, 1e-8 J/kg on the ODE path); at least 40 roll over an edge. The closed form
    and the ODE path both follow every ball to the end (the closed form stopped two whose
    roll reached a corner out of the vertical plane through its vertex, until the
    spherical pendulum). (Found by this test: a roll's end decided from the signs at the end of
    one bisection, which rounding can flip, sent a ball 2 cm into a tread.)"""
    scene = estim.load_scene(str(ROOT / "data" / "scenes" / "stairs_exact.xml"))
    n = 64
    params = sliding_off_treads(n, seed=0)
    r = np.asarray(params.radius)
    ts = np.linspace(0.0, 3.0, 1501)
    kw = {"solver": diffrax.Tsit5(), "max_steps": 4096} if path == "ode" else {"max_segments": 96}
    traj = estim.simulate(scene, params, 3.0, ts=ts, throw=False, keep=("samples", "solution"), **kw)
    q, v = np.asarray(traj.position), np.asarray(traj.velocity)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(v))
    done = np.asarray(traj.complete)
    assert done.all(), np.flatnonzero(~done)
    if path == "ode":
        rolls = np.any(np.asarray(traj.solution.steps.mode) == ROLL, axis=1)
    else:
        rolls = np.any(np.asarray(traj.solution.structure.kind) == ROLL, axis=1)
    assert rolls.sum() >= 40, rolls.sum()
    depth = np.min(box_distance(q[done], scene.box_centre, scene.box_half), axis=-1) - r[done, None]
    assert depth.min() >= -1e-9 and np.min(q[done, :, 2] - r[done, None]) >= -1e-9
    energy = G * q[done, :, 2] + 0.5 * np.sum(v[done] ** 2, axis=-1)
    assert np.max(np.diff(energy, axis=1)) <= (1e-12 if path == "closed_form" else 1e-8)


@pytest.mark.parametrize("n", [1, 2, 3, 6, 7])
def test_the_sorting_network_sorts(n):
    """The contact search's sorting network (minima and maxima, no ``sort`` in the step
    loop) against NumPy's sort, with ties and infinities, along the last axis of a batch."""
    rng = np.random.default_rng(n)
    x = rng.choice([-1.0, 0.0, 0.5, 2.0, np.inf, -np.inf, 3.25], size=(200, n))
    x[:100] = rng.normal(size=(100, n))
    np.testing.assert_array_equal(np.asarray(_sorted(jnp.asarray(x))), np.sort(x, axis=-1))


def dropped_on_corners(n: int, seed: int) -> estim.Params:
    """n balls (r 0.02-0.08 m) dropped from 0.1 mm onto a top corner of a tread of
    ``stairs_exact.xml`` (off the vertical planes through the vertex along the box's axes),
    moving sideways at up to about 0.3 m/s, with e = 1e-12 and mu_t = 1: each lands on the
    corner without normal speed, keeps its tangential velocity and rolls over the corner
    off the vertical plane through its vertex (the spherical pendulum)."""
    scene = estim.load_scene(str(ROOT / "data" / "scenes" / "stairs_exact.xml"))
    c, h = np.asarray(scene.box_centre), np.asarray(scene.box_half)
    rng = np.random.default_rng(seed)
    r = rng.uniform(0.02, 0.08, n)
    box = rng.integers(0, len(c), n)
    sy = rng.choice([-1.0, 1.0], n)
    vertex = c[box] + h[box] * np.stack([np.ones(n), sy, np.ones(n)], 1)
    theta, phi = rng.uniform(0.05, 0.6, n), rng.uniform(0.1, np.pi / 2 - 0.1, n)
    out = np.stack([np.sin(theta) * np.cos(phi), sy * np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    vel = rng.normal(0.0, 0.15, (n, 3))
    vel[:, 2] = -0.05
    return estim.Params(np.full(n, 1e-12), np.ones(n), r, vertex + (r[:, None] + 1e-4) * out, vel)


def test_a_roll_over_a_corner_is_the_constrained_motion():
    """The spherical pendulum in closed form (``Spherical``) against a Dopri8 integration
    (rtol 1e-13) of the frictionless motion on the sphere about the vertex (gravity along
    the surface, the centripetal push holding it on): 12 pressed starts off the vertical
    planes through the vertex, states to 1e-10 at seven times of each roll; each roll ends
    where the surface's push falls to 0 or the centre's offset from the vertex along x or y
    to 0 (the corner's region ends: the ball goes on over an edge), both seen."""

    def field(t, y, args):
        p, v = y[:3], y[3:]
        r = jnp.sqrt(jnp.sum(p * p))
        n = p / r
        a = jnp.array([0.0, 0.0, -G])
        return jnp.concatenate([v, a - jnp.dot(a, n) * n - (jnp.dot(v, v) - jnp.dot(v, n) ** 2) / r * n])

    signs = jnp.ones(3)
    roll = jax.jit(lambda p, v: (lambda s: (s.duration, s.exit_axis))(Spherical(jnp.zeros(3), p, v, G, signs)))
    states = jax.jit(lambda p, v, ts: jax.vmap(
        lambda t: jnp.concatenate(Spherical(jnp.zeros(3), p, v, G, signs).state(t)))(ts))
    rng = np.random.default_rng(1)
    ends = set()
    done = 0
    while done < 12:
        r = rng.uniform(0.02, 0.1)
        theta, phi = rng.uniform(0.0, 0.5), rng.uniform(0.05, np.pi / 2 - 0.05)
        n0 = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        e1 = np.cross([0.0, 0.0, 1.0], n0)
        e1 /= np.linalg.norm(e1)
        v0 = 0.8 * np.sqrt(G * r) * (rng.uniform(-1, 1) * e1 + rng.uniform(-1, 1) * np.cross(n0, e1))
        if G * n0[2] * r <= v0 @ v0:  # not pressed: it would fly off at once
            continue
        done += 1
        duration, axis = (float(x) for x in roll(jnp.asarray(r * n0), jnp.asarray(v0)))
        ts = np.linspace(0.0, duration, 7)
        sol = diffrax.diffeqsolve(diffrax.ODETerm(field), diffrax.Dopri8(), 0.0, duration, duration / 200,
                                  jnp.concatenate([r * n0, v0]), saveat=diffrax.SaveAt(ts=jnp.asarray(ts)),
                                  stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-15), max_steps=100_000)
        ref = np.asarray(sol.ys)
        np.testing.assert_allclose(states(jnp.asarray(r * n0), jnp.asarray(v0), jnp.asarray(ts)), ref,
                                   rtol=0, atol=1e-10)
        p, v = ref[-1, :3], ref[-1, 3:]
        n = p / np.linalg.norm(p)
        if axis < 0:
            assert abs(G * n[2] - (v @ v - (v @ n) ** 2) / r) < 1e-8
        else:
            assert abs(p[int(axis)]) < 1e-12
        ends.add(axis >= 0)
    assert ends == {True, False}


@pytest.fixture(scope="module")
def corner_drops():
    scene = estim.load_scene(str(ROOT / "data" / "scenes" / "stairs_exact.xml"))
    return scene, dropped_on_corners(64, seed=0)


def test_balls_dropped_on_corners_roll_off_them_as_the_ode_path_integrates(corner_drops):
    """64 balls dropped onto corners roll over them off the vertical plane through the
    vertex (the spherical pendulum: at least 50 of them), then over edges and off: the
    closed form follows every one to the end, within 1e-9 m of the ODE path (an
    integration of the same motion, rtol 1e-11) at 301 times over 1.5 s, never gaining
    energy (to rounding) and never inside a solid (Euclidean distance, to 1e-9 m)."""
    scene, params = corner_drops
    ts = np.linspace(0.0, 1.5, 301)
    traj = estim.simulate(scene, params, 1.5, ts=ts, max_segments=96, keep=("samples", "solution"))
    ode = estim.simulate(scene, params, 1.5, ts=ts, keep=("samples",), solver=diffrax.Tsit5(), max_steps=4096,
                         rtol=1e-11, atol=1e-12)
    kinds, axes = np.asarray(traj.solution.structure.kind), np.asarray(traj.solution.segments.normal)
    assert np.sum(np.any((kinds == ROLL) & np.all(axes == 0, axis=-1), axis=1)) >= 50
    q, v = np.asarray(traj.position), np.asarray(traj.velocity)
    np.testing.assert_allclose(q, np.asarray(ode.position), rtol=0, atol=1e-9)
    r = np.asarray(params.radius)
    depth = np.min(box_distance(q, scene.box_centre, scene.box_half), axis=-1) - r[:, None]
    assert depth.min() >= -1e-9 and np.min(q[..., 2] - r[:, None]) >= -1e-9
    energy = G * q[..., 2] + 0.5 * np.sum(v**2, axis=-1)
    assert np.max(np.diff(energy, axis=1)) <= 1e-12


def test_derivatives_through_a_roll_over_a_corner_match_finite_differences():
    """d(positions at 0.05 s and 0.12 s, final position)/d(vx0, vy0) of a ball dropped onto a
    corner that rolls over it off the vertical plane through the vertex, then over an
    edge: jacfwd through the closed form against central differences."""
    scene = estim.load_scene(str(EXACT_STAIRS))
    vertex, r = np.array([2.7, -0.6, 0.6]), 0.058
    out = np.array([np.sin(0.3) * np.cos(0.7), -np.sin(0.3) * np.sin(0.7), np.cos(0.3)])
    x = jnp.concatenate([jnp.array([1e-12, 1.0, r]), jnp.asarray(vertex + (r + 1e-4) * out), jnp.array([0.03, 0.15, -0.05])])
    t_end = jnp.asarray(0.2)

    def positions(out):
        return np.concatenate([np.ravel(out[1]), np.asarray(out[2])])

    _, (_, js, jf, _), axes, complete = one_ball(scene, x, t_end, TWO_TIMES)
    assert complete
    assert np.all(np.asarray(axes[1]) == 0)  # (the second segment: the roll over the corner)
    jac = np.concatenate([np.asarray(js).reshape(-1, 9), np.asarray(jf)])[:, 6:8]
    fd = central_differences(scene, x, t_end, TWO_TIMES, positions, (6, 7), 1e-7)
    np.testing.assert_allclose(jac, fd, rtol=0, atol=1e-7 * np.abs(jac).max())
