"""The hard-case catalogue of issue 5 (docs/pages/hard-cases.md): one test per named case.

Every case is checked against an independent truth: closed forms worked out by hand in the
test (Zeno accumulation time and point, ballistic contact times, reset maps), or
``Reference2D`` below, a plain-numpy event-by-event simulator that follows every bounce
one by one (no closed-form sums) in the x-z plane of the seed stairs, round edges included.
Gradients (``jax.jacfwd`` of the final position, the event times and the samples with
respect to e, mu_t and vx0) are compared with closed-form derivatives or with central finite
differences where the trajectory is smooth in the parameters, and checked finite where it
is not (the tolerance is written next to each assertion).

Each test runs once per solver path (``PATHS``): the closed form, and the ODE path of
issue 4 (a diffrax solver forced on these gravity-only scenes). The path switch is in one
place, ``simulate``/``_jac_any`` below.

Speed: every simulation here is a batch padded to the suite's fixed B balls and NT sample
times on the seed stairs (``conftest``), so the module reuses the compiled programs of
tests/test_simulate.py and tests/test_properties.py (forward, Jacobian and single ball).
The ODE path compiles its own four programs once for the module (forward, jacfwd, jax.grad,
single ball): its tolerances are traced, its max_steps and shapes are those of every call.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import (
    BATCH_ROUNDING,
    NT,
    B,
    G,
    box_distance,
    grad_final_x,
    jac_outputs,
    padded_params,
    padded_ts,
)

import estim
from estim.forward._constants import ROLL

# ---------------------------------------------------------------------------------------
# The solver paths: the only place that knows how each one is called.
# ---------------------------------------------------------------------------------------

PATHS = ["closed_form", "ode"]
# Times (s) and positions (m) must match the truths to TOL[path]; derivatives to DTOL[path]
# (relative, against closed forms; finite differences get their own tolerance).
# The ODE path (forced with diffrax.Tsit5 on these gravity-only scenes, default rtol 1e-8,
# atol 1e-9, contact slack 1e-6 m) meets the same tolerances: in a vacuum every flight is
# a parabola, which a Runge-Kutta step of order >= 2 reproduces to rounding, each contact
# time is a Newton root of the RK step's guard (to rounding), and bounce series are summed
# by the same closed forms (the contact law's, estim.forward.laws). rtol and the slack bound the error only where
# the path is not a parabola (air), which no case here has.
TOL = {"closed_form": 1e-9, "ode": 1e-9}
DTOL = {"closed_form": 1e-8, "ode": 1e-8}
# A ball alone and in a batch: on the closed-form path faces and counts bit for bit, times
# and states to rounding (conftest.BATCH_ROUNDING, relative and absolute). On the ODE path the
# discrete structure (event times, faces, counts) is bit for bit too, but positions and
# velocities differ by a few ulp: the program compiled for B balls and the one for a single
# ball round the Runge-Kutta sums differently (XLA vectorises and contracts multiply-adds
# per program). Measured: at most 4.3e-14 on 50 m/s velocities (6 ulp) and 7.1e-15 m at
# x = 52 m; 1e-12 still catches any coupling between balls.
BATCH_TOL = {"closed_form": BATCH_ROUNDING, "ode": 1e-12}
BATCH_RTOL = {"closed_form": BATCH_ROUNDING, "ode": 0.0}


def simulate(scene, params, t_end, path, **kw) -> estim.Trajectory:
    """``estim.simulate`` on the solver path ``path``."""
    if path == "closed_form":
        return estim.simulate(scene, params, t_end, **kw)
    if path == "ode":  # a diffrax solver forces the ODE path, even without air
        import diffrax

        return estim.simulate(scene, params, t_end, solver=diffrax.Tsit5(), **kw)
    raise ValueError(f"unknown solver path {path!r} (PATHS: {PATHS})")


@functools.partial(jax.jit, static_argnames="path")
def _jac_any(scene, theta, radius, position, velocity, t_end, ts, path):
    def f(delta):
        th = theta + delta
        vel = velocity.at[:, 0].set(th[:, 2])
        p = estim.Params(th[:, 0], th[:, 1], radius, position, vel)
        traj = simulate(scene, p, t_end, path, ts=ts, throw=False)
        return (traj.final.position, traj.events.t, traj.position,
                traj.complete.astype(jnp.float64))

    zero = jnp.zeros(3)
    return f(zero), jax.jacfwd(f)(zero)


@functools.partial(jax.jit, static_argnames="path")
def _grad_any(scene, theta, radius, position, velocity, t_end, ts, path):
    def f(th0):
        th = theta.at[0].set(th0)
        vel = velocity.at[:, 0].set(th[:, 2])
        p = estim.Params(th[:, 0], th[:, 1], radius, position, vel)
        return simulate(scene, p, t_end, path, ts=ts, throw=False).final.position[0, 0]

    return jax.grad(f)(theta[0])


def _theta_args(params: estim.Params, t_end, ts):
    """The padded arguments of the compiled derivative programs: (theta = (e, mu_t, vx0)
    per ball, radius, position, velocity, t_end, sample times)."""
    padded, _ = padded_params(params.e, params.mu_t, params.radius, params.position,
                              params.velocity)
    theta = jnp.stack([padded.e, padded.mu_t, padded.velocity[:, 0]], axis=1)
    ts = padded_ts(np.linspace(0.0, t_end, NT) if ts is None else ts)
    return (theta, padded.radius, padded.position, padded.velocity, jnp.asarray(float(t_end)), ts)


def reverse_gradient(scene, params: estim.Params, t_end, path, ts=None):
    """``jax.grad`` (reverse mode) of the first ball's final x w.r.t. its (e, mu_t, vx0)."""
    args = _theta_args(params, t_end, ts)
    if path == "closed_form":  # conftest's compiled program (exact geometry: this module's alone)
        return np.asarray(grad_final_x(scene, *args))
    return np.asarray(_grad_any(scene, *args, path=path))


def jacobian(scene, params: estim.Params, t_end, path, ts=None):
    """Values and per-ball ``jax.jacfwd`` w.r.t. (e, mu_t, vx0) of (final position, event
    times, sampled positions): ``((final, t, samples), (d final, d t, d samples))`` for the
    balls of ``params`` (each Jacobian with a trailing axis of 3)."""
    k = params.batch_shape[0]
    args = _theta_args(params, t_end, ts)
    if path == "closed_form":  # conftest's compiled program (exact geometry: this module's alone)
        values, jac = jac_outputs(scene, *args)
    else:
        values, jac = _jac_any(scene, *args, path=path)
    assert np.all(np.asarray(values[3][:k]) == 1.0), "a ball did not reach t_end"
    return (tuple(np.asarray(v[:k]) for v in values[:3]),
            tuple(np.asarray(j[:k]) for j in jac[:3]))


# ---------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def stairs(stairs_exact):
    """The hard cases run on the seed's staircase with exact edges and corners (the seed's
    own geometry, with no edges, lets balls pass through them)."""
    return stairs_exact

R = 0.05  # the golf ball of the seed
E_DEF, MU_DEF = 0.5, 0.9


class Ball(NamedTuple):
    e: float
    mu: float
    pos: tuple
    vel: tuple
    r: float = R


def params_of(balls) -> estim.Params:
    e, mu, pos, vel, r = (np.array(x, dtype=np.float64) for x in zip(*balls, strict=True))
    return estim.Params(e, mu, r, pos, vel)


def run(scene, params: estim.Params, t_end, path, ts=None) -> estim.Trajectory:
    """``simulate`` on ``params`` padded to B balls and NT sample times (slice the first
    ``params.batch_shape[0]`` balls of the result); asserts every ball reached t_end."""
    k = params.batch_shape[0]
    padded, _ = padded_params(params.e, params.mu_t, params.radius, params.position,
                              params.velocity)
    ts = padded_ts(np.linspace(0.0, t_end, NT) if ts is None else ts)
    traj = simulate(scene, padded, t_end, path, ts=ts, throw=False)
    assert np.all(np.asarray(traj.complete[:k])), "a ball did not reach t_end"
    return traj


def events(scene, traj, i):
    """Events of ball i: list of (t, position, velocity before, after, (solid, face), kind)."""
    ev = traj.events
    n = int(ev.count[i])
    return [
        (float(ev.t[i, j]), np.asarray(ev.position[i, j]), np.asarray(ev.velocity_pre[i, j]),
         np.asarray(ev.velocity_post[i, j]), scene.face_label(int(ev.face[i, j])),
         "impact" if int(ev.kind[i, j]) == 0 else "settle")
        for j in range(n)
    ]


def central_differences(scene, balls, t_end, path, h=1e-6, ts=None):
    """Central differences, step h, of (final position, event times, samples) w.r.t.
    (e, mu_t, vx0) of each ball: arrays shaped like ``jacobian``'s. Components whose
    perturbation would leave [0, 1] are NaN."""
    rows, ok = [], []
    for b in balls:
        for k in range(3):
            for sign in (1.0, -1.0):
                th = np.array([b.e, b.mu, b.vel[0]]) + sign * h * np.eye(3)[k]
                ok.append(k == 2 or 0.0 <= th[k] <= 1.0)
                th[:2] = np.clip(th[:2], 0.0, 1.0)
                rows.append(Ball(th[0], th[1], b.pos, (th[2], *b.vel[1:]), b.r))
    out = []
    for start in range(0, len(rows), B):
        chunk = rows[start:start + B]
        tr = run(scene, params_of(chunk), t_end, path, ts)
        n = len(chunk)
        ev_t = np.asarray(tr.events.t[:n])
        out.append((np.asarray(tr.final.position[:n]), np.where(np.isfinite(ev_t), ev_t, 0.0),
                    np.asarray(tr.position[:n])))
    fin, evt, smp = (np.concatenate(x) for x in zip(*out, strict=True))
    ok = np.array(ok).reshape(len(balls), 3, 2).all(axis=2)

    def quotient(x):
        x = x.reshape((len(balls), 3, 2) + x.shape[1:])
        d = (x[:, :, 0] - x[:, :, 1]) / (2.0 * h)
        d = np.where(ok.reshape(ok.shape + (1,) * (d.ndim - 2)), d, np.nan)
        return np.moveaxis(d, 1, -1)

    return quotient(fin), quotient(evt), quotient(smp)


def assert_outside(scene, traj, k, r=R):
    """Samples and final states of the first k balls (radius r) lie outside every solid:
    distance >= r from every box, centre >= r above the ground, to 1e-9 m."""
    final = np.asarray(traj.final.position[:k])[:, None, :]
    for pts in (np.asarray(traj.position[:k]), final):
        depth = box_distance(pts, scene.box_centre, scene.box_half)
        assert np.all(depth >= r - 1e-9), float(np.min(depth - r))
        assert np.all(pts[..., 2] >= r - 1e-9)


def energy(p, v):
    return G * np.asarray(p)[..., 2] + 0.5 * np.sum(np.asarray(v) ** 2, axis=-1)


def drop(h, e):
    """A ball dropped from h above a horizontal face: (fall time, impact speed w, first
    rebound flight T0 = 2 e w / g, accumulation time t_fall + T0 / (1 - e))."""
    t_fall = math.sqrt(2.0 * h / G)
    w = G * t_fall
    T0 = 2.0 * e * w / G
    return t_fall, w, T0, t_fall + T0 / (1.0 - e)


def landing_time(height, vz):
    """Time for a ball at ``height`` above a horizontal face, vertical velocity vz, to reach
    it (the decreasing root of height + vz t - g t^2 / 2)."""
    return (vz + math.sqrt(vz * vz + 2.0 * G * height)) / G


def reset(v, n, e, mu):
    """The documented reset map, v+ = mu (v - (v.n) n) - e (v.n) n."""
    v, n = np.asarray(v, float), np.asarray(n, float)
    vn = v @ n
    return mu * (v - vn * n) - e * vn * n


