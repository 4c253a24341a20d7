"""The seed's contact law: restitution e on the normal velocity, a factor mu_t on the
tangential one."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ...model._params import Params
from .._constants import SERIES_GAP
from .._contact import inner
from ._base import AbstractSummableLaw, Series
from ._geometric import flights_at_least, geometric_count, geometric_sum, safe_power


class FactorCoefficients(eqx.Module):
    """The factor law's numbers, per ball: restitution e and tangential factor mu_t, both in
    [0, 1] (``estim.Params``)."""

    e: Float[Array, "*batch"]
    mu_t: Float[Array, "*batch"]


class FactorLaw(AbstractSummableLaw):
    r"""The seed's law: at an impact on a face of unit normal n the normal velocity is
    reversed and scaled by the coefficient of restitution e, the tangential velocity is
    scaled by mu_t,

        v+ = mu_t (v - (v . n) n) - e (v . n) n.                                   (1)

    Its bounce series on one face sum in closed form. After a bounce, split gravity ``a``
    and the velocity into normal and tangential parts (:class:`Series`): ``a_n = a . n < 0``,
    ``a_t = a - a_n n``, normal speed ``w > 0``, tangential velocity ``u``. Every flight
    leaves and returns to the face with the same normal speed, which the next bounce scales
    by e, so flight j lasts ``T_j = T0 e^j`` with ``T0 = 2 w / |a_n|``. The tangential
    velocity gains ``a_t T_j`` in flight j and is scaled by mu at the bounce that ends it:

        u_j = mu^j u + a_t T0 mu K_j,        K_j = sum_{k<j} mu^(j-1-k) e^k = (mu^j - e^j) / (mu - e).

    Summing the flights gives the start of flight j (time, tangential displacement):

        t_j = T0 (1 - e^j) / (1 - e),
        X_j = T0 (u G(e mu, j) + a_t T0 mu L_j) + a_t T0^2 G(e^2, j) / 2,
        L_j = sum_{i<j} e^i K_i = (G(e mu, j) - G(e^2, j)) / (mu - e),

    with ``G(q, j) = (1 - q^j) / (1 - q)`` (``geometric_sum``). On a horizontal face a_t = 0
    and bounce n of a series that starts at (t_0, x_0) happens at

        t_n = t_0 + T0 (1 - e^n) / (1 - e),   x_n = x_0 + u T0 (1 - (e mu)^n) / (1 - e mu):

    the seed's stairs. For e < 1 every sum converges as j -> inf: the series accumulates at
    ``T0 / (1 - e)`` (Zeno) with tangential velocity ``u_inf = u + a_t T0 / (1 - e)`` if
    mu = 1 and 0 otherwise.

    Where mu and e agree to within ``SERIES_GAP`` (1e-6) the divided differences K and L are
    evaluated with e moved by ``SERIES_GAP``, a relative error of that order in the (then
    tiny) gravity terms, instead of a division by zero.

    The native kernels (``estim/forward/_kernels.cc``) implement this law.
    """

    def coefficients(self, params: Params) -> FactorCoefficients:
        return FactorCoefficients(params.e, params.mu_t)

    def reset(self, v, n, c: FactorCoefficients):
        """Equation (1)."""
        vn = inner(v, n)
        return c.mu_t * (v - vn * n) - c.e * vn * n

    def rebound(self, v, n, c: FactorCoefficients):
        """``e (-v . n)``."""
        return c.e * -inner(v, n)

    def settle(self, tangential, c: FactorCoefficients):
        """Each of infinitely many vanishing bounces scales the tangential velocity by mu_t:
        it stays only if mu_t = 1."""
        return tangential * jnp.where(c.mu_t == 1.0, 1.0, 0.0)

    def flight_start(self, s: Series, j, c: FactorCoefficients):
        """``(t_j, X_j, u_j + w e^j n)`` of the class docstring, and the series' spin, which
        this law leaves as it is."""
        return (*_flight_start(s, j, c.e, c.mu_t), s.spin)

    def bounces_within(self, y, c: FactorCoefficients):
        """Flights last ``T0 e^j``: the largest n with ``G(e, n) <= y``."""
        return geometric_count(c.e, y)

    def landings_within(self, y, c: FactorCoefficients):
        """On a horizontal face flight j travels ``|u| T0 (e mu)^j``: the largest n with
        ``G(e mu, n) <= y``."""
        return geometric_count(c.e * c.mu_t, y)

    def flights_longer(self, period, shortest, c: FactorCoefficients):
        """Flight j lasts ``period e^j``: ``flights_at_least``."""
        return flights_at_least(c.e, period, shortest)

    def accumulates(self, c: FactorCoefficients):
        return c.e < 1


def _differences(e, mu, j):
    """K_j and L_j of ``FactorLaw``'s docstring (j may be inf)."""
    close = jnp.abs(mu - e) < SERIES_GAP
    e2 = jnp.where(close, jnp.where(e >= SERIES_GAP, e - SERIES_GAP, e + SERIES_GAP), e)
    gap = mu - e2
    k = (safe_power(mu, j) - safe_power(e2, j)) / gap
    l_ = (geometric_sum(e2 * mu, j) - geometric_sum(e2 * e2, j)) / gap
    return k, l_


@jax.jit  # traced once per signature, not at each call (estim._config, TRACING)
def _flight_start(s: Series, j, e, mu_t):
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
