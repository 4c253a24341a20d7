"""estim._fold: reductions over short axes written out, against NumPy's reductions, and the
air's vector field free of reducers (each costs every call of a program, estim._fold)."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import estim  # noqa: F401  (float64)
from estim._fold import LONGEST, first_least, inner, least, some, total
from estim.model._air import Air, acceleration, step_bounds


@pytest.mark.parametrize("n", [1, 2, 3, 5, 6, 7, 8, LONGEST + 3])
@pytest.mark.parametrize("axis", [0, -1])
def test_folds_match_numpy(n, axis):
    rng = np.random.default_rng(n)
    x = rng.normal(size=(n, 4) if axis == 0 else (4, n))
    x[x > 1.0] = np.inf  # infinities and ties
    x.flat[::3] = np.round(x.flat[::3])
    np.testing.assert_array_equal(least(x, axis), np.min(x, axis))
    np.testing.assert_array_equal(some(x > 0.5, axis), np.any(x > 0.5, axis))
    np.testing.assert_array_equal(first_least(x, axis), np.argmin(x, axis))
    finite = np.where(np.isfinite(x), x, 0.0)
    left_to_right = np.moveaxis(finite, axis, -1)[..., 0].copy()
    for i in range(1, n):
        left_to_right = left_to_right + np.moveaxis(finite, axis, -1)[..., i]
    np.testing.assert_allclose(total(finite, axis), np.sum(finite, axis), rtol=1e-14, atol=1e-14)
    if n <= LONGEST:  # written out: the rounding of a loop, exactly
        np.testing.assert_array_equal(total(finite, axis), left_to_right)


def test_least_lets_nan_win_and_inner_is_a_dot():
    np.testing.assert_array_equal(least(jnp.array([1.0, jnp.nan, -2.0])), np.nan)
    x, y = np.array([[1e16, 1.0, -1e16]]), np.array([[1.0, 1.0, 1.0]])
    assert float(inner(x, y)[0]) == (1e16 * 1.0 + 1.0 * 1.0) + (-1e16) * 1.0  # left to right: 0
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    np.testing.assert_allclose(inner(a, b), np.einsum("ij,ij->i", a, b), rtol=1e-14)


def test_the_air_vector_field_and_step_bound_have_no_reducer():
    """The air's acceleration is evaluated at every Runge-Kutta stage of every step: its
    reductions are written out, so its program has no ``reduce``."""
    air = Air(density=1.2, viscosity=1.8e-5, wind=(0.5, 0.0, 0.0))

    def f(v, w):
        a = acceleration(air, 9.81, 0.02, 0.0027, 0.5, w, v, 1.0)
        return a, step_bounds(air, 9.81, 0.02, 0.0027, 0.5, w, v, 0.01, 1.0)

    v, w = jnp.array([3.0, -1.0, 2.0]), jnp.array([10.0, -150.0, 20.0])
    hlo = jax.jit(f).lower(v, w).compile().as_text()
    assert not re.search(r"\breduce\(", hlo)
    # Drag against its formula with NumPy's sums (eqs. (1)-(2) of estim.model._air).
    rel = np.asarray(v) - np.array([0.5, 0.0, 0.0])
    speed = np.sqrt(np.sum(rel * rel))
    area = np.pi * 0.02**2
    quad = -(1.2 * 0.5 * area / (2 * 0.0027)) * speed * rel
    lin = -(6 * np.pi * 1.8e-5 * 0.02 / 0.0027) * rel
    no_spin = np.asarray(acceleration(air, 9.81, 0.02, 0.0027, 0.5, jnp.zeros(3), v, 1.0))
    np.testing.assert_allclose(no_spin, quad + lin + np.array([0.0, 0.0, -9.81]), rtol=1e-14)


def test_first_least_stays_in_range_with_nan():
    assert 0 <= int(first_least(jnp.array([3.0, jnp.nan, 1.0, 2.0]))) < 4