# ---------------------------------------------------------------------------------------
# An independent reference: every bounce one by one, in the x-z plane of the seed stairs
# with exact edges (balls with y away from the treads' ends). Each tread, grown by r, has a
# top and two risers (lines) and two round edges (quarter circles of radius r about its
# top corners); beyond the last tread is the ground. Contact times on an edge are the real
# roots of the quartic |q(t) - corner|^2 = r^2 by numpy's companion-matrix eigenvalues,
# polished by Newton's method: another method than estim's (estim.forward._curved).
# ---------------------------------------------------------------------------------------


class Face(NamedTuple):
    name: str  # e.g. "step1+x+z"
    solid: str
    n: np.ndarray  # a line's unit outward normal (x, z); an edge's quadrant (+-1, 1)
    h: float  # a line lies on the plane n . q = h ...
    a: np.ndarray  # ... between the points a and b; an edge: a is its corner point
    b: np.ndarray
    rank: int  # 1: top, riser, ground; 2: edge


def stairs_faces(r):
    faces = [Face("ground", "ground", np.array([0.0, 1.0]), r, np.array([-1e6, r]),
                  np.array([1e6, r]), 1)]
    for k in range(5):
        name, lo, hi, top = f"step{k + 1}", -0.3 + 0.6 * k, 0.3 + 0.6 * k, 1.40 - 0.2 * k

        def P(x, z):
            return np.array([x, z], dtype=np.float64)

        faces += [
            Face(f"{name}+z", name, P(0, 1), top + r, P(lo, top + r), P(hi, top + r), 1),
            Face(f"{name}+x+z", name, P(1, 1), 0.0, P(hi, top), P(hi, top), 2),
            Face(f"{name}-x+z", name, P(-1, 1), 0.0, P(lo, top), P(lo, top), 2),
            Face(f"{name}+x", name, P(1, 0), hi + r, P(hi + r, top), P(hi + r, -1.0), 1),
            Face(f"{name}-x", name, P(-1, 0), -(lo - r), P(lo - r, -1.0), P(lo - r, top), 1),
        ]
    return faces


def _entering(g0, g1, g2, tol=1e-12):
    """Smallest tau >= 0 at which g0 + g1 tau + g2 tau^2 / 2 reaches 0 decreasing."""
    if abs(g0) <= tol and (g1 < -tol or (abs(g1) <= tol and g2 < 0)):
        return 0.0
    if g2 == 0.0:
        return -g0 / g1 if g1 < 0 and -g0 / g1 > 0 else math.inf
    disc = g1 * g1 - 2.0 * g2 * g0
    if disc <= 0:
        return math.inf
    s = math.sqrt(disc)
    tau = 2.0 * g0 / (s - g1) if g1 < 0 else (-g1 - s) / g2
    return tau if tau > 0 and (g1 < 0 or g2 < 0) else math.inf


def _edge_entering(f, q, v, acc, r, tol=1e-12):
    """Smallest tau >= 0 at which the centre enters the circle of radius r about edge f's
    corner, in its quadrant (inf if never)."""
    A, B, C = q - f.a, v, 0.5 * acc
    rho = math.hypot(*A)
    g0, g1 = rho - r, float(A @ B) / rho
    g2 = (float(B @ B) + 2.0 * float(A @ C)) / rho - g1 * g1 / rho
    if abs(g0) <= tol and (g1 < -tol or (abs(g1) <= tol and g2 < -tol)):
        return 0.0
    coeffs = [C @ C, 2 * B @ C, B @ B + 2 * A @ C, 2 * A @ B, A @ A - r * r]
    if coeffs[0] == 0.0:
        coeffs = coeffs[2:]
    best = math.inf
    for z in np.roots(coeffs):
        if abs(z.imag) > 1e-6 * max(1.0, abs(z.real)):
            continue
        t = z.real
        for _ in range(3):  # Newton on D(t) = |P(t)|^2 - r^2
            P, dP = A + B * t + C * t * t, B + 2 * C * t
            slope = 2 * float(P @ dP)
            if slope != 0:
                t -= (float(P @ P) - r * r) / slope
        P, dP = A + B * t + C * t * t, B + 2 * C * t
        p = f.a + P
        in_quadrant = f.n[0] * (p[0] - f.a[0]) >= -1e-9 and p[1] - f.a[1] >= -1e-9
        if t > 1e-12 and float(P @ dP) < 0 and in_quadrant:
            best = min(best, t)
    # A hop off the edge too low for the quartic's float64 (estim.forward._contact: 1 nm).
    if abs(g0) <= tol and g1 > 0 > g2 and g1 * g1 <= -2.0 * g2 * 1e-9:
        best = min(best, -2.0 * g1 / g2)
    return best


def _normal(f, q, r):
    return f.n if f.rank == 1 else (q - f.a) / math.hypot(*(q - f.a))


def _along(f, q):
    """Distance of q along the face from its end a, and the face's length."""
    d = f.b - f.a
    length = math.hypot(*d)
    return float((q - f.a) @ d) / length, length


def _roll(f, q, v, r, t_left, dt=1e-5):
    """A ball at q with velocity v rolling over edge f (the circle of radius r about its
    corner, in its quadrant), integrated: theta'' = (g / r) sin theta (theta from the
    vertical, towards the outside of the edge) by classical Runge-Kutta (dt = 1e-5 s), its
    end (k cos theta = theta'^2: the ball leaves the edge; or theta = 0 moving back: on top
    of the tread again) found by bisection of the last step. Returns (tau, q, v, on_top),
    tau <= t_left. An integrator, not estim's closed form (elliptic integrals,
    estim.forward._roll)."""
    side, k = float(f.n[0]), G / r

    def state(th, om):
        return (f.a + r * np.array([side * math.sin(th), math.cos(th)]),
                r * om * np.array([side * math.cos(th), -math.sin(th)]))

    d = q - f.a
    th = math.atan2(side * d[0], d[1])
    om = float(v @ np.array([side * math.cos(th), -math.sin(th)])) / r

    def rk4(th, om, h):
        def f_(y):
            return (y[1], k * math.sin(y[0]))
        k1 = f_((th, om))
        k2 = f_((th + h / 2 * k1[0], om + h / 2 * k1[1]))
        k3 = f_((th + h / 2 * k2[0], om + h / 2 * k2[1]))
        k4 = f_((th + h * k3[0], om + h * k3[1]))
        return (th + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]),
                om + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]))

    def ended(th, om):
        return k * math.cos(th) - om * om <= 0 or th < 0

    t = 0.0
    while t < t_left:
        h = min(dt, t_left - t)
        nxt = rk4(th, om, h)
        if ended(*nxt):
            lo, hi = 0.0, h
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if not ended(*rk4(th, om, mid)) else (lo, mid)
            th, om = rk4(th, om, hi)
            return t + hi, *state(max(th, 0.0), om), th <= 0
        th, om, t = *nxt, t + h
    return t_left, *state(th, om), False


class Reference2D:
    """The contact model of docs/pages/contact-model.md, one bounce at a time.

    Flights are parabolas; the first face entered ends a flight (ties within 1e-9 s go to
    the lower rank). A bounce series on a supporting face is followed bounce by bounce
    until a rebound is slower than 1e-9 m/s, where it settles (tangential velocity kept if
    mu = 1, else 0) and slides with the tangential part of gravity until it leaves its
    face. A ball that reaches an edge without normal speed, pressed onto it, rolls over it
    (``_roll``, integrated; ``rolls`` lists them) until it leaves it, or is back on top of
    the tread, where it slides. ``events``: (t, x, z, vx-, vz-, vx+, vz+, face name,
    "impact" | "settle"); ``final``: (t, x, z, vx, vz).
    """

    def __init__(self, e, mu, x0, z0, vx0, vz0, t_end, r=R, max_events=100_000):
        faces = stairs_faces(r)
        a = np.array([0.0, -G])
        t, q, v = 0.0, np.array([x0, z0], float), np.array([vx0, vz0], float)
        support, sliding, last = None, False, None
        self.events, self.rolls = [], []  # (start time, start angle) of each roll
        while len(self.events) < max_events:
            acc = a - (a @ support.n) * support.n if sliding else a
            best, face = math.inf, None
            for f in faces:
                if f is support:
                    continue
                if f.rank == 2:
                    tau = _edge_entering(f, q, v, acc, r)
                else:
                    g0, g1, g2 = float(f.n @ q - f.h), float(f.n @ v), float(f.n @ acc)
                    # Back onto the face it just bounced off: exactly after 2 g1 / |g2|.
                    tau = -2.0 * g1 / g2 if (f is last and g1 > 0 > g2) else _entering(g0, g1, g2)
                if not tau < math.inf:
                    continue
                qc = q + v * tau + 0.5 * acc * tau * tau
                if f.rank == 1:
                    s, length = _along(f, qc)
                    if not -1e-9 <= s <= length + 1e-9:
                        continue
                if tau < best - 1e-9 or (tau <= best + 1e-9 and f.rank < face.rank):
                    best, face = tau, f
            tau_exit = math.inf
            if sliding:  # leaves its face through one end or the other
                s, length = _along(support, q)
                u = (support.b - support.a) / length
                s1, s2 = float(v @ u), float(acc @ u)
                tau_exit = min(_entering(length - s, -s1, -s2), _entering(s, s1, s2))
            tau = min(best, tau_exit)
            if t + tau >= t_end:
                tau = t_end - t
                q, v, t = q + v * tau + 0.5 * acc * tau * tau, v + acc * tau, t_end
                break
            q, v, t = q + v * tau + 0.5 * acc * tau * tau, v + acc * tau, t + tau
            if tau_exit < best:
                sliding, last, support = False, None, support
                continue
            n = _normal(face, q, r)
            vn = float(v @ n)
            tangential = v - vn * n
            post = mu * tangential - e * vn * n
            touch = -vn <= 1e-9  # no impact: the normal velocity is dropped
            dies = e * -vn <= 1e-9 and float(a @ n) < 0  # the series dies out
            if face.rank == 2:
                if touch or dies:
                    post = tangential * (1.0 if (touch or mu == 1.0) else 0.0)
                    across = float(post @ post) - float(post @ n) ** 2
                    self.events.append((t, *q, *v, *post, face.name, "settle"))
                    v, support, sliding, last = post, face, False, None
                    if float(a @ n) + across / r < 0:  # pressed onto the edge: it rolls over it
                        self.rolls.append((t, float(math.atan2(float(face.n[0]) * (q - face.a)[0], (q - face.a)[1]))))
                        tau, q, v, on_top = _roll(face, q, post, r, t_end - t)
                        t += tau
                        if on_top:  # sliding on the tread's top
                            support = next(f for f in faces if f.name == face.solid + "+z")
                            sliding = True
                        if t >= t_end:
                            break
                else:
                    self.events.append((t, *q, *v, *post, face.name, "impact"))
                    v, support, sliding, last = post, None, False, face
                continue
            q = q - (float(face.n @ q) - face.h) * face.n  # exactly on the face's plane
            if touch or dies:
                post = tangential * (1.0 if (touch or mu == 1.0) else 0.0)
                self.events.append((t, *q, *v, *post, face.name, "settle"))
                v, support, sliding, last = post, face, True, None
            else:
                self.events.append((t, *q, *v, *post, face.name, "impact"))
                v, support, sliding, last = post, None, False, face
        self.final = (t, *q, *v)

    def impacts(self):
        return [x for x in self.events if x[8] == "impact"]


