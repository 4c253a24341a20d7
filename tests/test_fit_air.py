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
    with pytest.raises(ValueError, match="needs a scene with air"):
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
