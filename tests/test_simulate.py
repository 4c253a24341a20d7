"""estim.simulate against independent truths: the seed numbers, a pure-numpy event-by-event
reference simulator of the seed model, closed forms (Zeno sums, periodic bouncing),
finite differences, and physical invariants (energy, non-penetration)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import (
    NT,
    ROOT,
    SEED_MU,
    SEED_T_END,
    SEED_VX,
    B,
    G,
    assert_complete,
    box_distance,
    evaluate,
    grad_final_x,
    jac_args,
    jac_outputs,
    run,
    seed_arrays,
    seed_release,
)

import estim

# ---------------------------------------------------------------------------------------
# An independent reference: the seed model, event by event, in plain numpy.
# Treads k = 0..4 cover x in [-0.3 + 0.6k, 0.3 + 0.6k] with tops 1.40 - 0.2k; beyond the
# last tread (x > 2.7) is the ground z = 0. The guard is z - r - floor(x), floor(x) the top
# of the tread under the centre; a contact resets vz -> -e vz, vx -> mu vx.
# ---------------------------------------------------------------------------------------

TOPS = [1.40 - 0.2 * k for k in range(5)] + [0.0]
LEFT = [-0.3 + 0.6 * k for k in range(5)] + [2.7]
RIGHT = [0.3 + 0.6 * k for k in range(5)] + [math.inf]


def _fall_time(a: float, b: float, g: float) -> float:
    """Smallest tau >= 0 with a + b tau - g tau^2 / 2 = 0 after which it is negative
    (a >= 0), free of cancellation."""
    s = math.sqrt(b * b + 2.0 * g * max(a, 0.0))
    return (b + s) / g if b >= 0 else 2.0 * max(a, 0.0) / (s - b)


class Reference:
    """Event-by-event flight of one ball down the seed stairs (vx >= 0, y ignored)."""

    def __init__(self, e, mu, r, x0, z0, vx0, vz0, t_end, g=G, max_bounces=60, min_flight=0.0):
        assert vx0 >= 0
        self.events = []  # (t, x, z, vx_pre, vz_pre, vx_post, vz_post, tread)
        self.edge_gap = math.inf  # closest approach (m) to a tread edge, minus r
        self.zeno = False  # more than max_bounces, or a flight shorter than min_flight
        t, x, z, vx, vz = 0.0, x0, z0, vx0, vz0
        k = next(i for i in range(6) if LEFT[i] <= x <= RIGHT[i])
        t_last = 0.0
        while True:
            tau_hit = _fall_time(z - r - TOPS[k], vz, g)
            tau_edge = (RIGHT[k] - x) / vx if vx > 0 else math.inf
            tau = min(tau_hit, tau_edge)
            if t + tau >= t_end:
                tau = t_end - t
                x, z, vz = x + vx * tau, z + vz * tau - 0.5 * g * tau * tau, vz - g * tau
                t = t_end
                break
            x_new = x + vx * tau
            z_new = z + vz * tau - 0.5 * g * tau * tau
            vz_new = vz - g * tau
            if tau_hit <= tau_edge:
                t, x, z = t + tau, x_new, TOPS[k] + r
                self.edge_gap = min(self.edge_gap, abs(x - LEFT[k]), abs(x - RIGHT[k]))
                if t - t_last < min_flight or len(self.events) >= max_bounces:
                    self.zeno = True
                    break
                t_last = t
                pre = (vx, vz_new)
                vx, vz = mu * vx, -e * vz_new
                self.events.append((t, x, z, *pre, vx, vz, k))
            else:
                # The centre passes over the edge (RIGHT[k], TOPS[k]); the grown tread is
                # at L1 distance (clearance + r) there and at (x - edge) once z = TOPS[k]:
                # the closest approach to the edge is the smaller (the L1 distance is
                # concave in time between those two instants, linear after).
                clearance = z_new - r - TOPS[k]
                tau_top = _fall_time(z_new - TOPS[k], vz_new, g)
                gap = min(clearance, vx * tau_top - r)
                self.edge_gap = min(self.edge_gap, abs(gap))
                t, x, z, vz = t + tau, RIGHT[k], z_new, vz_new
                k += 1
        self.final = (t, x, z, vx, vz)


def reference_rest(e, mu, r, x0, z0, vx0, vz0):
    """Follow a Zeno series bounce by bounce until a flight lasts < 1e-12 s."""
    ref = Reference(e, mu, r, x0, z0, vx0, vz0, t_end=100.0, max_bounces=100000, min_flight=1e-12)
    assert ref.zeno
    return ref


# ---------------------------------------------------------------------------------------
# Seed scene
# ---------------------------------------------------------------------------------------

SEED_IMPACTS = (9, 6, 4)
SEED_FINAL_X = (2.2427444662, 2.3048901184, 2.3278961376)
SEED_FINAL_Z = (0.7329133018, 0.6932422527, 1.0811260425)


@pytest.fixture(scope="module")
def seed_traj(stairs):
    traj = run(stairs, *seed_arrays(stairs), SEED_T_END)
    assert_complete(traj)
    return traj


def test_seed_numbers(stairs, seed_traj):
    ev = seed_traj.events
    kinds = np.asarray(ev.kind[:3])
    np.testing.assert_array_equal(np.asarray(ev.count[:3]), SEED_IMPACTS)
    np.testing.assert_array_equal(np.sum(kinds == 0, axis=1), SEED_IMPACTS)  # all impacts
    final = np.asarray(seed_traj.final.position[:3])
    np.testing.assert_allclose(final[:, 0], SEED_FINAL_X, rtol=0, atol=1e-9)
    np.testing.assert_allclose(final[:, 2], SEED_FINAL_Z, rtol=0, atol=1e-9)
    np.testing.assert_allclose(final[:, 1], [-0.3, 0.0, 0.3], rtol=0, atol=0)
    # Every seed impact is on a tread top.
    for i, n in enumerate(SEED_IMPACTS):
        labels = {stairs.face_label(int(f))[1] for f in np.asarray(ev.face[i, :n])}
        assert labels == {"+z"}


def test_seed_matches_numpy_reference(stairs, seed_traj):
    e, mu, r, pos, vel = seed_arrays(stairs)
    for i in range(3):
        ref = Reference(e[i], mu[i], r[i], pos[i, 0], pos[i, 2], vel[i, 0], 0.0, SEED_T_END)
        n = len(ref.events)
        assert n == SEED_IMPACTS[i]
        t_ref = np.array([ev[0] for ev in ref.events])
        np.testing.assert_allclose(np.asarray(seed_traj.events.t[i, :n]), t_ref, rtol=0, atol=1e-9)
        np.testing.assert_allclose(
            np.asarray(seed_traj.final.position[i])[[0, 2]],
            [ref.final[1], ref.final[2]],
            rtol=0,
            atol=1e-9,
        )


def _comparable_random_points(stairs):
    """64 random seed-like golf releases, simulated by estim and by the reference; yields
    (i, traj, ref, n) for the points where the two models must agree: no Zeno series
    before t_end, at most 60 bounces, no approach within 1e-6 of a tread edge, no bevel."""
    rng = np.random.default_rng(1234)
    e = rng.uniform(0.3, 0.95, B)
    mu = rng.uniform(0.8, 1.0, B)
    vx = rng.uniform(0.5, 1.5, B)
    r = 0.05
    pos = seed_release(stairs, "golf")
    vel = np.stack([vx, np.zeros(B), np.zeros(B)], axis=1)
    traj = run(stairs, e, mu, r, pos, vel, SEED_T_END)
    assert_complete(traj)
    edges = np.array(LEFT[:5] + [2.7])
    out = []
    for i in range(B):
        ref = Reference(e[i], mu[i], r, pos[0], pos[2], vx[i], 0.0, SEED_T_END, min_flight=1e-6)
        n = int(traj.events.count[i])
        faces = [stairs.face_label(int(f)) for f in np.asarray(traj.events.face[i, :n])]
        if (
            ref.zeno
            or ref.edge_gap < 1e-6
            or any(lab[1] != "plane" and len(lab[1]) > 2 for lab in faces)
        ):
            continue
        ev_x = np.asarray(traj.events.position[i, :n, 0])
        if n and np.min(np.abs(ev_x[:, None] - edges)) < 1e-6:
            continue
        out.append((i, traj, ref, n, faces))
    assert len(out) >= 15, f"only {len(out)} comparable points"
    return out


def test_random_points_match_numpy_reference(stairs):
    """Final state exactly as the reference (1e-9), and every event estim lists is a
    reference bounce (time, x, post-impact velocity, tread; 1e-9)."""
    for i, traj, ref, n, faces in _comparable_random_points(stairs):
        _, xf, zf, vxf, vzf = ref.final
        np.testing.assert_allclose(
            np.asarray(traj.final.position[i]), [xf, 0.0, zf], rtol=0, atol=1e-9
        )
        np.testing.assert_allclose(
            np.asarray(traj.final.velocity[i]), [vxf, 0.0, vzf], rtol=0, atol=1e-9
        )
        assert not bool(traj.events.truncated[i])
        assert np.all(np.asarray(traj.events.kind[i, :n]) == 0)  # no Zeno: impacts only
        t_ref = np.array([x[0] for x in ref.events])
        for j in range(n):
            t = float(traj.events.t[i, j])
            m = int(np.argmin(np.abs(t_ref - t)))
            assert abs(t_ref[m] - t) <= 1e-9, (i, j, t, t_ref)
            x = ref.events[m]
            np.testing.assert_allclose(
                np.asarray(traj.events.position[i, j]), [x[1], 0.0, x[2]], rtol=0, atol=1e-9
            )
            np.testing.assert_allclose(
                np.asarray(traj.events.velocity_pre[i, j]), [x[3], 0.0, x[4]], rtol=0, atol=1e-9
            )
            np.testing.assert_allclose(
                np.asarray(traj.events.velocity_post[i, j]), [x[5], 0.0, x[6]], rtol=0, atol=1e-9
            )
            assert faces[j] == (
                f"step{x[7] + 1}" if x[7] < 5 else "ground",
                "+z" if x[7] < 5 else "plane",
            )
        assert np.all(np.diff(np.asarray(traj.events.t[i, :n])) > 0)


def test_random_points_event_lists_complete(stairs):
    """Every reference bounce is listed by estim, in order (times to 1e-9). (In ab16d34,
    6 of these points lost the last bounce of a bounce train: see the next test.)"""
    bad = []
    for i, traj, ref, n, _ in _comparable_random_points(stairs):
        t_ref = np.array([x[0] for x in ref.events])
        t = np.asarray(traj.events.t[i, :n])
        if n != len(t_ref) or np.max(np.abs(t - t_ref), initial=0.0) > 1e-9:
            bad.append((i, n, len(t_ref)))
    assert not bad, f"(ball, estim events, reference bounces): {bad}"


def test_last_bounce_of_a_train_is_listed(stairs):
    """Regression (bug in ab16d34): the seed golf ball with e = 0.71 instead of 0.70 bounces
    twice on step3 (t = 1.0994598 and t = 1.4864748 s, reference); estim listed only the
    first, because list_events recounted the single bounce of the TRAIN segment (n = 1,
    ended at BOUNCES) from (t1 - t0) / t_flight = 0.9999999999999998 < 1."""
    ref = Reference(0.71, 0.98, 0.05, -0.2, 1.70, 1.15, 0.0, SEED_T_END)
    assert [x[7] for x in ref.events] == [0, 1, 2, 2, 3]
    assert ref.edge_gap > 1e-2
    traj = run(stairs, 0.71, 0.98, 0.05, (-0.2, 0.0, 1.70), (1.15, 0.0, 0.0), SEED_T_END)
    assert_complete(traj)
    np.testing.assert_allclose(
        np.asarray(traj.final.position[0])[[0, 2]], ref.final[1:3], rtol=0, atol=1e-9
    )
    assert int(traj.events.count[0]) == 5
    np.testing.assert_allclose(
        np.asarray(traj.events.t[0, :5]), [x[0] for x in ref.events], rtol=0, atol=1e-9
    )


# ---------------------------------------------------------------------------------------
# Derivatives
# ---------------------------------------------------------------------------------------

GOLF_GRAD = (0.19213914, 6.81524982, 2.17816532)  # d final x / d (e, mu_t, vx0), seed golf


def test_seed_golf_gradient(stairs):
    golf = seed_release(stairs, "golf")
    args, _ = jac_args(0.70, SEED_MU, 0.05, golf, (SEED_VX, 0.0, 0.0), SEED_T_END)
    (final, _, _, complete), (jfinal, _, _, _) = jac_outputs(stairs, *args)
    assert float(complete[0]) == 1.0
    np.testing.assert_allclose(float(final[0, 0]), 2.3048901184, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(jfinal[0, 0]), GOLF_GRAD, rtol=0, atol=1e-7)  # jacfwd
    np.testing.assert_allclose(
        np.asarray(grad_final_x(stairs, *args)), GOLF_GRAD, rtol=0, atol=1e-7
    )  # grad
    # Independent truth: central differences of estim's own primal (h = 1e-6).
    h = 1e-6
    base = np.array([0.70, SEED_MU, SEED_VX])
    pts = np.concatenate([base + h * np.eye(3), base - h * np.eye(3)])
    vel = np.stack([pts[:, 2], np.zeros(6), np.zeros(6)], axis=1)
    traj = run(stairs, pts[:, 0], pts[:, 1], 0.05, golf, vel, SEED_T_END)
    assert_complete(traj)
    x = np.asarray(traj.final.position[:6, 0])
    np.testing.assert_allclose((x[:3] - x[3:]) / (2 * h), GOLF_GRAD, rtol=0, atol=1e-7)


def _fd_batch(stairs, theta, hs, golf, ts):
    """Central differences of (final position, event times, sampled positions, event
    count, faces) for each row of theta (e, mu_t, vx0), each parameter, each h."""
    rows = []
    for h in hs:
        for k in range(3):
            for sign in (1.0, -1.0):
                rows.append(theta + sign * h * np.eye(3)[k])
    pts = np.concatenate(rows)  # (len(hs) * 6 * P, 3)
    out = []
    for start in range(0, len(pts), B):
        chunk = pts[start : start + B]
        vel = np.stack([chunk[:, 2], np.zeros(len(chunk)), np.zeros(len(chunk))], axis=1)
        tr = run(stairs, chunk[:, 0], chunk[:, 1], 0.05, golf, vel, SEED_T_END, ts=ts)
        assert_complete(tr)
        k = len(chunk)
        out.append(
            (
                np.asarray(tr.final.position[:k]),
                np.asarray(tr.events.t[:k]),
                np.asarray(tr.position[:k]),
                np.asarray(tr.events.count[:k]),
                np.asarray(tr.events.face[:k]),
            )
        )
    fin, evt, smp, cnt, face = (np.concatenate(x) for x in zip(*out, strict=True))
    P = len(theta)
    shape = (len(hs), 3, 2, P)
    return tuple(x.reshape(shape + x.shape[1:]) for x in (fin, evt, smp, cnt, face))


def test_derivatives_match_finite_differences(stairs):
    """jax.jacfwd of the final state, of every event time and of positions at fixed
    times, against central differences (h = 1e-6) at 10 random points. Entries where
    the difference quotient is unstable (h = 1e-6 and h = 1e-5 disagree by more than 1e-4
    relative: a bounce crosses to another tread, an event crosses a sample time) are
    skipped, as are event lists whose structure changes under the perturbation."""
    rng = np.random.default_rng(7)
    P = 10
    theta = np.stack(
        [rng.uniform(0.4, 0.9, P), rng.uniform(0.85, 0.99, P), rng.uniform(0.6, 1.4, P)], axis=1
    )
    golf = seed_release(stairs, "golf")
    ts = np.linspace(0.0, SEED_T_END, NT)
    vel = np.stack([theta[:, 2], np.zeros(P), np.zeros(P)], axis=1)
    args, _ = jac_args(theta[:, 0], theta[:, 1], 0.05, golf, vel, SEED_T_END, ts)
    (final, evt, smp, complete), (jfin, jevt, jsmp, _) = jac_outputs(stairs, *args)
    assert np.all(np.asarray(complete[:P]) == 1.0)
    jfin, jevt, jsmp = (np.asarray(x[:P]) for x in (jfin, jevt, jsmp))
    evt = np.asarray(evt[:P])
    hs = (1e-6, 1e-5)
    fin_p, evt_p, smp_p, cnt_p, face_p = _fd_batch(stairs, theta, hs, golf, ts)

    def quotient(x):  # (len(hs), 3, 2, P, ...) -> (len(hs), P, ..., 3)
        d = (x[:, :, 0] - x[:, :, 1]) / np.array(hs).reshape((-1, 1, 1) + (1,) * (x.ndim - 4))
        return np.moveaxis(d / 2.0, 1, -1)

    n_checked = {"final": 0, "events": 0, "samples": 0}
    with np.errstate(invalid="ignore"):
        for name, jac, x in (("final", jfin, fin_p), ("samples", jsmp, smp_p)):
            fd = quotient(x)
            stable = np.abs(fd[0] - fd[1]) <= 1e-4 * np.maximum(np.abs(fd[0]), 1.0)
            np.testing.assert_allclose(
                np.where(stable, jac, 0.0), np.where(stable, fd[0], 0.0), rtol=1e-6, atol=1e-6
            )
            n_checked[name] = int(stable.sum())
        # Event times: only where every perturbed run lists the same faces as the base.
        same = np.all(face_p == face_p[:, :1, :1], axis=(0, 1, 2, 4))  # (P,)
        fd = quotient(np.where(np.isfinite(evt_p), evt_p, 0.0))
        for i in np.flatnonzero(same):
            n = int(cnt_p[0, 0, 0, i])
            stable = np.abs(fd[0, i, :n] - fd[1, i, :n]) <= 1e-4 * np.maximum(
                np.abs(fd[0, i, :n]), 1.0
            )
            assert np.all(np.isfinite(evt[i, :n]))
            np.testing.assert_allclose(
                np.where(stable, jevt[i, :n], 0.0),
                np.where(stable, fd[0, i, :n], 0.0),
                rtol=1e-6,
                atol=1e-6,
            )
            n_checked["events"] += int(stable.sum())
    # The comparison must not be vacuous.
    assert n_checked["final"] >= 0.8 * P * 9, n_checked
    assert n_checked["samples"] >= 0.8 * P * NT * 9, n_checked
    assert n_checked["events"] >= 30, n_checked
    assert np.all(np.isfinite(jfin)) and np.all(np.isfinite(jsmp))


# ---------------------------------------------------------------------------------------
# Zeno: bounce series summed in closed form
# ---------------------------------------------------------------------------------------


def test_zeno_on_the_stairs_matches_bounce_by_bounce_reference(stairs):
    """Golf, e = 0.518, mu_t = 0.966, vx0 = 0.801: comes to rest on step2 at x ~ 0.733 m,
    t ~ 1.298 s. Truth: the numpy reference followed bounce by bounce until a flight lasts
    < 1e-12 s (what is left of the series is then < 1e-11 s and < 1e-11 m)."""
    e, mu, vx = 0.518, 0.966, 0.801
    golf = seed_release(stairs, "golf")
    ref = reference_rest(e, mu, 0.05, golf[0], golf[2], vx, 0.0)
    t_rest, x_rest = ref.events[-1][0], ref.events[-1][1]
    assert ref.events[-1][7] == 1 and abs(x_rest - 0.733) < 1e-3 and abs(t_rest - 1.298) < 1e-3
    traj = run(stairs, e, mu, 0.05, golf, (vx, 0.0, 0.0), SEED_T_END)
    assert_complete(traj)
    n = int(traj.events.count[0])
    kinds = np.asarray(traj.events.kind[0, :n])
    assert kinds[-1] == 1 and np.all(kinds[:-1] == 0)  # impacts, then one settle
    assert not bool(traj.events.truncated[0])
    assert stairs.face_label(int(traj.events.face[0, n - 1])) == ("step2", "+z")
    np.testing.assert_allclose(float(traj.events.t[0, n - 1]), t_rest, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(traj.events.position[0, n - 1]), [x_rest, 0.0, 1.25], rtol=0, atol=1e-9
    )
    # The listed impacts are the reference's first bounces (those with flights >= 1e-6 s).
    t_ref = np.array([x[0] for x in ref.events[: n - 1]])
    np.testing.assert_allclose(np.asarray(traj.events.t[0, : n - 1]), t_ref, rtol=0, atol=1e-9)
    assert t_ref[-1] - t_ref[-2] >= 1e-6 and ref.events[n - 1][0] - t_ref[-1] < 1e-6
    np.testing.assert_allclose(
        np.asarray(traj.final.position[0]), [x_rest, 0.0, 1.20 + 0.05], rtol=0, atol=1e-9
    )
    np.testing.assert_array_equal(np.asarray(traj.final.velocity[0]), [0.0, 0.0, 0.0])


def _drop(z0, r, e, g=G):
    """Closed form of a ball dropped from centre height z0 onto z = 0: (first landing time,
    impact speed, accumulation time t_fall + T0 / (1 - e), T0 = 2 e w / g)."""
    t_fall = math.sqrt(2.0 * (z0 - r) / g)
    w = g * t_fall
    t_acc = t_fall + (2.0 * e * w / g) / (1.0 - e)
    return t_fall, w, t_acc


@pytest.fixture(scope="module")
def yard_traj(yard):
    """Six balls in the yard (ground plane, wall at x = 3 - r ... 3.2), t_end = 3:
    0: Zeno with mu_t = 1, vx0 = -0.5 (slides on after accumulating),
    1: pure vertical Zeno (vx0 = 0),
    2: e = 0, mu_t = 0.9: sticks where it lands,
    3: e = 0, mu_t = 1: lands without bouncing, slides on at vx0,
    4: flies into the wall, 5: slides into the wall (released resting on the ground)."""
    r = 0.05
    rows = [
        (0.6, 1.0, (0.0, 0.0, 0.5 + r), (-0.5, 0.0, 0.0)),
        (0.6, 0.9, (0.0, 0.0, 0.5 + r), (0.0, 0.0, 0.0)),
        (0.0, 0.9, (0.0, 0.0, 0.5 + r), (0.7, 0.0, 0.0)),
        (0.0, 1.0, (0.0, 0.0, 0.5 + r), (0.7, 0.0, 0.0)),
        (0.7, 0.9, (2.5, 0.0, 0.5), (3.0, 0.0, 0.0)),
        (0.5, 1.0, (2.0, 0.0, r), (1.0, 0.0, 0.0)),
    ]
    e, mu, pos, vel = (np.array(x) for x in zip(*rows, strict=True))
    traj = run(yard, e, mu, r, pos, vel, 3.0)
    assert_complete(traj)
    return traj


def test_zeno_mu_one_slides_on(yard, yard_traj):
    r, vx = 0.05, -0.5
    _, _, t_acc = _drop(0.5 + r, r, 0.6)
    ev, n = yard_traj.events, int(yard_traj.events.count[0])
    assert int(ev.kind[0, n - 1]) == 1 and yard.face_label(int(ev.face[0, n - 1])) == (
        "ground",
        "plane",
    )
    np.testing.assert_allclose(float(ev.t[0, n - 1]), t_acc, rtol=0, atol=1e-9)
    x_acc = vx * t_acc
    np.testing.assert_allclose(float(ev.position[0, n - 1, 0]), x_acc, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(yard_traj.final.position[0]),
        [x_acc + vx * (3.0 - t_acc), 0.0, r],
        rtol=0,
        atol=1e-9,
    )
    np.testing.assert_allclose(
        np.asarray(yard_traj.final.velocity[0]), [vx, 0.0, 0.0], rtol=0, atol=1e-12
    )
    # After the accumulation it slides along the ground at constant speed.
    ts = np.linspace(t_acc + 1e-3, 3.0, NT)
    p, v = evaluate(yard_traj, np.stack([ts] * 3))
    np.testing.assert_allclose(
        np.asarray(p[0, 0]),
        np.stack([x_acc + vx * (ts - t_acc), 0 * ts, r + 0 * ts], 1),
        rtol=0,
        atol=1e-9,
    )
    np.testing.assert_allclose(
        np.asarray(v[0, 0]), np.tile([vx, 0.0, 0.0], (NT, 1)), rtol=0, atol=1e-12
    )


def test_zeno_vertical_rest_time(yard, yard_traj):
    r, e = 0.05, 0.6
    t_fall, w, t_acc = _drop(0.5 + r, r, e)
    ev, n = yard_traj.events, int(yard_traj.events.count[1])
    kinds = np.asarray(ev.kind[1, :n])
    assert kinds[-1] == 1 and np.all(kinds[:-1] == 0)
    np.testing.assert_allclose(float(ev.t[1, n - 1]), t_acc, rtol=0, atol=1e-9)
    # Bounce k happens at t_fall + T0 (1 - e^k) / (1 - e), T0 = 2 e w / g.
    k = np.arange(n - 1)
    t_k = t_fall + 2 * e * w / G * (1 - e**k) / (1 - e)
    np.testing.assert_allclose(np.asarray(ev.t[1, : n - 1]), t_k, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(ev.velocity_post[1, : n - 1, 2]), w * e ** (k + 1), rtol=0, atol=1e-9
    )
    np.testing.assert_array_equal(np.asarray(yard_traj.final.velocity[1]), [0.0, 0.0, 0.0])
    np.testing.assert_allclose(
        np.asarray(yard_traj.final.position[1]), [0.0, 0.0, r], rtol=0, atol=1e-12
    )


def test_e_zero_sticks_at_first_contact(yard, yard_traj):
    r, vx = 0.05, 0.7
    t_fall, w, _ = _drop(0.5 + r, r, 0.0)
    landing = [vx * t_fall, 0.0, r]
    for i in (2, 3):  # mu_t = 0.9, 1.0
        ev = yard_traj.events
        assert int(ev.count[i]) == 1
        np.testing.assert_allclose(float(ev.t[i, 0]), t_fall, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(ev.position[i, 0]), landing, rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            np.asarray(ev.velocity_pre[i, 0]), [vx, 0.0, -w], rtol=0, atol=1e-12
        )
    # mu_t < 1: the limit of infinitely many vanishing bounces, each scaling vx by mu_t.
    np.testing.assert_array_equal(np.asarray(yard_traj.final.velocity[2]), [0.0, 0.0, 0.0])
    np.testing.assert_allclose(np.asarray(yard_traj.final.position[2]), landing, rtol=0, atol=1e-12)
    # mu_t = 1: no normal speed left, the ball slides on.
    np.testing.assert_allclose(
        np.asarray(yard_traj.final.velocity[3]), [vx, 0.0, 0.0], rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(yard_traj.final.position[3]), [vx * 3.0, 0.0, r], rtol=0, atol=1e-12
    )


def test_wall_bounces_back(yard, yard_traj):
    r, e, mu = 0.05, 0.7, 0.9
    ev = yard_traj.events
    # Ball 4 flies into the wall's -x face (x = 3 - r) at t = (3 - r - 2.5) / 3.
    t = (3.0 - r - 2.5) / 3.0
    assert yard.face_label(int(ev.face[4, 0])) == ("wall", "-x")
    np.testing.assert_allclose(float(ev.t[4, 0]), t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(ev.position[4, 0]), [3.0 - r, 0.0, 0.5 - 0.5 * G * t * t], rtol=0, atol=1e-12
    )
    pre = np.array([3.0, 0.0, -G * t])
    np.testing.assert_allclose(np.asarray(ev.velocity_pre[4, 0]), pre, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(ev.velocity_post[4, 0]), [-e * 3.0, 0.0, mu * pre[2]], rtol=0, atol=1e-12
    )
    assert float(yard_traj.final.position[4, 0]) < 3.0 - r
    # Ball 5 slides into the wall at t = (3 - r - 2) / 1, keeps sliding back at -e m/s.
    n = int(ev.count[5])
    assert n == 2 and yard.face_label(int(ev.face[5, 1])) == ("wall", "-x")
    t = 3.0 - r - 2.0
    np.testing.assert_allclose(float(ev.t[5, 1]), t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(ev.velocity_post[5, 1]), [-0.5, 0.0, 0.0], rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(yard_traj.final.position[5]),
        [3.0 - r - 0.5 * (3.0 - t), 0.0, r],
        rtol=0,
        atol=1e-12,
    )


def test_elastic_bouncing_is_periodic(yard):
    """e = 1, mu_t = 1 on the ground: 1000 bounces, energy conserved, the closed form
    z = r + w s - g s^2 / 2 with s = (t - t1) mod T at every sample, t_k = t1 + (k-1) T."""
    r, h, vx = 0.05, 1.0, -0.3
    t1 = math.sqrt(2 * h / G)
    w = G * t1
    T = 2 * t1
    t_end = t1 + 1000.5 * T
    ks = np.unique(np.linspace(1, 1000, NT // 2).round()).astype(int)
    ks = np.concatenate([ks, np.arange(1, 1 + NT // 2 - len(ks))])
    t_bounce = t1 + (ks - 1) * T
    ts = np.sort(np.concatenate([t_bounce, t_bounce + T / 2]))
    traj = run(yard, 1.0, 1.0, r, (0.0, 0.0, r + h), (vx, 0.0, 0.0), t_end, ts=ts)
    assert_complete(traj)
    pos, vel = np.asarray(traj.position[0]), np.asarray(traj.velocity[0])
    s = np.mod(ts - t1, T)
    s = np.where(s > T - 1e-6, s - T, s)  # at a bounce time s = 0 (rounding either side)
    expect = np.stack([vx * ts, 0 * ts, r + w * s - 0.5 * G * s * s], axis=1)
    np.testing.assert_allclose(pos, expect, rtol=0, atol=1e-9)
    energy = G * pos[:, 2] + 0.5 * np.sum(vel**2, axis=1)
    e0 = G * (r + h) + 0.5 * vx * vx
    np.testing.assert_allclose(energy, e0, rtol=1e-12, atol=0)
    fin = np.asarray(traj.final.position[0])
    np.testing.assert_allclose(fin, [vx * t_end, 0.0, r + h], rtol=0, atol=1e-9)  # at an apex
    ef = G * fin[2] + 0.5 * np.sum(np.asarray(traj.final.velocity[0]) ** 2)
    np.testing.assert_allclose(ef, e0, rtol=1e-12, atol=0)
    ev = traj.events
    assert int(ev.count[0]) == 64 and bool(ev.truncated[0])
    np.testing.assert_allclose(np.asarray(ev.t[0]), t1 + np.arange(64) * T, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(ev.velocity_post[0]), np.tile([vx, 0.0, w], (64, 1)), rtol=0, atol=1e-12
    )


# ---------------------------------------------------------------------------------------
# Invariants, other faces, dense output
# ---------------------------------------------------------------------------------------


def _random_stairs_batch(rng, n=B):
    """Random releases above the stairs: any e, mu_t, velocities, each seed radius."""
    r = rng.choice([0.08, 0.05, 0.04], n)
    x = rng.uniform(-0.3, 2.7, n)
    top = np.array([TOPS[min(int((xi + 0.3) // 0.6), 4)] for xi in x])
    z = rng.uniform(top + r + 0.01, 3.0)
    pos = np.stack([x, rng.uniform(-0.5, 0.5, n), z], axis=1)
    vel = np.stack([rng.uniform(-3, 3, n), rng.uniform(-1, 1, n), rng.uniform(-2, 3, n)], axis=1)
    return rng.uniform(0, 1, n), rng.uniform(0, 1, n), r, pos, vel


def test_energy_never_increases(stairs):
    """g z + |v|^2 / 2 is non-increasing (to 1e-9 J/kg) on 4 x NT dense samples."""
    rng = np.random.default_rng(99)
    e, mu, r, pos, vel = _random_stairs_batch(rng)
    t_end = 2.3
    energies = []
    for w in range(4):
        ts = np.linspace(w * t_end / 4, (w + 1) * t_end / 4, NT)
        traj = run(stairs, e, mu, r, pos, vel, t_end, ts=ts)
        p, v = np.asarray(traj.position), np.asarray(traj.velocity)
        energies.append(G * p[..., 2] + 0.5 * np.sum(v * v, axis=-1))
    # Ball 52 of this batch slides off the lower end of step1's top-left bevel (the case
    # of test_slide_off_a_bevel_then_fall): it must complete too.
    assert_complete(traj)
    energy = np.concatenate(energies, axis=1)
    e0 = G * pos[:, 2] + 0.5 * np.sum(vel * vel, axis=1)
    np.testing.assert_allclose(energy[:, 0], e0, rtol=0, atol=1e-12)
    assert np.max(np.diff(energy, axis=1)) <= 1e-9
    # Non-vacuous: balls do lose energy.
    assert np.mean(energy[:, -1] < e0 - 1e-3) > 0.5


def test_thrown_up_the_stairs_hits_a_riser(stairs_exact):
    stairs = stairs_exact
    """Released above step3 moving -x at 2 m/s: it hits the riser of step2 (its +x face,
    x = 0.9 + r), vx flips to -e vx, vz scales by mu_t; it never ends inside a solid."""
    e, mu, r = 0.7, 0.9, 0.05
    traj = run(stairs, e, mu, r, (1.2, 0.0, 1.2), (-2.0, 0.0, 0.0), SEED_T_END)
    assert_complete(traj)
    ev, n = traj.events, int(traj.events.count[0])
    labels = [stairs.face_label(int(f)) for f in np.asarray(ev.face[0, :n])]
    j = labels.index(("step2", "+x"))
    pre, post = np.asarray(ev.velocity_pre[0, j]), np.asarray(ev.velocity_post[0, j])
    assert pre[0] < 0 < post[0]
    np.testing.assert_allclose(post, [-e * pre[0], 0.0, mu * pre[2]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(float(ev.position[0, j, 0]), 0.9 + r, rtol=0, atol=1e-12)
    assert 1.0 <= float(ev.position[0, j, 2]) <= 1.2  # on the riser, between the tops
    # Independent check: straight ballistic flight from (1.2, 1.2) at -2 m/s reaches the
    # riser plane x = 0.9 + r at t = (1.2 - 0.9 - r) / 2, above step3 (z - r > 1.0).
    t = (1.2 - 0.9 - r) / 2.0
    assert j == 0
    np.testing.assert_allclose(float(ev.t[0, 0]), t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(pre, [-2.0, 0.0, -G * t], rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        float(ev.position[0, 0, 2]), 1.2 - 0.5 * G * t * t, rtol=0, atol=1e-12
    )
    for p in (np.asarray(traj.final.position[0]), *np.asarray(traj.position[0])):
        assert np.min(box_distance(p, stairs.box_centre, stairs.box_half)) >= r - 1e-9
        assert p[2] >= r - 1e-9


def test_dense_output(stairs, seed_traj):
    ts = np.asarray(seed_traj.ts)
    p, v = evaluate(seed_traj, np.stack([ts] * 3))
    np.testing.assert_allclose(
        np.asarray(p[:, 0]), np.asarray(seed_traj.position), rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(v[:, 0]), np.asarray(seed_traj.velocity), rtol=0, atol=1e-12
    )
    # Continuity across every event: left / right neighbours of the event time (one ulp
    # away) and the event time itself give the event's position.
    for i in range(3):
        n = int(seed_traj.events.count[i])
        t = np.full(NT, SEED_T_END / 2)  # (the slots past n: any time inside [0, t_end])
        t[:n] = np.asarray(seed_traj.events.t[i, :n])
        times = np.stack([np.nextafter(t, -np.inf), t, np.nextafter(t, np.inf)])
        p, v = evaluate(seed_traj, times)
        p, v = np.asarray(p[i]), np.asarray(v[i])
        ev_pos = np.asarray(seed_traj.events.position[i, :n])
        for side in range(3):
            np.testing.assert_allclose(p[side, :n], ev_pos, rtol=0, atol=1e-12)
        # Velocity jumps there: pre-impact just before, post-impact just after (1e-9).
        np.testing.assert_allclose(
            v[0, :n], np.asarray(seed_traj.events.velocity_pre[i, :n]), rtol=0, atol=1e-9
        )
        np.testing.assert_allclose(
            v[2, :n], np.asarray(seed_traj.events.velocity_post[i, :n]), rtol=0, atol=1e-9
        )
    # Dense output on a grid between the samples equals the analytic parabola of the
    # first flight (golf: x0 + vx t, z0 - g t^2 / 2 until the first impact).
    t_first = float(seed_traj.events.t[1, 0])
    tt = np.linspace(0.0, t_first, NT)
    p, _ = evaluate(seed_traj, np.stack([tt] * 3))
    golf = seed_release(stairs, "golf")
    expect = np.stack([golf[0] + SEED_VX * tt, 0 * tt, golf[2] - 0.5 * G * tt * tt], axis=1)
    np.testing.assert_allclose(np.asarray(p[1, 0]), expect, rtol=0, atol=1e-12)


def test_drop_onto_an_edge_bounces_off_along_its_normal(stairs_exact):
    """Golf, e = 0.5, mu_t = 0.5, dropped from rest at (-0.325, 0, 1.6), r/2 beyond step1's
    top-left edge (x = -0.3, z = 1.4): it meets the edge's fillet 60 degrees round from the
    top, where (x + 0.3)^2 + (z - 1.4)^2 = r^2, is reset about the normal from the edge to
    its centre, flies up and away past the riser and lands on the ground (closed forms)."""
    r, e, mu = 0.05, 0.5, 0.5
    traj = run(stairs_exact, e, mu, r, (-0.325, 0.0, 1.6), (0.0, 0.0, 0.0), 1.0)
    assert_complete(traj, 1)
    ev = traj.events
    z_c = 1.4 + math.sqrt(r * r - 0.025**2)
    t_c = math.sqrt(2 * (1.6 - z_c) / G)
    n = np.array([-0.025, 0.0, z_c - 1.4]) / r
    v = np.array([0.0, 0.0, -G * t_c])
    post = mu * (v - (v @ n) * n) - e * (v @ n) * n
    assert stairs_exact.face_label(int(ev.face[0, 0])) == ("step1", "-x+z")
    np.testing.assert_allclose(float(ev.t[0, 0]), t_c, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(ev.position[0, 0]), [-0.325, 0.0, z_c], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(ev.velocity_post[0, 0]), post, rtol=0, atol=1e-12)
    # Then a parabola to the ground, z = r.
    t_g = (post[2] + math.sqrt(post[2] ** 2 + 2 * G * (z_c - r))) / G
    assert stairs_exact.face_label(int(ev.face[0, 1])) == ("ground", "plane")
    np.testing.assert_allclose(float(ev.t[0, 1]), t_c + t_g, rtol=0, atol=1e-12)
    np.testing.assert_allclose(float(ev.position[0, 1, 0]), -0.325 + post[0] * t_g, rtol=0, atol=1e-12)


@pytest.mark.parametrize("air", [False, True], ids=["closed_form", "ode"])
def test_argument_checks_run_inside_jit(stairs, air):
    """Inside a user's jit the values are traced, so simulate's Python checks cannot see
    them; the same checks run in the compiled program and raise with the same words. (Before
    they did, t_end = -1 ran the parabola backwards through the ground, and t_end = NaN
    reported too few segments.)"""
    scene = stairs.with_air(estim.Air(density=1.204)) if air else stairs
    golf = scene.ball("golf")

    @jax.jit
    def final(t_end, ts, position, e, lift_factor):
        p = estim.Params(e, 0.98, golf.radius, position, jnp.array([1.15, 0.0, 0.0]), mass=golf.mass,
                         lift_factor=lift_factor)
        return estim.simulate(scene, p, t_end, ts=ts, keep=("samples",)).final.position

    good = dict(t_end=1.0, ts=jnp.array([0.0, 0.5, 1.0]), position=jnp.array([-0.2, 0.0, 1.7]), e=0.7,
                lift_factor=1.0)
    ref = estim.simulate(scene, estim.Params(0.7, 0.98, golf.radius, (-0.2, 0.0, 1.7), (1.15, 0.0, 0.0),
                                             mass=golf.mass), 1.0).final.position
    np.testing.assert_allclose(np.asarray(final(**good)), np.asarray(ref), rtol=0, atol=1e-12)
    bad = [
        (dict(t_end=-1.0), "t_end must be a finite time > 0"),
        (dict(t_end=jnp.nan), "t_end must be a finite time > 0"),
        (dict(ts=jnp.array([0.0, 1.5, 1.0])), r"ts must be finite and lie in \[0, t_end\]"),
        (dict(ts=jnp.array([-0.1, 0.5, 1.0])), r"ts must be finite and lie in \[0, t_end\]"),
        (dict(position=jnp.array([0.0, 0.0, 1.0])), "a ball starts inside a solid"),  # step1
        (dict(position=jnp.array([2.0, 0.0, -0.02])), "a ball starts inside a solid"),  # the ground
        (dict(e=1.5), r"e must lie in \[0, 1\]"),
    ]
    if air:  # (checks the native kernels of a scene without air do not run: what they do not read)
        bad += [(dict(lift_factor=-1.0), "lift_factor must be >= 0"),  # a check after the solids'
                (dict(e=1.5, lift_factor=-1.0), r"e must lie in \[0, 1\]")]  # the first failing check
    for change, words in bad:
        with pytest.raises(ValueError, match=words):
            jax.block_until_ready(final(**{**good, **change}))


def test_evaluate_refuses_times_outside_the_solution(stairs, seed_traj):
    """The dense solution covers [0, t_end]: outside it, evaluate raises (in Python for
    concrete times, in the program inside jit) instead of extrapolating a parabola."""
    t_end = float(np.asarray(seed_traj.final.t).ravel()[0])
    for t in (-0.1, t_end + 0.5, np.nan, [0.5, t_end * 2]):
        with pytest.raises(ValueError, match=r"t must be finite and lie in \[0, t_end"):
            seed_traj.evaluate(t)
    inside = jax.jit(lambda t: seed_traj.evaluate(t)[0])
    np.testing.assert_allclose(np.asarray(inside(t_end)), np.asarray(seed_traj.final.position), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match=r"t must be finite and lie in \[0, t_end\]"):
        jax.block_until_ready(inside(t_end + 0.5))


@pytest.mark.parametrize(("x", "aside", "fall", "solid"), [
    (0.5, (), 0.5 - 0.1525 - 0.02, "net"),  # onto the net's top
    (0.5, ("net",), 0.5 - 0.02, "table"),  # past the net to the table
    (1.0, (), 0.5 + 0.76 - 0.02, "floor"),  # beside the table to the floor
    (1.0, ("floor",), None, None),  # to no floor
])
def test_a_solid_set_aside_is_out_of_play(x, aside, fall, solid):
    """``Scene.set_aside`` moves solids out of reach: a ball dropped from 0.5 m above the
    table-tennis table's top, on the net's line or beside the table, first meets what is
    left in play, at the closed-form time of its fall from rest in a vacuum, sqrt(2 h / g)."""
    scene = estim.load_scene(ROOT / "data" / "scenes" / "table_tennis.xml").with_air(None).set_aside(aside)
    params = estim.Params.for_ball(scene, "pingpong", e=0.9, mu_t=0.0, mu=0.2, position=np.array([x, 0.0, 0.5]),
                                   velocity=np.zeros(3))
    events = estim.simulate(scene, params, 0.6).events
    n = int(np.asarray(events.count).ravel()[0])
    if fall is None:
        assert n == 0
        return
    assert scene.face_label(int(np.asarray(events.face).reshape(-1)[0]))[0] == solid
    assert float(np.asarray(events.t).reshape(-1)[0]) == pytest.approx(math.sqrt(2 * fall / float(scene.gravity)),
                                                                       abs=1e-9)


def test_set_aside_names_a_solid_the_scene_lacks():
    scene = estim.load_scene(ROOT / "data" / "scenes" / "table_tennis.xml")
    with pytest.raises(KeyError, match="'fence'.*'net'"):
        scene.set_aside(("fence",))