def assert_matches_reference(scene, traj, i, ref, tol, n=None, final=True):
    """estim's events of ball i (the first n, default all it lists) are the reference's,
    in order: time, position, velocities, face (to tol); its final state too (``final``).
    A Zeno series lists only bounces whose flight lasts >= 1 us, then one settle: the
    reference's bounces are matched by time."""
    ours = events(scene, traj, i)[:n]
    ref_t = np.array([x[0] for x in ref.events])
    for t, p, _, post, (solid, label), kind in ours:
        m = int(np.argmin(np.abs(ref_t - t)))
        x = ref.events[m]
        assert abs(x[0] - t) <= tol, (t, x)
        if kind == "settle":  # the reference stops a series at a rebound < 1e-9 m/s
            m = next(j for j in range(m, len(ref.events)) if ref.events[j][8] == "settle")
            x = ref.events[m]
            assert abs(x[0] - t) <= tol, (t, x)
        assert x[7] == (solid if label == "plane" else solid + label), (x, solid, label)
        assert x[8] == kind, (x, kind)
        np.testing.assert_allclose(p[[0, 2]], x[1:3], rtol=0, atol=tol)
        np.testing.assert_allclose(post[[0, 2]], x[5:7], rtol=0, atol=max(tol, 1e-8))
    if not final:
        return ours
    t_end = float(traj.final.t[i])
    assert ref.final[0] == pytest.approx(t_end, abs=0)
    np.testing.assert_allclose(np.asarray(traj.final.position[i])[[0, 2]], ref.final[1:3],
                               rtol=0, atol=tol)
    np.testing.assert_allclose(np.asarray(traj.final.velocity[i])[[0, 2]], ref.final[3:5],
                               rtol=0, atol=max(tol, 1e-8))
    return ours


def assert_rolls_over_the_edge(scene, params, t_end, path, ref, tol, bounces_on_edge=False):
    """Ball 0 reaches an edge without normal speed, pressed onto it, and rolls over it
    (estim.forward._roll; the reference integrates the roll): every contact is the
    reference's, in order, and so is the final state.

    Every bounce is listed (none is summed: those on an edge are each a segment), so the
    events pair one to one, however short the flights between them. Where the bounces on an
    edge die out, the last is a settle for the reference (it drops the normal speed below
    1e-9 m/s) and an impact or a settle for estim (which keeps e times it).

    A ball that starts to roll at rest theta0 from the top leaves the edge after about
    sqrt(r / g) ln(1 / theta0): the roll multiplies an error in its start by about
    1 / theta0, and so the tolerance after it (the reference's integrator is converged to
    1e-12 s, and ``test_roll_matches_an_integrator`` checks the roll alone to that).

    ``bounces_on_edge``: the ball bounces on the edge before it rolls. The ODE path takes
    a hop lower than its contact slack (1 um) there for a touch (its prediction cannot
    resolve it), the rest of the series for the law's limit of one (the ball settles), and
    so starts to roll where the reference is still bouncing, 76 um up the fillet from
    where the reference starts (near the top, from rest, where the roll takes 1 / theta0
    longer): its events pair one to one up to its first contact with the edge, then it
    rolls over the edge and lands on the next tread."""
    padded, _ = padded_params(params.e, params.mu_t, params.radius, params.position, params.velocity)
    traj = simulate(scene, padded, t_end, path, ts=padded_ts(np.linspace(0.0, t_end, NT)), max_events=256)
    assert ref.rolls and bool(traj.complete[0])
    ours = events(scene, traj, 0)
    assert_outside(scene, traj, 1)
    if path == "ode" and bounces_on_edge:
        first = next(j for j, x in enumerate(ref.events) if x[7].endswith(("x+z", "y+z")))
        assert len(ours[first][4][1]) == 4 and len(ours[first + 1][4][1]) == 2, ours[first:first + 2]
        assert ours[first + 1][4][0] == ref.events[-1][7][:5]  # (lands where the reference does)
        t, p, _, _, (solid, label), _ = ours[first]  # (then it settles: its velocity is not the reference's)
        assert abs(ref.events[first][0] - t) <= tol and ref.events[first][7] == solid + label
        np.testing.assert_allclose(p[[0, 2]], ref.events[first][1:3], rtol=0, atol=tol)
        ref_events, ours = ref.events[:first], ours[:first]
    else:
        ref_events = ref.events
    assert len(ours) == len(ref_events), (len(ours), len(ref_events))
    t_roll, theta0 = ref.rolls[0]
    after = tol * max(1.0, 1.0 / max(abs(theta0), 1e-300))
    for (t, p, _, post, (solid, label), kind), x in zip(ours, ref_events, strict=True):
        tol = after if x[0] > t_roll else tol
        assert abs(x[0] - t) <= tol, (t, x)
        assert x[7] == (solid if label == "plane" else solid + label), (x, label)
        assert x[8] == kind or len(label) == 4, (x, kind)
        np.testing.assert_allclose(p[[0, 2]], x[1:3], rtol=0, atol=tol)
        np.testing.assert_allclose(post[[0, 2]], x[5:7], rtol=0, atol=max(tol, 1e-8))
    if ref_events is ref.events:
        np.testing.assert_allclose(np.asarray(traj.final.position[0])[[0, 2]], ref.final[1:3], rtol=0, atol=after)
        np.testing.assert_allclose(np.asarray(traj.final.velocity[0])[[0, 2]], ref.final[3:5], rtol=0,
                                   atol=max(after, 1e-8))
    return events(scene, traj, 0)


def assert_jacobian(jac, truth, rtol, atol=0.0):
    """A Jacobian row equals its truth (closed form or finite differences) wherever the
    truth is a number (NaN marks components not compared)."""
    truth = np.asarray(truth, dtype=np.float64)
    jac = np.asarray(jac)
    assert np.all(np.isfinite(jac)), jac
    known = np.isfinite(truth)
    np.testing.assert_allclose(jac[known], truth[known], rtol=rtol, atol=atol)


# ---------------------------------------------------------------------------------------
# Zeno
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("path", PATHS)
def test_zeno_on_a_flat_tread(stairs, path):
    """Golf dropped from 0.3 m above step2 at vx0 = 0.2 m/s, e = 0.6, mu_t = 0.8: infinitely
    many bounces accumulate at t_fall + T0 / (1 - e) (T0 = 2 e w / g) and the ball rests at
    x0 + vx0 (t_fall + mu T0 / (1 - e mu)). Derivatives of the accumulation time and the rest
    point: closed forms."""
    e, mu, vx0, x0, h = 0.6, 0.8, 0.2, 0.45, 0.3
    ball = Ball(e, mu, (x0, 0.0, 1.25 + h), (vx0, 0.0, 0.0))
    t_fall, w, T0, t_acc = drop(h, e)
    x_rest = x0 + vx0 * (t_fall + mu * T0 / (1 - e * mu))
    traj = run(stairs, params_of([ball]), 1.5, path)
    ev = events(stairs, traj, 0)
    assert all(x[4] == ("step2", "+z") for x in ev)
    assert [x[5] for x in ev] == ["impact"] * (len(ev) - 1) + ["settle"]
    # Bounce k (from 0) at t_fall + T0 (1 - e^k) / (1 - e), x_k by eq. (1) of the docs.
    k = np.arange(len(ev) - 1)
    t_k = t_fall + T0 * (1 - e**k) / (1 - e)
    x_k = x0 + vx0 * (t_fall + mu * T0 * (1 - (e * mu) ** k) / (1 - e * mu))
    np.testing.assert_allclose([x[0] for x in ev[:-1]], t_k, rtol=0, atol=TOL[path])
    np.testing.assert_allclose([x[1][0] for x in ev[:-1]], x_k, rtol=0, atol=TOL[path])
    # Listed: the bounces whose flight (T0 e^(k-1) before bounce k) lasts at least 1 us.
    assert T0 * e ** (k[-1] - 1) >= 1e-6 > T0 * e ** k[-1]
    assert ev[-1][0] == pytest.approx(t_acc, abs=TOL[path])
    np.testing.assert_allclose(ev[-1][1], [x_rest, 0.0, 1.25], rtol=0, atol=TOL[path])
    np.testing.assert_allclose(np.asarray(traj.final.position[0]), [x_rest, 0.0, 1.25],
                               rtol=0, atol=TOL[path])
    np.testing.assert_array_equal(np.asarray(traj.final.velocity[0]), [0.0, 0.0, 0.0])
    # Derivatives w.r.t. (e, mu_t, vx0): t_acc = t_fall (1 + e) / (1 - e).
    (_, evt, _), (jfin, jevt, _) = jacobian(stairs, params_of([ball]), 1.5, path)
    n = len(ev)
    assert_jacobian(jevt[0, n - 1], [2 * t_fall / (1 - e) ** 2, 0.0, 0.0], DTOL[path], 1e-12)
    c = 2 * w / G / (1 - e * mu) ** 2
    assert_jacobian(jfin[0, 0], [vx0 * mu * c, vx0 * e * c, x_rest / vx0 - x0 / vx0],
                    DTOL[path], 1e-12)
    assert_jacobian(jfin[0, 2], [0.0, 0.0, 0.0], 0.0, 1e-12)


@pytest.mark.parametrize("side", ["before", "beyond"])
@pytest.mark.parametrize("path", PATHS)
def test_zeno_near_a_tread_edge(stairs, path, side):
    """Golf dropped 0.2 m above step1 at vx0 = 0.3, e = 0.5, mu_t = 0.9, placed so that the
    accumulation point lies 0.1 mm before or beyond the tread's edge (x = 0.3).

    before: the whole series is summed; the ball rests 0.1 mm before the edge. Derivatives:
    closed form.
    beyond: the series is cut after the last bounce that lands on the tread; the next
    flight meets the round edge, a series of bounces on it accumulates there, the ball
    comes to rest on the fillet and rolls over the edge, leaves it and lands on step2.
    Truth: the bounce-by-bounce reference, its roll integrated."""
    e, mu, u, h = E_DEF, MU_DEF, 0.3, 0.2
    t_fall, w, T0, t_acc = drop(h, e)
    reach = u * (t_fall + mu * T0 / (1 - e * mu))
    x0 = 0.3 - reach + (-1e-4 if side == "before" else 1e-4)
    ball = Ball(e, mu, (x0, 0.0, 1.45 + h), (u, 0.0, 0.0))
    t_end = 1.5
    ref = Reference2D(e, mu, x0, 1.45 + h, u, 0.0, t_end)
    if side == "beyond":
        # The bounces on step1 whose landing point x_k lies on the tread are all listed
        # (their flights last >= 1 us), then the edge, bounce after bounce, until the ball
        # rests on the fillet 0.1 mm beyond the edge and rolls over it, then step2.
        # The bounces on the round edge accumulate rounding (each bounce on the curve
        # magnifies the last bit of the one before): an event time 1.2e-9 s from the
        # reference's on the JAX planner (jax 0.10.2, numpy 2.4.6), 2.2e-9 s on the native
        # kernels (their libm's last bits); four times the tolerance here (the ODE path, which
        # settles at its first contact with the edge: twice).
        edge_tol = (4 if path == "closed_form" else 2) * TOL[path]
        ev = assert_rolls_over_the_edge(stairs, params_of([ball]), t_end, path, ref, edge_tol,
                                        bounces_on_edge=True)
        labels = [x[4] for x in ev]
        k = np.arange(60)
        x_k = x0 + u * (t_fall + mu * T0 * (1 - (e * mu) ** k) / (1 - e * mu))
        on_tread = int(np.sum(x_k <= 0.3))
        assert labels[:on_tread] == [("step1", "+z")] * on_tread
        on_edge = labels.index(("step2", "+z"))
        # (The ODE path settles at its first contact with the edge, a hop below its slack.)
        assert set(labels[on_tread:on_edge]) == {("step1", "+x+z")} and on_edge > on_tread + (path == "closed_form")
        return
    traj = run(stairs, params_of([ball]), t_end, path)
    ev = assert_matches_reference(stairs, traj, 0, ref, TOL[path])
    assert_outside(stairs, traj, 1)
    labels = [x[4] for x in ev]
    (_, evt, _), (jfin, jevt, _) = jacobian(stairs, params_of([ball]), t_end, path)
    assert set(labels) == {("step1", "+z")}
    assert ev[-1][0] == pytest.approx(t_acc, abs=TOL[path])
    np.testing.assert_allclose(np.asarray(traj.final.position[0]), [0.3 - 1e-4, 0, 1.45],
                               rtol=0, atol=TOL[path])
    c = 2 * w / G / (1 - e * mu) ** 2
    assert_jacobian(jfin[0, 0], [u * mu * c, u * e * c, reach / u], DTOL[path], 1e-12)


