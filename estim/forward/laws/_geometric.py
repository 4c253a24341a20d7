"""Geometric sums and counts, accurate and differentiable at the ends of their range: the
arithmetic of bounce series (``estim.forward.laws.FactorLaw``, ``FrictionLaw``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp


@jax.jit  # traced once per signature, not at each call (estim._config, TRACING)
def geometric_sum(q, n):
    """``sum_{j<n} q^j = (1 - q^n) / (1 - q)`` for q in [0, 1] and real n >= 0 (n may be
    inf), accurate and differentiable up to q = 1, where it is n (with the exact first
    derivative n (n - 1) / 2 there)."""
    one = q == 1.0
    zero = q == 0.0
    lq = jnp.log(jnp.where(one | zero, 0.5, q))
    n_safe = jnp.where(jnp.isfinite(n), n, 1e300)
    general = jnp.expm1(jnp.minimum(n_safe * lq, 0.0)) / jnp.expm1(lq)
    general = jnp.where(jnp.isfinite(n), general, -1.0 / jnp.expm1(lq))
    # (At q = 1 an infinite n gives inf below; a finite stand-in keeps reverse-mode
    # cotangents of this unused branch free of inf * 0.)
    n_one = jnp.where(jnp.isfinite(n), n, 1.0)
    at_one = n_one + 0.5 * n_one * (n_one - 1.0) * (q - 1.0)
    at_zero = jnp.where(n >= 1, 1.0 + q * jnp.minimum(n - 1.0, 1.0), 0.0)
    return jnp.where(one, jnp.where(jnp.isfinite(n), at_one, jnp.inf), jnp.where(zero, at_zero, general))


@jax.jit  # traced once per signature, not at each call (estim._config, TRACING)
def geometric_count(q, y):
    """Largest whole n >= 0 with ``geometric_sum(q, n) <= y`` (inf if every n qualifies).

    Not differentiated: counts are discrete. A correction step makes the result exact with
    respect to ``geometric_sum`` itself, whatever the rounding of the logarithms.
    """
    q = jax.lax.stop_gradient(q)
    y = jax.lax.stop_gradient(y)
    lq = jnp.log(jnp.where((q > 0) & (q < 1), q, 0.5))
    arg = 1.0 - y * (1.0 - q)
    n_gen = jnp.where(arg > 0, jnp.floor(jnp.log(jnp.where(arg > 0, arg, 1.0)) / lq), jnp.inf)
    n = jnp.where(q >= 1.0, jnp.floor(y), jnp.where(q <= 0.0, jnp.where(y >= 1, jnp.inf, 0.0), n_gen))
    n = jnp.where(y < 0, -1.0, n)
    finite = jnp.isfinite(n) & (n >= 0)
    nf = jnp.where(finite, n, 0.0)
    n = jnp.where(finite & (geometric_sum(q, nf + 1) <= y), nf + 1, n)
    n = jnp.where(finite & (nf > 0) & (geometric_sum(q, nf) > y), nf - 1, n)
    return jnp.where(y < 0, -1.0, jnp.maximum(n, 0.0))


@jax.jit  # traced once per signature, not at each call (estim._config, TRACING)
def safe_power(x, n):
    """``x ** n`` for x in [0, 1] and whole n >= 0 (n may be inf), with finite gradients:
    ``x ** 0 = 1`` and ``x ** inf = 0`` (``1`` when x = 1)."""
    finite = jnp.isfinite(n)
    whole = finite & (n >= 1)
    n_safe = jnp.where(whole, n, 1.0)
    x_pos = x > 0
    x_safe = jnp.where(x_pos, x, 1.0)
    # x^n = x * x^(n-1), so that d/dx at x = 0 is 1 for n = 1 and 0 beyond.
    rest = jnp.where(x_pos, x_safe ** (n_safe - 1.0), jnp.where(n_safe == 1.0, 1.0, 0.0))
    at_inf = jnp.where(x == 1.0, 1.0, 0.0)
    return jnp.where(whole, x * rest, jnp.where(finite, 1.0, at_inf))


def flights_at_least(e, period, shortest):
    """How many flights of a series whose flight j lasts ``period e^j`` last at least
    ``shortest``: those with ``j <= log(shortest / period) / log(e)``; every flight for
    e = 1, none for e = 0. Not differentiated."""
    le = jnp.log(jnp.where((e > 0) & (e < 1), e, 0.5))
    ratio = jnp.log(shortest / period)
    listable = jnp.where(period >= shortest, jnp.floor(ratio / le) + 1.0, 0.0)
    return jnp.where((e > 0) & (e < 1), listable, jnp.where(e == 0, 0.0, jnp.inf))
