"""Fitting in a scene with air: the drag coefficient is recovered from synthetic tracks."""

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ROOT

import estim

DROP = ROOT / "data" / "scenes" / "drop.xml"


def test_drag_coefficient_needs_air():
    scene = estim.load_scene(DROP)
    t = np.linspace(0.0, 0.5, 30)
    pos = np.stack([0.0 * t, np.full_like(t, np.nan), 0.5 - 4.905 * t**2], axis=1)
    with pytest.raises(ValueError, match="acts only in a scene with air"):
        estim.fit(scene, {"pingpong": (t, pos)}, free=("e", "drag_coefficient"))


@pytest.mark.slow
def test_fit_recovers_drag_coefficient_and_restitution():
    """A 2.7 g ping-pong ball dropped in air, 120 fps, 0.5 mm noise: C_D and e come back
    within 3 standard errors of the values that made the data."""
    scene = estim.load_scene(DROP).with_air(estim.Air(density=1.204))
    truth = dict(e=0.82, mu_t=0.9, vx0=0.3, drag_coefficient=0.50)
    params = estim.Params.for_ball(scene, "pingpong", e=truth["e"], mu_t=truth["mu_t"],
                                   velocity=(truth["vx0"], 0, 0),
                                   drag_coefficient=truth["drag_coefficient"])
    ts = jnp.arange(0.0, 1.5, 1 / 120)
    exact = np.asarray(estim.simulate(scene, params, 1.5, ts=ts).position)
    obs = exact + np.random.default_rng(0).normal(0.0, 5e-4, exact.shape)
    obs[:, 1] = np.nan  # a side view: no depth
    result = estim.fit(scene, {"pingpong": (np.asarray(ts), obs)},
                       free=("e", "mu_t", "vx0", "x0", "z0", "drag_coefficient"), restarts=0)
    fitted = result.balls["pingpong"]
    for name in ("e", "vx0", "drag_coefficient"):
        err = fitted.values[name] - truth[name]
        assert abs(err) < 3 * fitted.stderr[name], (name, err, fitted.stderr[name])
    assert fitted.stderr["drag_coefficient"] < 0.02
    assert fitted.rms_m == pytest.approx(5e-4, rel=0.15)  # the noise floor


@pytest.mark.slow
def test_fit_recovers_the_lift_factor_of_a_spinning_ball():
    """A ping-pong ball thrown with 150 rad/s of backspin in air, its Magnus lift 1.3 times
    the textbook curve (the lift factor), 120 fps, 0.5 mm noise, spin known: the lift factor
    comes back within 3 standard errors of the value that made the data, and the fit
    reaches the noise floor."""
    scene = estim.load_scene(DROP).with_air(estim.Air(density=1.204))
    spin = (0.0, -150.0, 0.0)  # backspin for a ball moving along +x: lift
    params = estim.Params.for_ball(scene, "pingpong", e=0.85, mu_t=0.9, position=(-0.6, 0.0, 0.4),
                                   velocity=(2.5, 0, 0.5), spin=spin, lift_factor=1.3)
    ts = jnp.arange(0.0, 0.9, 1 / 120)
    exact = np.asarray(estim.simulate(scene, params, 0.9, ts=ts).position)
    obs = exact + np.random.default_rng(1).normal(0.0, 5e-4, exact.shape)
    obs[:, 1] = np.nan
    fixed = {"pingpong": {"spin_x": 0.0, "spin_y": spin[1], "spin_z": 0.0}}
    result = estim.fit(scene, {"pingpong": (np.asarray(ts), obs)}, fixed=fixed,
                       free=("e", "mu_t", "vx0", "vz0", "x0", "z0", "lift_factor"), restarts=0)
    fitted = result.balls["pingpong"]
    err = fitted.values["lift_factor"] - 1.3
    assert abs(err) < 3 * fitted.stderr["lift_factor"], (err, fitted.stderr["lift_factor"])
    assert fitted.stderr["lift_factor"] < 0.1
    assert fitted.rms_m == pytest.approx(5e-4, rel=0.15)