@pytest.mark.parametrize("path", PATHS)
def test_zeno_pure_vertical(stairs, path):
    """vx0 = 0: golf dropped 0.4 m onto the middle of step3, e = 0.7: bounces in place, all
    at x = 1.2 exactly, and rests at t_fall (1 + e) / (1 - e). Derivatives: d t_acc / d e =
    2 t_fall / (1 - e)^2, d x / d vx0 = t_fall + mu T0 / (1 - e mu), zero w.r.t. e and mu_t."""
    e, mu, h = 0.7, MU_DEF, 0.4
    ball = Ball(e, mu, (1.2, 0.0, 1.05 + h), (0.0, 0.0, 0.0))
    t_fall, w, T0, t_acc = drop(h, e)
    traj = run(stairs, params_of([ball]), 2.0, path)
    ev = events(stairs, traj, 0)
    assert ev[-1][5] == "settle" and ev[-1][0] == pytest.approx(t_acc, abs=TOL[path])
    for _, p, pre, post, face, _ in ev:
        assert face == ("step3", "+z")
        np.testing.assert_allclose(p[:2], [1.2, 0.0], rtol=0, atol=1e-12)
        assert abs(pre[0]) <= 1e-12 and abs(post[0]) <= 1e-12
    np.testing.assert_allclose(np.asarray(traj.position[0])[:, :2], np.tile([1.2, 0.0], (NT, 1)),
                               rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(traj.final.velocity[0]), [0.0, 0.0, 0.0])
    (_, _, _), (jfin, jevt, _) = jacobian(stairs, params_of([ball]), 2.0, path)
    assert_jacobian(jevt[0, len(ev) - 1], [2 * t_fall / (1 - e) ** 2, 0.0, 0.0], DTOL[path],
                    1e-12)
    assert_jacobian(jfin[0, 0], [0.0, 0.0, t_fall + mu * T0 / (1 - e * mu)], DTOL[path],
                    1e-12)
    fd_fin, _, _ = central_differences(stairs, [ball], 2.0, path)
    assert_jacobian(jfin[0], fd_fin[0], 1e-6, 1e-8)


@pytest.mark.parametrize("path", PATHS)
def test_mu_one_slides_after_the_bounces_then_flies_off_the_edge(stairs, path):
    """mu_t = 1, e = 0.3, vx0 = 0.8: on each tread the bounces accumulate (Zeno), the ball
    slides on at vx0 without friction, flies off the edge, falls 0.2 m to the next tread, ...
    With mu_t = 1 nothing changes vx: x(t) = x0 + vx0 t exactly, at every sample. Truth:
    that, the accumulation and departure times by hand, and the bounce-by-bounce
    reference. At t_end = 2.3 s the ball is falling from step3 to step4.

    Gradient: d x / d vx0 = t_end, d x / d e = 0, d z / d vx0 from the departure time
    (x_edge - x0) / vx0. mu_t = 1 is a point of discontinuity (with mu_t < 1 the series
    stops the ball: it rests on step1): d / d mu_t is only checked finite."""
    e, mu, vx0, x0, h, t_end = 0.3, 1.0, 0.8, -0.25, 0.05, 2.3
    ball = Ball(e, mu, (x0, 0.0, 1.45 + h), (vx0, 0.0, 0.0))
    t_fall, w, T0, t_acc = drop(h, e)
    ts = np.linspace(0.0, t_end, NT)
    traj = run(stairs, params_of([ball]), t_end, path, ts)
    np.testing.assert_allclose(np.asarray(traj.position[0])[:, 0], x0 + vx0 * ts, rtol=0,
                               atol=1e-12)
    ref = Reference2D(e, mu, x0, 1.45 + h, vx0, 0.0, t_end)
    ev = assert_matches_reference(stairs, traj, 0, ref, TOL[path])
    settles = [x for x in ev if x[5] == "settle"]
    # Step1: accumulation at t_acc; steps 2, 3: landing after the 0.2 m fall from the edge,
    # accumulation T0' / (1 - e) later.
    t_dep = [(0.3 + 0.6 * k - x0) / vx0 for k in range(3)]
    fall = math.sqrt(0.4 / G)
    T1 = 2 * e * G * fall / G
    expect = [t_acc] + [t_dep[k] + fall + T1 / (1 - e) for k in range(2)]
    np.testing.assert_allclose([x[0] for x in settles[:3]], expect, rtol=0, atol=TOL[path])
    for x, k in zip(settles, range(3), strict=False):
        assert x[4] == (f"step{k + 1}", "+z")
        np.testing.assert_allclose(x[3], [vx0, 0.0, 0.0], rtol=0, atol=1e-12)
    z_end = 1.05 - 0.5 * G * (t_end - t_dep[2]) ** 2
    np.testing.assert_allclose(np.asarray(traj.final.position[0]),
                               [x0 + vx0 * t_end, 0.0, z_end], rtol=0, atol=TOL[path])
    (_, _, _), (jfin, _, jsmp) = jacobian(stairs, params_of([ball]), t_end, path, ts)
    dz = G * (t_end - t_dep[2]) * (1.5 - x0) / vx0**2  # t_dep[2] = (1.5 - x0) / vx0
    assert_jacobian(jfin[0, 0], [0.0, np.nan, t_end], DTOL[path], 1e-12)
    assert_jacobian(jfin[0, 2], [0.0, np.nan, -dz], DTOL[path], 1e-12)
    assert_jacobian(jsmp[0, :, 0], np.stack([0 * ts, np.nan * ts, ts], 1), DTOL[path], 1e-12)


@pytest.mark.parametrize("path", PATHS)
def test_bounces_against_a_riser_with_a_vanishing_vx(stairs, path):
    """Found by tests/test_properties.py: golf (r 0.05, e 0.625, mu_t 1) released touching
    step2's riser (x = 0.9 + r) over step3, with vx = -5e-189 and vy = 0.5. Its bounces on
    step3 are a series against the riser it touches without entering; the series' slab
    test took the 1e-188 component of its direction for motion into the riser, and the
    ball spent its 48 segments on single bounces. Truth: the series accumulates at
    t_fall + T0 / (1 - e) at x = 0.95, and with mu_t = 1 and nothing across its path in y
    the ball keeps vy: y(t) = 0.5 t at every sample (to 1.1 s: at 1.2 s it would reach the
    tread's side edge slower than sqrt(g r) and roll over it, which estim does not model)."""
    e, h, t_end = 0.625, 0.21, 1.1
    ball = Ball(e, 1.0, (0.95, 0.0, 1.05 + h), (-5.146940322656966e-189, 0.5, 0.0), 0.05)
    _, _, _, t_acc = drop(h, e)
    ts = np.linspace(0.0, t_end, NT)
    traj = run(stairs, params_of([ball]), t_end, path, ts)
    ev = events(stairs, traj, 0)
    first = next(x for x in ev if x[5] == "settle")
    assert first[4] == ("step3", "+z")
    assert first[0] == pytest.approx(t_acc, abs=TOL[path])
    np.testing.assert_allclose(first[1][:2], [0.95, 0.5 * t_acc], rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(traj.position[0])[:, :2],
                               np.stack([np.full(NT, 0.95), 0.5 * ts], 1), rtol=0, atol=1e-9)


def test_a_ball_that_rolls_off_an_edge_from_rest_has_finite_reverse_mode_derivatives(stairs):
    """A ball (r 0.2257) dropped at rest onto step3's corner bounces into a Zeno series on
    step4's edge, settles on it a little past its top, rolls off from rest (no horizontal
    velocity) and comes to rest on the ground. Reverse mode gives forward mode's
    derivatives of the final x, finite (regression: NaN in every reverse-mode derivative of
    the ball, from the square root of its zero horizontal speed in ``roll_axis``, on the
    kernels and the JAX path alike; forward mode was finite). (The closed-form path: the
    module's compiled derivative programs.)"""
    ball = Ball(0.18388939650969116, 0.039686418459000006, (1.6426989679356205, 0.6326762076381514, 2.1790086128506316),
                (0.0, 0.0, 0.0), r=0.225651796360997865)
    solution = run(stairs, params_of([ball]), 2.0, "closed_form").solution
    kind = np.asarray(solution.structure.kind[0])
    rolls = np.flatnonzero(kind == ROLL)
    assert rolls.size == 1 and np.all(np.asarray(solution.segments.v0[0])[rolls[0], :2] == 0.0)  # from rest
    _, (jfin, _, _) = jacobian(stairs, params_of([ball]), 2.0, "closed_form")
    grad = reverse_gradient(stairs, params_of([ball]), 2.0, "closed_form")
    assert np.all(np.isfinite(jfin)) and np.all(np.isfinite(grad))
    np.testing.assert_allclose(grad, jfin[0, 0], rtol=1e-9, atol=1e-12)


# ---------------------------------------------------------------------------------------
# Grazing
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("offset", [-1e-6, 0.0, 1e-6])
@pytest.mark.parametrize("path", PATHS)
def test_grazing_apex_touches_a_tread_top(stairs, path, offset):
    """Thrown up the stairs (vx0 = -1, e = 0.5, mu_t = 0.9) so that the apex of its flight is
    the edge point of step1's top, (0.3, 1.40 + r + offset): the only place where a rising
    ball can touch a tread top at its apex (anywhere else over the tread it would have met
    the riser or bevel first).

    offset <= 0: the ball meets the round edge just before its apex, where the parabola
    enters the fillet's circle about the edge point (0.3, 1.40) (a tangent touch of the top
    is not a contact), is reset about the normal from the edge point to its centre, lands
    on step1 and comes to rest. offset = +1e-6: it passes 1 um above the edge, lands on the
    top sqrt(2 offset / g) later with a normal speed of 4.4 mm/s and comes to rest 1.2 mm
    from the edge. Near the jump (offset = -1e-6, +1e-6) d/d(e, mu_t, vx0) equals central
    differences (h = 1e-6 in vx0 moves the apex by 0.15 um along x, which keeps each case on
    its side); at it (offset = 0) the derivative is the one-sided one of the edge contact,
    finite. At offset = 0 the apex touches the fillet's top, where it meets the top: a
    double root, where rounding decides whether the ball touches top or fillet (and the
    reference and estim part ways by one tangential factor mu_t); there the ball only has
    to stay outside every solid and rest on step1, with finite derivatives."""
    vx0, tau, e, mu = -1.0, 0.15, E_DEF, MU_DEF
    x0, z0 = 0.3 - vx0 * tau, 1.45 + offset - 0.5 * G * tau * tau
    ball = Ball(e, mu, (x0, 0.0, z0), (vx0, 0.0, G * tau))
    t_end = 1.0
    traj = run(stairs, params_of([ball]), t_end, path)
    ev = events(stairs, traj, 0)
    ref = Reference2D(e, mu, x0, z0, vx0, G * tau, t_end)
    if offset:
        assert_matches_reference(stairs, traj, 0, ref, TOL[path])
    assert_outside(stairs, traj, 1)
    t, p, pre, post, face, _ = ev[0]
    if offset == 0:
        assert face[0] == "step1" and t == pytest.approx(tau, abs=1e-6)
        assert ev[-1][4] == ("step1", "+z") and float(traj.final.position[0, 2]) == pytest.approx(1.45, abs=1e-12)
    elif offset < 0:
        assert face == ("step1", "+x+z")
        # The fillet is met dt before the apex, where dt^2 + (r - d - g dt^2 / 2)^2 = r^2
        # (d = -offset, |vx0| = 1): to first order dt = sqrt(2 r d / (1 - g r)).
        assert t == pytest.approx(tau - math.sqrt(-2 * R * offset / (1 - G * R)), abs=1e-6)
        n = (p - np.array([0.3, 0.0, 1.4])) / R
        np.testing.assert_allclose(np.linalg.norm(p - np.array([0.3, p[1], 1.4])), R, rtol=0, atol=1e-12)
        np.testing.assert_allclose(post, reset(pre, n, e, mu), rtol=0, atol=1e-12)
    else:
        fall = math.sqrt(2 * offset / G)
        w = G * fall
        assert face == ("step1", "+z") and t == pytest.approx(tau + fall, abs=TOL[path])
        np.testing.assert_allclose(pre, [vx0, 0.0, -w], rtol=0, atol=1e-9)
        T0 = 2 * e * w / G
        x_rest = 0.3 + vx0 * (fall + mu * T0 / (1 - e * mu))
        assert x_rest == pytest.approx(0.3 - 1.19e-3, abs=1e-5)
        np.testing.assert_allclose(np.asarray(traj.final.position[0]), [x_rest, 0.0, 1.45],
                                   rtol=0, atol=TOL[path])
    (_, evt, _), (jfin, jevt, jsmp) = jacobian(stairs, params_of([ball]), t_end, path)
    assert np.all(np.isfinite(jfin)) and np.all(np.isfinite(jevt)) and np.all(np.isfinite(jsmp))
    if offset != 0.0:
        fd_fin, fd_evt, _ = central_differences(stairs, [ball], t_end, path)
        assert_jacobian(jfin[0], fd_fin[0], 1e-5, 1e-6)  # smooth here: FD error ~1e-8
        listed = np.isfinite(evt[0])
        assert_jacobian(jevt[0][listed], fd_evt[0][listed], 1e-5, 1e-6)


