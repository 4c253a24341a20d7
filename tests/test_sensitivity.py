"""Event-time sensitivities: autodiff through the solver against the implicit-function
theorem (dt/dp = -(dg/dp + dg/dx dx/dp) / (dg/dt)) and against finite differences."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import STAIRS_XML

import estim


@pytest.fixture(scope="module")
def scene():
    return estim.load_scene(STAIRS_XML)


def make_golf(theta):
    """theta = (e, mu_t, vx0, z0, top of step3): ball parameters and one scene dimension."""
    return estim.Params(theta[0], theta[1], 0.05, jnp.stack([-0.2, 0.0, theta[3]]),
                        jnp.stack([theta[2], 0.0, 0.0]))


def with_step3_raised(scene, dz):
    """The scene with the top of step3 moved up by dz (its box grows from the ground)."""
    return estim.Scene(scene.box_centre.at[2, 2].add(dz / 2), scene.box_half.at[2, 2].add(dz / 2),
                       scene.plane_normal, scene.plane_offset, scene.gravity, scene.names,
                       scene.face_solid, scene.face_direction, scene.balls)


def event_times(scene, theta):
    sc = with_step3_raised(scene, theta[4])
    ev = estim.simulate(sc, make_golf(theta), 2.3, max_events=64).events
    return np.asarray(ev.t), int(ev.count)


def test_seed_point_autodiff_equals_implicit_and_fd(scene):
    theta = jnp.array([0.70, 0.98, 1.15, 1.70, 0.0])
    s = estim.event_sensitivities(lambda th: (with_step3_raised(scene, th[4]), make_golf(th)),
                                  theta, 2.3)
    v = np.asarray(s.valid)
    assert v.sum() == 6  # the six bounces of the seed golf ball
    auto, impl = np.asarray(s.autodiff)[v], np.asarray(s.implicit)[v]
    # Two formulas of the same derivative: equal to rounding.
    np.testing.assert_allclose(auto, impl, rtol=1e-10, atol=1e-12)
    assert not np.any(np.asarray(s.grazing))
    # Against central differences of the event times (h = 1e-6; the contact sequence does
    # not change within h here).
    h = 1e-6
    t0, n = event_times(scene, np.asarray(theta))
    for k in range(5):
        dp = np.zeros(5)
        dp[k] = h
        tp, n_p = event_times(scene, np.asarray(theta) + dp)
        tm, n_m = event_times(scene, np.asarray(theta) - dp)
        assert n_p == n_m == n
        fd = (tp[:n] - tm[:n]) / (2 * h)
        np.testing.assert_allclose(auto[:, k], fd, rtol=1e-6, atol=1e-7)
    # Raising step3 makes the ball land on it earlier: negative derivative for its bounces.
    assert np.all(auto[2:4, 4] < 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_points_autodiff_equals_implicit(scene, seed):
    rng = np.random.default_rng(seed)
    theta = jnp.array([rng.uniform(0.3, 0.95), rng.uniform(0.85, 1.0), rng.uniform(0.5, 1.6),
                       rng.uniform(1.6, 2.2), rng.uniform(-0.05, 0.05)])
    s = estim.event_sensitivities(lambda th: (with_step3_raised(scene, th[4]), make_golf(th)),
                                  theta, 2.3)
    v = np.asarray(s.valid) & ~np.asarray(s.grazing)
    assert v.sum() >= 3
    auto, impl = np.asarray(s.autodiff)[v], np.asarray(s.implicit)[v]
    assert np.all(np.isfinite(auto)) and np.all(np.isfinite(impl))
    # Deep in a Zeno series the closing speed is tiny and (1) amplifies rounding: compare
    # relative to the size of the derivative.
    scale = np.maximum(np.abs(auto), 1.0)
    assert np.max(np.abs(auto - impl) / scale) < 1e-6


def test_grazing_contact_is_flagged_not_nan():
    # A ball drifting towards a wall with a vanishing normal speed: the contact time
    # gap / vx and its derivative -gap / vx^2 blow up as vx -> 0, but stay finite, and
    # below 1e-6 m/s the event is flagged as grazing.
    wall = estim.Scene.from_arrays({}, {"wall": ((-1.0, 0.0, 0.0), -0.1)})  # solid x >= 0.1
    gap = 1e-8
    for vx in (1e-3, 1e-7):
        s = estim.event_sensitivities(
            lambda th: estim.Params(0.5, 0.9, 0.05, jnp.array([0.05 - gap, 0.0, 0.0]),
                                    jnp.stack([th[0], 0.0, 0.0])),
            jnp.array([vx]), 1.0, scene=wall)
        assert np.all(np.isfinite(np.asarray(s.autodiff)))
        assert np.all(np.isfinite(np.asarray(s.implicit)))
        assert bool(s.valid[0])
        assert float(s.t[0]) == pytest.approx(gap / vx, rel=1e-6)
        assert float(s.closing_speed[0]) == pytest.approx(-vx, rel=1e-9)
        assert float(s.autodiff[0, 0]) == pytest.approx(-gap / vx**2, rel=1e-6)
        assert bool(s.grazing[0]) == (vx < 1e-6)
        if vx >= 1e-6:
            assert float(s.implicit[0, 0]) == pytest.approx(-gap / vx**2, rel=1e-6)
