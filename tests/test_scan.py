"""estim.forward._scan.scan_used against lax.scan: same values and derivatives (forward and reverse
mode), whatever the number of used items, the chunking and the batching."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from estim.forward._scan import scan_used

IDLE = -1.0  # an item that leaves the carry alone


def step(carry, x):
    """A damped, nonlinear recurrence; idle items keep the carry and output (carry, 0)."""
    s, p = carry
    active = x != IDLE
    s1 = jnp.where(active, jnp.sin(s) * p + x * x, s)
    p1 = jnp.where(active, p * (1.0 + 0.1 * x), p)
    return (s1, p1), (s1, jnp.where(active, s1 * p1, 0.0))


def idle(carry):
    return carry[0], jnp.zeros(())


def items(length, n_used, seed=0):
    x = np.random.default_rng(seed).uniform(0.0, 1.0, length)
    x[n_used:] = IDLE
    return jnp.asarray(x)


def both(theta, xs, n_used):
    init = (theta[0], theta[1])
    ref = jax.lax.scan(step, init, xs)
    got = scan_used(step, init, xs, n_used, idle, jnp.float64(IDLE))
    return ref, got


@pytest.mark.parametrize("length", [1, 5, 48, 50])
@pytest.mark.parametrize("frac", [0.0, 0.3, 1.0])
def test_values_and_derivatives_match_lax_scan(length, frac):
    n_used = int(round(frac * length))
    xs = items(length, n_used)
    theta = jnp.array([0.3, 1.2])
    ref, got = both(theta, xs, n_used)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got), strict=True):
        np.testing.assert_array_equal(a, b)

    def total(which):
        def f(th):
            ref, got = both(th, xs, n_used)
            (s, p), (ys, zs) = ref if which == "ref" else got
            return s * p + jnp.sum(ys * zs)
        return f

    for d in (jax.grad, jax.jacfwd):
        np.testing.assert_allclose(d(total("got"))(theta), d(total("ref"))(theta), rtol=1e-13, atol=0)


def test_batched_count_is_exact():
    """Under vmap the count may differ per element (cond becomes select): still exact."""
    length = 30
    counts = jnp.array([0, 4, 17, 30])
    xs = jnp.stack([items(length, int(n), seed=i) for i, n in enumerate(counts)])
    theta = jnp.array([0.7, 0.9])

    def one(x, n):
        ref, got = both(theta, x, n)
        return ref, got

    ref, got = jax.vmap(one)(xs, counts)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got), strict=True):
        np.testing.assert_array_equal(a, b)