CORNER_SPEEDS = [0.0, 0.5, 3.0, -0.5, -2.0]
# A series of vertical bounces exactly at an edge point is ill-conditioned bounce by bounce:
# once the rebounds are tiny, rounding alone decides whether the reference meets the top or
# the bevel first. There the closed forms are the truth (estim sums the series on the top).


@pytest.mark.parametrize("vx0", CORNER_SPEEDS)
@pytest.mark.parametrize("path", PATHS)
def test_grazing_centre_passes_exactly_over_a_tread_edge(stairs, path, vx0):
    """The centre passes exactly through step1's edge point (0.3, 1.45) at t = 0.2 s, falling
    at 1.962 m/s, moving sideways at vx0. Both the top and the edge bevel are reached at that
    instant; estim lands the ball on the top (box faces win ties), as documented. Then by
    hand: vx0 = 0 bounces in place and rests on the edge; vx0 = 0.5 (steep) and 3.0
    (shallow) fly on beyond the edge and land on step2 and step3; vx0 = -0.5 and -2.0 fly
    back over the tread and land on it 2 e 1.962 / g later. (Regression: with vx0 = -2 the
    rebound from the edge point, up and away from the tread, also 'entered' the bevel at
    tau = 0 and bounced off it a second time.) The derivatives are those of landing on the
    top: finite, one-sided (a ball 1 nm further out meets the bevel)."""
    e, mu, tau = E_DEF, MU_DEF, 0.2
    w = G * tau
    ball = Ball(e, mu, (0.3 - vx0 * tau, 0.0, 1.45 + 0.5 * G * tau * tau), (vx0, 0.0, 0.0))
    t_end = 1.0
    traj = run(stairs, params_of([ball]), t_end, path)
    ev = events(stairs, traj, 0)
    t, p, pre, post, face, kind = ev[0]
    assert face == ("step1", "+z") and kind == "impact"
    assert t == pytest.approx(tau, abs=1e-12)
    np.testing.assert_allclose(p, [0.3, 0.0, 1.45], rtol=0, atol=1e-12)
    np.testing.assert_allclose(pre, [vx0, 0.0, -w], rtol=0, atol=1e-12)
    np.testing.assert_allclose(post, [mu * vx0, 0.0, e * w], rtol=0, atol=1e-12)
    u, up = mu * vx0, e * w
    if vx0 == 0.0:
        T0 = 2 * up / G  # the flights after the first bounce: T0, e T0, e^2 T0, ...
        assert ev[-1][5] == "settle"
        assert ev[-1][0] == pytest.approx(tau + T0 / (1 - e), abs=TOL[path])
        np.testing.assert_allclose(np.asarray(traj.final.position[0]), [0.3, 0.0, 1.45],
                                   rtol=0, atol=1e-12)
    else:
        drop_to, step = {0.5: (0.2, "step2"), 3.0: (0.4, "step3")}.get(vx0, (0.0, "step1"))
        t2 = landing_time(drop_to, up)
        assert ev[1][4] == (step, "+z")
        assert ev[1][0] == pytest.approx(tau + t2, abs=TOL[path])
        np.testing.assert_allclose(ev[1][1], [0.3 + u * t2, 0.0, 1.45 - drop_to], rtol=0,
                                   atol=TOL[path])
    if vx0 != 0.0:  # (see the note above CORNER_SPEEDS)
        ref = Reference2D(e, mu, *np.asarray(ball.pos)[[0, 2]], vx0, 0.0, t_end)
        assert_matches_reference(stairs, traj, 0, ref, TOL[path])
    assert_outside(stairs, traj, 1)
    _, (jfin, jevt, jsmp) = jacobian(stairs, params_of([ball]), t_end, path)
    assert np.all(np.isfinite(jfin)) and np.all(np.isfinite(jevt)) and np.all(np.isfinite(jsmp))


RELEASES_AT_THE_EDGE = {
    "at rest": (0.0, 0.0, 0.0),
    "sliding off": (1.0, 0.0, 0.0),
    "sliding onto the tread": (-1.0, 0.0, 0.0),
    "thrown up": (0.0, 0.0, 1.0),
}


@pytest.mark.parametrize("how", list(RELEASES_AT_THE_EDGE))
@pytest.mark.parametrize("path", PATHS)
def test_release_exactly_at_an_edge(stairs, path, how):
    """Released with its centre exactly at step1's edge point (0.3, 1.45), touching the top
    and the edge bevel at once. at rest: stays (a settle event at t = 0, balanced on the
    edge). sliding off (vx0 = 1): leaves at once, clears the bevel (2 vx0^2 / g > r) and
    lands on step2 after a 0.2 m fall. sliding onto the tread (vx0 = -1): slides across
    step1 without friction, leaves its far edge at t = 0.6 s (faster than sqrt(g r): it flies
    off the round edge), lands on the ground.
    (Regression: the slide 'entered' the bevel at tau = 0 and bounced off it.) thrown up
    (vz0 = 1): comes back to the edge point 2 / g later, lands on the top, bounces in place
    (Zeno) and rests on the edge."""
    v = RELEASES_AT_THE_EDGE[how]
    e, mu, t_end = E_DEF, MU_DEF, 2.0
    ball = Ball(e, mu, (0.3, 0.0, 1.45), v)
    traj = run(stairs, params_of([ball]), t_end, path)
    ev = events(stairs, traj, 0)
    fin = np.asarray(traj.final.position[0])
    if how == "at rest":
        assert len(ev) == 1 and ev[0][0] == 0.0 and ev[0][4] == ("step1", "+z")
        assert ev[0][5] == "settle"
        np.testing.assert_allclose(fin, [0.3, 0.0, 1.45], rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(traj.position[0]), np.tile(fin, (NT, 1)), rtol=0,
                                   atol=1e-12)
    elif how == "sliding off":
        t2 = math.sqrt(0.4 / G)
        assert ev[0][:1] == (0.0,) and ev[0][5] == "settle"  # touches the top at t = 0
        assert ev[1][4] == ("step2", "+z") and ev[1][0] == pytest.approx(t2, abs=1e-12)
        np.testing.assert_allclose(ev[1][1], [0.3 + t2, 0.0, 1.25], rtol=0, atol=1e-12)
    elif how == "sliding onto the tread":
        t2 = 0.6 + math.sqrt(2 * 1.4 / G)
        assert [x[4] for x in ev[:2]] == [("step1", "+z"), ("ground", "plane")]
        assert ev[1][0] == pytest.approx(t2, abs=1e-12)
        np.testing.assert_allclose(ev[1][1], [0.3 - t2, 0.0, R], rtol=0, atol=1e-12)
    else:
        t1, T0 = 2.0 / G, 2.0 * e / G  # back at 1 m/s; rebound flights T0, e T0, ...
        assert ev[0][4] == ("step1", "+z") and ev[0][0] == pytest.approx(t1, abs=1e-12)
        assert ev[-1][5] == "settle"
        assert ev[-1][0] == pytest.approx(t1 + T0 / (1 - e), abs=TOL[path])
        np.testing.assert_allclose(fin, [0.3, 0.0, 1.45], rtol=0, atol=1e-12)
    if how != "thrown up":  # (see the note above CORNER_SPEEDS)
        ref = Reference2D(e, mu, 0.3, 1.45, v[0], v[2], t_end)
        assert_matches_reference(stairs, traj, 0, ref, TOL[path])
    assert_outside(stairs, traj, 1)
    _, (jfin, jevt, jsmp) = jacobian(stairs, params_of([ball]), t_end, path)
    assert np.all(np.isfinite(jfin)) and np.all(np.isfinite(jevt)) and np.all(np.isfinite(jsmp))


RESTING = {
    "on a tread": ((0.0, 0.0, 1.45), (0.0, 0.0, 0.0), E_DEF),
    "on the ground": ((3.5, 0.0, R), (0.0, 0.0, 0.0), E_DEF),
    "sliding on a tread": ((0.0, 0.0, 1.45), (1.0, 0.0, 0.0), E_DEF),
    "sliding slowly off a tread": ((0.0, 0.0, 1.45), (0.5, 0.0, 0.0), E_DEF),
    "against a riser": ((0.35, 0.0, 1.30), (0.0, 0.0, 0.0), E_DEF),
    "against a riser, e = 0.8": ((0.35, 0.0, 1.30), (0.0, 0.0, 0.0), 0.8),
}


