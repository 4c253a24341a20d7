"""A whole series of bounces on one face, in closed form.

After a bounce on a face with unit normal n, split gravity ``a`` and the velocity into normal
and tangential parts: ``a_n = a . n < 0`` (gravity presses the ball onto the face),
``a_t = a - a_n n``; normal speed ``w > 0``, tangential velocity ``u``. Every flight leaves
and returns to the face with the same normal speed, which the next bounce scales by e, so
flight j lasts ``T_j = T0 e^j`` with ``T0 = 2 w / |a_n|``. The tangential velocity gains
``a_t T_j`` in flight j and is scaled by mu at the bounce that ends it:

    u_j = mu^j u + a_t T0 mu K_j,               K_j = sum_{k<j} mu^(j-1-k) e^k = (mu^j - e^j) / (mu - e).

Summing the flights gives the start of flight j (time, tangential displacement):

    t_j = T0 (1 - e^j) / (1 - e),
    X_j = T0 (u G(e mu, j) + a_t T0 mu L_j) + a_t T0^2 G(e^2, j) / 2,
    L_j = sum_{i<j} e^i K_i = (G(e mu, j) - G(e^2, j)) / (mu - e),

with ``G(q, j) = (1 - q^j) / (1 - q)``. On a horizontal face a_t = 0 and this is the series
of the seed stairs (``estim.forward._solver``, eq. (1)). For e < 1 every sum converges as j -> inf:
the series accumulates at ``T0 / (1 - e)`` (Zeno) with tangential velocity
``u_inf = u + a_t T0 / (1 - e)`` if mu = 1 and 0 otherwise.

Where mu and e agree to within 1e-6 the divided differences K and L are evaluated with e
moved by 1e-6, a relative error of that order in the (then tiny) gravity terms, instead of
a division by zero.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ._contact import geometric_count, geometric_sum, inner, safe_power

_GAP = 1e-6
# Bounce counts are whole floats; beyond 2^52 float64 cannot count them. (An e = 1 series
# with a 0.2 us period reaches 10^7 bounces in 2 s: a cap of 10^6 made such a ball fall
# through its face after 10^6 bounces.)
_MAX_COUNT = 2.0**52


class Series(NamedTuple):
    normal: jnp.ndarray  # (3,)
    a_n: jnp.ndarray  # normal gravity (< 0)
    a_t: jnp.ndarray  # (3,) tangential gravity
    w: jnp.ndarray  # normal speed after the first bounce
    u: jnp.ndarray  # (3,) tangential velocity after it
    period: jnp.ndarray  # T0, the first flight's duration


def series(v, normal, a) -> Series:
    """Decompose the post-bounce velocity ``v`` on a face of normal ``normal``."""
    a_n = inner(a, normal)
    w = inner(v, normal)
    return Series(normal, a_n, a - a_n * normal, w, v - w * normal, 2.0 * w / -a_n)


def _differences(e, mu, j):
    """K_j and L_j of the module docstring (j may be inf)."""
    close = jnp.abs(mu - e) < _GAP
    e2 = jnp.where(close, jnp.where(e >= _GAP, e - _GAP, e + _GAP), e)
    gap = mu - e2
    k = (safe_power(mu, j) - safe_power(e2, j)) / gap
    l_ = (geometric_sum(e2 * mu, j) - geometric_sum(e2 * e2, j)) / gap
    return k, l_


@jax.jit  # traced once per signature, not at each call (estim._config, TRACING)
def flight_start(s: Series, j, e, mu_t):
    """Time offset, displacement and velocity at the start of flight j (after bounce j)."""
    t = s.period * geometric_sum(e, j)
    finite = jnp.isfinite(t)  # false only for e = 1, j = inf: never reached
    jj = jnp.where(finite, j, 0.0)
    k, _ = _differences(e, mu_t, j)
    _, l_ = _differences(e, mu_t, jj)
    displacement = s.period * (s.u * geometric_sum(e * mu_t, jj) + s.a_t * s.period * mu_t * l_) + 0.5 * s.a_t * s.period**2 * geometric_sum(e * e, jj)
    u_j = safe_power(mu_t, j) * s.u + s.a_t * s.period * mu_t * k
    w_j = s.w * safe_power(e, j)
    return t, displacement, u_j + w_j * s.normal


def state_at(s: Series, tau, e, mu_t, n_max):
    """Displacement and velocity ``tau`` after the series began (at most n_max bounces)."""
    j = geometric_count(e, tau / s.period)
    j = jnp.minimum(jnp.minimum(j, n_max), _MAX_COUNT)  # n_max may be inf
    t_j, x_j, v_j = flight_start(s, j, e, mu_t)
    tau_j = tau - t_j
    displacement = x_j + v_j * tau_j + 0.5 * (s.a_t + s.a_n * s.normal) * tau_j**2
    return displacement, v_j + (s.a_t + s.a_n * s.normal) * tau_j


def series_end(s: Series, n, e, mu_t):
    """Duration, displacement and velocity after bounce n (n = inf: the Zeno limit)."""
    duration, displacement, velocity = flight_start(s, n, e, mu_t)
    finite = jnp.isfinite(n)
    # At the Zeno limit the normal speed is 0 and the tangential velocity u_inf.
    velocity = jnp.where(finite, velocity, velocity - inner(velocity, s.normal) * s.normal)
    return duration, displacement, velocity


def bounce(s: Series, j, e, mu_t):
    """Bounce j (from 1): time offset, displacement, velocity before and after, and the
    start (time offset, displacement, velocity) of the flight that ends at it."""
    t, x, post = flight_start(s, j, e, mu_t)
    t_s, x_s, v_s = flight_start(s, j - 1.0, e, mu_t)
    tau = t - t_s
    pre = v_s + (s.a_t + s.a_n * s.normal) * tau
    return t, x, pre, post, (t_s, x_s, v_s)