@pytest.mark.parametrize("where", list(RESTING))
@pytest.mark.parametrize("path", PATHS)
def test_release_resting_on_a_surface(stairs, path, where):
    """Released touching a surface, with no normal velocity. On a tread or the ground at
    rest: stays exactly (one settle event at t = 0). Sliding on a tread at 1 m/s: slides
    without friction, leaves the edge at 0.3 s (faster than sqrt(g r), it flies off the
    round edge), lands on step2 0.2 m lower. Sliding at 0.5 m/s (slower than sqrt(g r)) it
    reaches the edge at 0.6 s, rolls over it and leaves it where cos theta = (v^2 / (g r) +
    2) / 3 (the reference integrates the roll). Against step1's
    riser (x = 0.3 + r, above step2): falls along the riser without an impact, lands on
    step2 at sqrt(2 * 0.05 / g), bounces in place against the riser and rests at
    t_fall (1 + e) / (1 - e), the series summed in closed form. (Regression: the riser,
    which the series only touches, counted as an obstacle in its way, so the series was
    followed bounce by bounce, one segment each: ~90 for e = 0.8, more than max_segments.)
    Derivatives finite; the sliding ball's final state equals central differences."""
    pos, vel, e = RESTING[where]
    mu, t_end = MU_DEF, 1.0
    ball = Ball(e, mu, pos, vel)
    if where == "sliding slowly off a tread":
        ref = Reference2D(e, mu, pos[0], pos[2], vel[0], vel[2], t_end)
        ev = assert_rolls_over_the_edge(stairs, params_of([ball]), t_end, path, ref, TOL[path])
        assert ev[1][4] == ("step1", "+x+z") and ev[1][0] == pytest.approx(0.6, abs=1e-12)
        return
    traj = run(stairs, params_of([ball]), t_end, path)
    ev = events(stairs, traj, 0)
    fin = np.asarray(traj.final.position[0])
    if vel == (0.0, 0.0, 0.0) and not where.startswith("against a riser"):
        assert len(ev) == 1 and ev[0][0] == 0.0 and ev[0][5] == "settle"
        np.testing.assert_allclose(fin, pos, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(np.asarray(traj.final.velocity[0]), [0.0, 0.0, 0.0])
    elif where == "sliding on a tread":
        t2 = 0.3 + math.sqrt(0.4 / G)
        assert ev[1][4] == ("step2", "+z") and ev[1][0] == pytest.approx(t2, abs=1e-12)
        np.testing.assert_allclose(ev[1][1], [t2, 0.0, 1.25], rtol=0, atol=1e-12)
    else:
        t1, _, _, t_acc = drop(0.05, e)
        assert ev[0][4] == ("step2", "+z") and ev[0][0] == pytest.approx(t1, abs=1e-12)
        np.testing.assert_allclose(ev[0][1], [0.35, 0.0, 1.25], rtol=0, atol=1e-12)
        # Summed: one settle event (bounce by bounce, e = 0.8 needed ~90 segments, more than
        # max_segments = 48, and run() would have found the ball incomplete).
        assert ev[-1][5] == "settle" and ev[-1][0] == pytest.approx(t_acc, abs=TOL[path])
        np.testing.assert_allclose(fin, [0.35, 0.0, 1.25], rtol=0, atol=1e-12)
    ref = Reference2D(e, mu, pos[0], pos[2], vel[0], vel[2], t_end)
    assert_matches_reference(stairs, traj, 0, ref, TOL[path])
    assert_outside(stairs, traj, 1)
    _, (jfin, jevt, jsmp) = jacobian(stairs, params_of([ball]), t_end, path)
    assert np.all(np.isfinite(jfin)) and np.all(np.isfinite(jevt)) and np.all(np.isfinite(jsmp))
    if where == "sliding on a tread":
        fd_fin, _, _ = central_differences(stairs, [ball], t_end, path)
        assert_jacobian(jfin[0], fd_fin[0], 1e-5, 1e-7)


# ---------------------------------------------------------------------------------------
# Extreme coefficients
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("where", ["on a tread", "into a riser"])
@pytest.mark.parametrize("path", PATHS)
def test_e_zero_sticks_at_first_contact(stairs, path, where):
    """e = 0 (mu_t = 0.7). On a tread: dropped 0.1 m at vx0 = 1 onto step1, it stops dead
    where it first touches, x0 + vx0 t_fall, and stays. Into a riser: thrown up the stairs
    at 2 m/s into step2's riser, it loses its normal velocity there, keeps mu_t vz, falls
    along the riser without touching it and sticks on step3 (hand-computed times).

    Derivatives: w.r.t. vx0 and mu_t those of sticking (closed form; central differences
    agree). w.r.t. e the trajectory is smooth only from the right (e >= 0). On a tread estim
    returns the derivative of sticking, 0, not the right derivative 2 mu u w / g of the
    bounce series that any e > 0 starts (documented; finite). At the riser, which does not
    support the ball, the rebound -e vx is kept and d/de is the right derivative."""
    e, mu = 0.0, 0.7
    if where == "on a tread":
        x0, h, vx0 = -0.25, 0.1, 1.0
        ball = Ball(e, mu, (x0, 0.0, 1.45 + h), (vx0, 0.0, 0.0))
        t_fall, w, _, _ = drop(h, 0.0)
        stick = [x0 + vx0 * t_fall, 0.0, 1.45]
        times = [t_fall]
    else:
        vx0 = -2.0
        ball = Ball(e, mu, (1.2, 0.0, 1.15), (vx0, 0.0, 0.0))
        t1 = (0.9 + R - 1.2) / vx0  # reaches x = 0.9 + r
        z1, vz1 = 1.15 - 0.5 * G * t1 * t1, -G * t1
        t2 = landing_time(z1 - 1.05, mu * vz1)
        stick = [0.9 + R, 0.0, 1.05]
        times = [t1, t1 + t2]
    t_end = 1.0
    traj = run(stairs, params_of([ball]), t_end, path)
    ev = events(stairs, traj, 0)
    assert len(ev) == len(times)
    np.testing.assert_allclose([x[0] for x in ev], times, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ev[-1][1], stick, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(ev[-1][3], [0.0, 0.0, 0.0])  # no rebound at all
    if where == "into a riser":
        assert ev[0][4] == ("step2", "+x") and ev[1][4] == ("step3", "+z")
        np.testing.assert_allclose(ev[0][3], [0.0, 0.0, mu * vz1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(traj.final.position[0]), stick, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(traj.final.velocity[0]), [0.0, 0.0, 0.0])
    (_, _, _), (jfin, jevt, _) = jacobian(stairs, params_of([ball]), t_end, path)
    if where == "on a tread":
        assert_jacobian(jfin[0, 0], [0.0, 0.0, t_fall], DTOL[path], 1e-12)
        fd_fin, _, _ = central_differences(stairs, [ball], t_end, path)
        assert_jacobian(jfin[0], fd_fin[0], 1e-6, 1e-8)
        # The right derivative w.r.t. e is not what estim returns (documented):
        right = 2 * mu * vx0 * w / G
        plus = run(stairs, params_of([ball._replace(e=1e-7)]), t_end, path)
        assert float(plus.final.position[0, 0] - stick[0]) / 1e-7 == pytest.approx(right,
                                                                                  rel=1e-5)
    else:
        # The riser does not support the ball: e scales the rebound -e vx0 there, which moves
        # the sticking point by -vx0 t2 per unit e (the right derivative, exact here).
        assert_jacobian(jfin[0, 0], [-vx0 * t2, 0.0, 0.0], DTOL[path], 1e-12)
        assert_jacobian(jfin[0, 1:], np.zeros((2, 3)), 0, 1e-12)
        assert_jacobian(jevt[0, 0], [0.0, 0.0, -t1 / vx0], DTOL[path], 1e-12)
    assert np.all(np.isfinite(jevt))


@pytest.mark.parametrize("how", ["1000 bounces", "11 million bounces"])
@pytest.mark.parametrize("path", PATHS)
def test_e_one_conserves_energy_over_1000_bounces(stairs, path, how):
    """e = 1 on the middle of step1, vx0 = 0: the ball bounces forever with period T (one
    closed-form segment). 1000 bounces: dropped 1 mm, T = 28.6 ms, t_end = 28.585 s.
    11 million bounces: released on the tread moving up at 1 um/s, T = 0.2 us, t_end = 2.3 s.
    The energy g z + |v|^2 / 2 at 64 samples (at bounces and apexes spread over all of them)
    and at the end stays equal to its initial value to 1e-12 (relative); the ball never
    goes below the tread (regression: with more than 10^6 bounces before a sample, the
    series was evaluated at bounce 10^6 and the ball fell through the tread and the
    ground); the listed bounces are at t1 + k T. Derivative of bounce k's time w.r.t. e at
    e = 1 (one-sided, e <= 1): (2 w / g) (1 + 2 + ... + (k - 1)) = (2 w / g) k (k - 1) / 2."""
    mu = 0.7
    if how == "1000 bounces":
        h = 1e-3
        ball = Ball(1.0, mu, (0.0, 0.0, 1.45 + h), (0.0, 0.0, 0.0))
        t1 = math.sqrt(2 * h / G)
        w = G * t1
        t_end = t1 + 1000.5 * (2 * t1)
    else:
        w = 1e-6
        ball = Ball(1.0, mu, (0.0, 0.0, 1.45), (0.0, 0.0, w))
        t1, h, t_end = 2 * w / G, w * w / (2 * G), 2.3
    T = 2 * w / G
    n_bounces = int((t_end - t1) / T) + 1
    assert n_bounces == 1001 if how == "1000 bounces" else n_bounces > 11_000_000
    ks = np.unique(np.linspace(1, n_bounces - 1, NT // 2).round()).astype(int)
    t_bounce = t1 + (ks - 1) * T
    ts = np.sort(np.concatenate([t_bounce, t_bounce + T / 2]))[:NT]
    traj = run(stairs, params_of([ball]), t_end, path, ts)
    e0 = G * (1.45 + h)
    p, v = np.asarray(traj.position[0]), np.asarray(traj.velocity[0])
    np.testing.assert_allclose(energy(p, v), e0, rtol=1e-12, atol=0)
    np.testing.assert_allclose(energy(traj.final.position[0], traj.final.velocity[0]), e0,
                               rtol=1e-12, atol=0)
    np.testing.assert_allclose(p[1::2, 2], 1.45 + h, rtol=0, atol=1e-12)  # every apex
    np.testing.assert_allclose(p[0::2, 2], 1.45, rtol=0, atol=1e-12)  # every bounce
    np.testing.assert_allclose(p[:, :2], np.zeros((NT, 2)), rtol=0, atol=1e-12)
    s = (t_end - t1) % T
    z_end = 1.45 + w * s - 0.5 * G * s * s
    assert float(traj.final.position[0, 2]) == pytest.approx(z_end, abs=1e-12)
    ev = traj.events
    n = int(ev.count[0])
    assert n == 64 and bool(ev.truncated[0])  # more bounces than the list holds
    np.testing.assert_allclose(np.asarray(ev.t[0]), t1 + np.arange(n) * T, rtol=0,
                               atol=1e-12 * max(t_end, 1.0))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(ev.velocity_post[0]), axis=1), w,
                               rtol=1e-9, atol=0)
    (_, evt, _), (jfin, jevt, jsmp) = jacobian(stairs, params_of([ball]), t_end, path, ts)
    # Reverse mode equals forward mode (regression: NaN at e = 1 on both paths, from the
    # discarded branch of a series that never ends, duration T0 * inf).
    np.testing.assert_allclose(reverse_gradient(stairs, params_of([ball]), t_end, path, ts),
                               jfin[0, 0], rtol=1e-9, atol=1e-12)
    k = np.arange(1, n + 1)
    np.testing.assert_allclose(jevt[0, :, 0], 2 * w / G * k * (k - 1) / 2, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(jevt[0, :, 1:], 0.0, atol=1e-12)
    assert np.all(np.isfinite(jsmp))


@pytest.mark.parametrize("where", ["on a tread", "into a riser"])
@pytest.mark.parametrize("path", PATHS)
def test_mu_t_zero_removes_the_tangential_velocity(stairs, path, where):
    """mu_t = 0 (e = 0.6). On a tread: dropped 0.3 m at vx0 = 0.5 onto step2, the first
    impact stops its horizontal motion; it bounces in place (Zeno) where it landed and rests
    at t_fall (1 + e) / (1 - e). Into a riser: thrown at step2's riser at -2 m/s, it leaves
    it horizontally at e 2 m/s (vz = 0 after the impact) and lands on step3 after falling
    from the impact height. Derivatives: closed forms; w.r.t. mu_t at mu_t = 0 (one-sided,
    mu_t >= 0) estim's equals the right derivative, u T0 / (1 - 0) on the tread."""
    e, mu = 0.6, 0.0
    if where == "on a tread":
        x0, h, vx0 = 0.45, 0.3, 0.5
        ball = Ball(e, mu, (x0, 0.0, 1.25 + h), (vx0, 0.0, 0.0))
        t_fall, w, T0, t_acc = drop(h, e)
        rest = [x0 + vx0 * t_fall, 0.0, 1.25]
    else:
        vx0 = -2.0
        ball = Ball(e, mu, (1.2, 0.0, 1.15), (vx0, 0.0, 0.0))
        t1 = (0.9 + R - 1.2) / vx0
        z1 = 1.15 - 0.5 * G * t1 * t1
        t2 = math.sqrt(2 * (z1 - 1.05) / G)
    t_end = 2.0
    traj = run(stairs, params_of([ball]), t_end, path)
    ev = events(stairs, traj, 0)
    if where == "on a tread":
        assert all(x[4] == ("step2", "+z") for x in ev) and ev[-1][5] == "settle"
        for x in ev:
            np.testing.assert_allclose(x[1], rest, rtol=0, atol=1e-12)
        assert ev[-1][0] == pytest.approx(t_acc, abs=TOL[path])
        np.testing.assert_allclose(np.asarray(traj.final.position[0]), rest, rtol=0,
                                   atol=1e-12)
    else:
        assert ev[0][4] == ("step2", "+x") and ev[0][0] == pytest.approx(t1, abs=1e-12)
        np.testing.assert_allclose(ev[0][3], [-e * vx0, 0.0, 0.0], rtol=0, atol=1e-12)
        assert ev[1][4] == ("step3", "+z") and ev[1][0] == pytest.approx(t1 + t2, abs=1e-12)
        np.testing.assert_allclose(ev[1][1], [0.9 + R - e * vx0 * t2, 0.0, 1.05], rtol=0,
                                   atol=1e-12)
    ref = Reference2D(e, mu, ball.pos[0], ball.pos[2], vx0, 0.0, t_end)
    assert_matches_reference(stairs, traj, 0, ref, TOL[path])
    (_, _, _), (jfin, _, _) = jacobian(stairs, params_of([ball]), t_end, path)
    if where == "on a tread":
        assert_jacobian(jfin[0, 0], [0.0, vx0 * T0, t_fall], DTOL[path], 1e-12)
    fd_fin, _, _ = central_differences(stairs, [ball], t_end, path)  # mu_t: NaN, one-sided
    assert_jacobian(jfin[0], fd_fin[0], 1e-5, 1e-7)


# ---------------------------------------------------------------------------------------
# Fast balls, risers
# ---------------------------------------------------------------------------------------

FAST = {
    # (release, velocity): skimming step1, straight down onto step3, into step2's riser
    "skims a tread": ((-0.25, 0.0, 1.50), (50.0, 0.0, -5.0)),
    "straight down": ((1.2, 0.0, 2.0), (0.0, 0.0, -50.0)),
    "into a riser": ((1.2, 0.0, 1.15), (-50.0, 0.0, 0.0)),
}


@pytest.mark.parametrize("how", list(FAST))
@pytest.mark.parametrize("path", PATHS)
def test_very_fast_ball_does_not_tunnel(stairs, path, how):
    """50 m/s (e = 0.8, mu_t = 0.95). Skimming: released 5 cm above step1 at (50, -5) m/s, it
    crosses the 0.6 m tread in 12 ms and meets it 10 ms after release at x = 0.245 (a
    fixed-step integrator at 1 kHz would move 5 cm per step); it rebounds and lands on the
    ground 52 m away. Straight down at 50 m/s onto step3: lands at the hand-computed time
    and flies back up at e times the impact speed. Into step2's riser at -50 m/s: meets it
    after 5 ms, vx -> -e vx, and lands on the ground beyond the stairs. Derivatives of the
    event times: closed forms."""
    e, mu = 0.8, 0.95
    pos, vel = FAST[how]
    ball = Ball(e, mu, pos, vel)
    t_end = 1.5
    traj = run(stairs, params_of([ball]), t_end, path)
    ev = events(stairs, traj, 0)
    if how == "skims a tread":
        t1 = landing_time(pos[2] - 1.45, vel[2])
        vz1 = vel[2] - G * t1
        face1, p1 = ("step1", "+z"), [pos[0] + vel[0] * t1, 0.0, 1.45]
        assert -0.3 < p1[0] < 0.3 and t1 < 0.6 / 50
        post = [mu * vel[0], 0.0, -e * vz1]
        t2 = t1 + landing_time(1.45 - R, post[2])
        p2 = [p1[0] + post[0] * (t2 - t1), 0.0, R]
    elif how == "straight down":
        t1 = landing_time(pos[2] - 1.05, vel[2])
        vz1 = vel[2] - G * t1
        face1, p1 = ("step3", "+z"), [1.2, 0.0, 1.05]
        post = [0.0, 0.0, -e * vz1]
        t2 = None  # still flying up at t_end
    else:
        t1 = (0.9 + R - pos[0]) / vel[0]
        vz1 = -G * t1
        face1, p1 = ("step2", "+x"), [0.9 + R, 0.0, pos[2] - 0.5 * G * t1 * t1]
        post = [-e * vel[0], 0.0, mu * vz1]
        t2 = t1 + landing_time(p1[2] - R, post[2])
        p2 = [p1[0] + post[0] * (t2 - t1), 0.0, R]
    assert ev[0][4] == face1
    assert ev[0][0] == pytest.approx(t1, abs=1e-12)
    np.testing.assert_allclose(ev[0][1], p1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ev[0][3], post, rtol=0, atol=1e-12)
    if t2 is None:
        assert len(ev) == 1
        tau = t_end - t1
        np.testing.assert_allclose(np.asarray(traj.final.position[0]),
                                   [1.2, 0.0, 1.05 + post[2] * tau - 0.5 * G * tau * tau],
                                   rtol=0, atol=1e-9)
    else:
        assert ev[1][4] == ("ground", "plane") and p2[0] > 2.7 + R
        assert ev[1][0] == pytest.approx(t2, abs=1e-12)
        np.testing.assert_allclose(ev[1][1], p2, rtol=0, atol=1e-9)
    assert_outside(stairs, traj, 1)
    (_, _, _), (jfin, jevt, _) = jacobian(stairs, params_of([ball]), t_end, path)
    if how == "skims a tread":  # t1 does not depend on vx0; d t2 / d e through post vz
        s = math.sqrt(post[2] ** 2 + 2 * G * (1.45 - R))
        assert_jacobian(jevt[0, 0], [0.0, 0.0, 0.0], 0, 1e-12)
        assert_jacobian(jevt[0, 1], [(1 + post[2] / s) / G * -vz1, 0.0, 0.0], DTOL[path], 1e-12)
    elif how == "into a riser":  # t1 = (0.9 + r - x0) / vx0
        assert_jacobian(jevt[0, 0], [0.0, 0.0, -t1 / vel[0]], DTOL[path], 1e-12)
    fd_fin, fd_evt, _ = central_differences(stairs, [ball], t_end, path)
    assert_jacobian(jfin[0], fd_fin[0], 1e-5, 1e-6)


@pytest.mark.parametrize("path", PATHS)
def test_thrown_up_the_stairs_into_a_riser(stairs, path):
    """Released above step3 at (-2, 0, 0.5) m/s (e = 0.7, mu_t = 0.9): meets the riser of step2
    (x = 0.9 + r) at t1 = 0.25 / 2 on its way down, vx -> -e vx and vz -> mu_t vz, and lands
    on step3 (hand-computed). Gradient of t1 w.r.t. vx0: closed form; the rest: central
    differences."""
    e, mu, vx0, vz0 = 0.7, MU_DEF, -2.0, 0.5
    ball = Ball(e, mu, (1.2, 0.0, 1.15), (vx0, 0.0, vz0))
    t1 = (0.9 + R - 1.2) / vx0
    z1 = 1.15 + vz0 * t1 - 0.5 * G * t1 * t1
    pre = [vx0, 0.0, vz0 - G * t1]
    post = [-e * vx0, 0.0, mu * pre[2]]
    assert 1.05 < z1 < 1.20  # on the riser, between the two treads
    t2 = landing_time(z1 - 1.05, post[2])
    t_end = 1.0
    traj = run(stairs, params_of([ball]), t_end, path)
    ev = events(stairs, traj, 0)
    assert [x[4] for x in ev[:2]] == [("step2", "+x"), ("step3", "+z")]
    np.testing.assert_allclose([ev[0][0], ev[1][0]], [t1, t1 + t2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(ev[0][1], [0.9 + R, 0.0, z1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(ev[0][2], pre, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ev[0][3], post, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ev[1][1], [0.9 + R + post[0] * t2, 0.0, 1.05], rtol=0,
                               atol=1e-12)
    ref = Reference2D(e, mu, 1.2, 1.15, vx0, vz0, t_end)
    assert_matches_reference(stairs, traj, 0, ref, TOL[path])
    assert_outside(stairs, traj, 1)
    (_, evt, _), (jfin, jevt, _) = jacobian(stairs, params_of([ball]), t_end, path)
    assert_jacobian(jevt[0, 0], [0.0, 0.0, -t1 / vx0], DTOL[path], 1e-12)
    fd_fin, fd_evt, _ = central_differences(stairs, [ball], t_end, path)
    assert_jacobian(jfin[0], fd_fin[0], 1e-5, 1e-7)
    listed = np.isfinite(evt[0])
    assert_jacobian(jevt[0][listed], fd_evt[0][listed], 1e-5, 1e-7)


# ---------------------------------------------------------------------------------------
# Many balls at once
# ---------------------------------------------------------------------------------------


def mixed_balls():
    """One ball of every case above (and a few with sideways motion), for one batch."""
    balls = [
        Ball(0.6, 0.8, (0.45, 0.0, 1.55), (0.2, 0.0, 0.0)),  # Zeno on a flat tread
        Ball(0.7, MU_DEF, (1.2, 0.0, 1.45), (0.0, 0.0, 0.0)),  # pure vertical Zeno
        Ball(0.3, 1.0, (-0.25, 0.0, 1.50), (0.8, 0.0, 0.0)),  # mu_t = 1: slides, flies off
        Ball(1.0, 0.7, (0.0, 0.0, 1.451), (0.0, 0.0, 0.0)),  # e = 1
        Ball(0.0, 0.7, (-0.25, 0.0, 1.55), (1.0, 0.0, 0.0)),  # e = 0
        Ball(0.6, 0.0, (0.45, 0.0, 1.55), (0.5, 0.0, 0.0)),  # mu_t = 0
        Ball(0.7, MU_DEF, (1.2, 0.0, 1.15), (-2.0, 0.0, 0.5)),  # into a riser
        Ball(0.518, 0.966, (-0.2, 0.0, 1.70), (0.801, 0.0, 0.0)),  # the Zeno ball
        Ball(0.5, 0.9, (-0.2, 0.55, 1.7), (0.6, 0.4, 0.0)),  # off the side of the stairs
        Ball(0.8, 0.95, (2.0, -0.3, 1.2), (-1.5, 0.2, 2.0)),  # up the stairs, sideways
    ]
    for offset in (-1e-6, 0.0, 1e-6):  # grazing apex
        balls.append(Ball(E_DEF, MU_DEF, (0.45, 0.0, 1.45 + offset - 0.5 * G * 0.0225),
                          (-1.0, 0.0, G * 0.15)))
    for vx0 in CORNER_SPEEDS:  # centre exactly over an edge
        balls.append(Ball(E_DEF, MU_DEF, (0.3 - vx0 * 0.2, 0.0, 1.45 + 0.5 * G * 0.04),
                          (vx0, 0.0, 0.0)))
    balls += [Ball(E_DEF, MU_DEF, (0.3, 0.0, 1.45), v) for v in RELEASES_AT_THE_EDGE.values()]
    balls += [Ball(e, MU_DEF, p, v) for p, v, e in RESTING.values()]
    balls += [Ball(0.8, 0.95, p, v) for p, v in FAST.values()]
    return balls


@pytest.mark.parametrize("path", PATHS)
def test_many_balls_in_one_batch_with_mixed_behaviour(stairs, path):
    """All the cases above in one batch over 2.3 s (Zeno series, slides, rest, grazing,
    e = 0 and 1, mu_t = 0 and 1, 50 m/s, rolls over edges): every ball completes, stays
    outside every solid, never gains energy, and gives the arrays it gives when simulated
    alone (to BATCH_TOL: faces and counts bit for bit, times and states to rounding,
    conftest.BATCH_ROUNDING)."""
    balls = mixed_balls()
    k = len(balls)
    t_end = 2.3
    ts = np.linspace(0.0, t_end, NT)
    padded, _ = padded_params(*(np.array(x, dtype=np.float64) for x in zip(*[(b.e, b.mu, b.r, b.pos, b.vel) for b in balls], strict=True)))
    traj = simulate(stairs, padded, t_end, path, ts=padded_ts(ts), throw=False)
    done = np.asarray(traj.complete[:k])
    assert done.all(), np.flatnonzero(~done)
    ok = np.flatnonzero(done)
    final = np.asarray(traj.final.position)[ok][:, None, :]
    for pts in (np.asarray(traj.position)[ok], final):
        assert np.all(np.min(box_distance(pts, stairs.box_centre, stairs.box_half), axis=-1) >= R - 1e-9)
        assert np.all(pts[..., 2] >= R - 1e-9)
    e0 = np.array([energy(b.pos, b.vel) for b in balls])[ok]
    smp = energy(np.asarray(traj.position)[ok], np.asarray(traj.velocity)[ok])
    assert np.all(np.diff(smp, axis=1) <= 1e-9) and np.all(smp[:, 0] <= e0 + 1e-12)
    for i, b in enumerate(balls):
        alone = simulate(stairs, estim.Params(b.e, b.mu, b.r, b.pos, b.vel), t_end,
                         path, ts=padded_ts(ts), throw=False)
        assert bool(alone.complete) == done[i]
        if not done[i]:
            continue
        for a, x in (
            (alone.position, traj.position[i]),
            (alone.velocity, traj.velocity[i]),
            (alone.final.position, traj.final.position[i]),
            (alone.final.velocity, traj.final.velocity[i]),
            (alone.events.t, traj.events.t[i]),
            (alone.events.position, traj.events.position[i]),
            (alone.events.velocity_post, traj.events.velocity_post[i]),
            (alone.events.face, traj.events.face[i]),
            (alone.events.count, traj.events.count[i]),
        ):
            np.testing.assert_allclose(np.asarray(a), np.asarray(x), rtol=BATCH_RTOL[path],
                                       atol=BATCH_TOL[path], err_msg=f"ball {i}")


@pytest.mark.parametrize("path", PATHS)
def test_ball_wedged_between_an_edge_and_a_riser(stairs, path):
    """A scene built like the stairs (five boxes on the ground, so the same compiled
    program) with a 12.5 cm gap between step2 (x up to 2.3125, top 0.5) and step3 (x from
    2.4375, top 1.0), g = 1 m/s^2 (found by the random-scene property test). A bocce ball
    (r = 0.08, wider than the gap) slides off step2 (e = 0.5, mu_t = 1), bounces off step3's
    riser onto step2's round edge and back: it may be wedged, with infinitely many bounces
    on two pieces. estim follows them one segment each: every contact lies outside both
    solids, and either the ball gets out and stays outside, or it is reported incomplete
    (simulate raises, naming max_segments) instead of returning a wrong answer.
    (Regression: the bounces on an edge bevel were summed as one closed-form series without
    looking for obstacles, and the series went 3 mm into step3's riser.)"""
    boxes = {f"step{k + 1}": ((0.0, 0.0, 0.5), (0.5, 1.0, 0.5)) for k in range(5)}
    boxes["step2"] = ((2.1875, 0.0, 0.25), (0.125, 1.0, 0.25))
    boxes["step3"] = ((2.8125, 0.0, 0.5), (0.375, 1.0, 0.5))
    scene = estim.Scene.from_arrays(boxes, {"ground": ((0.0, 0.0, 1.0), 0.0)}, gravity=1.0,
                                    balls=stairs.balls)
    ball = Ball(0.5, 1.0, (2.0, 0.0, 0.59), (0.5, 0.0, 0.0), r=0.08)
    p = params_of([ball])
    padded, _ = padded_params(p.e, p.mu_t, p.radius, p.position, p.velocity)
    ts = padded_ts(np.linspace(0.0, 2.3, NT))
    traj = simulate(scene, padded, 2.3, path, ts=ts, throw=False)
    ev = events(scene, traj, 0)
    labels = [x[4] for x in ev]
    assert ("step3", "-x") in labels and ("step2", "+x+z") in labels
    # Every event up to where the solver stopped lies outside both solids.
    pts = np.array([x[1] for x in ev])
    depth = box_distance(pts, scene.box_centre, scene.box_half)
    assert np.all(depth >= 0.08 - 1e-9), float(np.min(depth - 0.08))
    if bool(traj.complete[0]):  # a path that resolves the wedge must keep the ball outside
        assert_outside(scene, traj, 1, r=0.08)
    else:
        with pytest.raises(RuntimeError, match="max_"):
            simulate(scene, padded, 2.3, path, ts=ts)


@pytest.mark.parametrize("path", PATHS)
def test_released_over_a_corner_moving_along_an_edge(stairs, path):
    """Released over step5's far edge (x = 2.7 exactly), moving along +y towards its corner,
    the bocce-sized ball (e = mu_t = 0.25) lands on the tread and bounces towards the
    +y edge and the corner. (With bevels it slid down the ridge of a bevel and a corner face
    and switched between them forever at one instant.) Its values stay finite; it either
    ends on the ground beside step5 (z = r, outside it) or stops on an edge or a corner,
    where it would roll over it, reported so."""
    p, _ = padded_params(0.25, 0.25, 0.08, (2.7, 0.0, 1.845), (0.0, 1.0, 0.5))
    traj = simulate(stairs, p, 2.3, path, ts=padded_ts(np.linspace(0.0, 2.3, NT)), throw=False)
    assert np.all(np.isfinite(np.asarray(traj.final.position[0])))
    assert np.all(np.isfinite(np.asarray(traj.position[0])))
    if bool(traj.complete[0]):  # on the ground, beside step5
        q = np.asarray(traj.final.position[0])
        assert q[2] == pytest.approx(0.08, abs=1e-9)
        assert np.min(box_distance(q, stairs.box_centre, stairs.box_half)) >= 0.08 - 1e-9
    else:
        last = int(traj.events.face[0, int(traj.events.count[0]) - 1])
        assert len(stairs.face_label(last)[1]) >= 4, stairs.face_label(last)


# ---------------------------------------------------------------------------------------
# Degenerate contacts (found by an adversarial audit, session 10, against edge bevels, and
# placed again for round edges). Each ball once passed through a solid with complete = True.
# With round edges all resolve: three of them reach an edge (or the corner at its end)
# slower than sqrt(g r), pressed onto it, and roll over it (estim.forward._roll).
# ---------------------------------------------------------------------------------------

DEGENERATE = {
    "apex_grazes_step1_top_1e-12_inside_its_edge":
        ((0.5, 0.9, 0.05, (0.4 - 1e-12, 0.0, 1.40095), (-1.0, 0.0, 0.981)), 0.5),
    "slides_off_step1_edge_from_1e-12_inside":
        ((0.5, 0.9, 0.05, (0.3 - 1e-12, 0.0, 1.45), (1e-9, 0.0, 0.0)), 3.0),
    "series_on_step5_y_edge_r_0.5":
        ((0.5, 0.9, 0.5, (2.55, 0.6, 1.1), (0.0, 0.001, 0.0)), 2.0),
    "dropped_touching_step5_vertical_edge_r_1/16":
        ((0.3, 0.0, 0.0625, (2.7 + 0.0625 / 2**0.5, 0.6 + 0.0625 / 2**0.5, 0.1125), (0.0, 0.0, 0.0)), 3.0),
    "slides_along_step1_edge_ridge_to_its_corner":
        ((0.5, 0.9, 0.05, (-0.3, 0.0, 1.45), (0.0, 0.5, 0.0)), 3.0),
}

ROLLS = ("slides_off_step1_edge_from_1e-12_inside", "series_on_step5_y_edge_r_0.5",
         "slides_along_step1_edge_ridge_to_its_corner")


def _degenerate(stairs, case, path="closed_form", **kwargs):
    args, t_end = DEGENERATE[case]
    ts = np.linspace(0.0, t_end, 601)
    return simulate(stairs, estim.Params(*args), t_end, path, ts=ts, **kwargs), args[2]


def _outside(stairs, traj, r) -> bool:
    q = np.asarray(traj.position)
    depth = np.min(box_distance(q, stairs.box_centre, stairs.box_half), axis=-1)
    return bool(np.all(depth >= r - 1e-9) and np.all(q[..., 2] >= r - 1e-9))


@pytest.mark.parametrize("case", DEGENERATE)
@pytest.mark.parametrize("path", PATHS)
def test_degenerate_contacts_are_resolved(stairs, case, path):
    """Each reaches t_end outside every solid, on both solver paths. Three roll over an
    edge (one of them on over the corner at its end): there the two paths agree on where
    the ball ends (to 1e-6 m, the ODE path's slack; the closed form's roll is exact). (The
    apex that grazes the edge lands on the tread with no normal speed in closed form, and
    with the ODE path's slack-sized 1e-7 m/s: an impact, whose bounces the law sums to a
    stop.)"""
    traj, r = _degenerate(stairs, case, path, throw=False)
    assert bool(np.asarray(traj.complete)) and _outside(stairs, traj, r)
    if path == "ode" and case in ROLLS:
        exact, _ = _degenerate(stairs, case)
        np.testing.assert_allclose(np.asarray(traj.final.position), np.asarray(exact.final.position), rtol=0, atol=1e-6)


def test_grazing_apex_at_a_tread_edge_is_a_contact(stairs):
    """Flights whose apex touches a tread top (to -1e-13 ... +1e-16 m of top + r) 1e-12 to
    1e-6 m inside its edge, towards the tread, at 1 and 10 m/s, at step1's two edges and
    step4's: faster than sqrt(g r), each passes over the round edge (its parabola is
    flatter than the fillet; an apex 1e-13 m low may touch it without normal speed) and
    lands on the top at its apex (to 2e-5 s: after a graze of the fillet, a micrometre hop).
    (With edge bevels, the ball once reached the bevel rising at ~1e-11 m/s, which read as
    leaving the top, and flew through the tread: 56 of these 192 balls.)"""
    r, g = 0.05, G
    pos, vel, apex = [], [], []
    for edge, side, top in ((0.3, -1.0, 1.4), (-0.3, 1.0, 1.4), (2.1, -1.0, 0.8)):
        for d in (1e-12, 1e-10, 1e-8, 1e-6):
            for dh in (-1e-13, -5e-14, 0.0, 1e-16):
                for speed in (1.0, 10.0):
                    for ta in (0.1, 0.05):
                        v = side * speed
                        pos.append((edge + side * d - v * ta, 0.0, top + r + dh - g * ta * ta / 2))
                        vel.append((v, 0.0, g * ta))
                        apex.append(ta)
    ts = np.linspace(0.0, 0.6, 601)
    traj = estim.simulate(stairs, estim.Params(0.5, 0.9, r, np.array(pos), np.array(vel)), 0.6, ts=ts)
    q = np.asarray(traj.position)
    depth = np.min(box_distance(q, stairs.box_centre, stairs.box_half), axis=-1)
    assert np.all(depth >= r - 1e-9), float(np.min(depth - r))
    assert np.all(q[..., 2] >= r - 1e-9)
    assert np.all(np.asarray(traj.complete))
    # The first landing on the top is at the apex; before it (apexes 1e-13 m below the
    # fillet's top) at most a graze of the fillet, near the apex (vertical speed below 1e-4 m/s;
    # the factor law still scales the tangential velocity by mu_t there).
    ev = traj.events
    for i in range(len(apex)):
        labels = [stairs.face_label(int(f))[1] for f in np.asarray(ev.face[i])[: int(ev.count[i])]]
        k = labels.index("+z")
        assert all(lab in ("+x+z", "-x+z") for lab in labels[:k]), labels
        pre = np.asarray(ev.velocity_pre[i, :k])
        assert np.all(np.abs(pre[:, 2]) <= 1e-4), (i, pre)
        assert float(ev.t[i, k]) == pytest.approx(apex[i], abs=2e-5)
