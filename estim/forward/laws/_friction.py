"""A bounce that depends on spin: Coulomb friction at the contact point, sliding or gripping."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ...model._params import Params
from .._contact import inner
from ._base import AbstractContactLaw

# The impact speed at which ``e`` is the restitution when it depends on the speed (m/s):
# that of the ITTF's drop test (rule 2.1.3: dropped from 30.5 cm, sqrt(2 g 0.305)), so that
# e keeps the meaning the rules and the table-tennis scene's prior give it.
E_REFERENCE_SPEED = 2.446


class FrictionCoefficients(eqx.Module):
    """The friction law's numbers, per ball: restitution e in [0, 1] (at the impact speed
    ``E_REFERENCE_SPEED``), its slope with the impact speed ``e_slope`` (s/m), Coulomb
    friction coefficient mu >= 0, radius r (m) and inertia ratio ``alpha = I / (m r^2)``
    (2/5 for a solid sphere, 2/3 for a thin shell; ``estim.Params``)."""

    e: Float[Array, "*batch"]
    mu: Float[Array, "*batch"]
    radius: Float[Array, "*batch"]
    inertia: Float[Array, "*batch"]
    e_slope: Float[Array, "*batch"]

    def restitution(self, vn: Float[Array, ""]) -> Float[Array, ""]:
        """e at an impact of normal velocity ``vn`` (< 0): ``e + e_slope (|vn| - v_ref)``,
        kept in [0, 1]."""
        return jnp.clip(self.e + self.e_slope * (-vn - E_REFERENCE_SPEED), 0.0, 1.0)


class FrictionLaw(AbstractContactLaw):
    r"""A ball of radius r, mass m and moment of inertia ``I = alpha m r^2`` hits a rigid face
    of unit outward normal n with velocity v and spin (angular velocity) w. The face acts
    through one impulse ``J = J_n n + J_t`` at the contact point, ``-r n`` from the centre;
    Coulomb's law bounds the tangential part, ``|J_t| <= mu J_n``. This is the impact model
    of Garwin (1969, Am. J. Phys. 37, 88) without tangential compliance, as Nakashima et al.
    (2010, J. Syst. Des. Dyn. 4, 545) use it for table-tennis bounces, and as Cross (2005,
    Am. J. Phys. 73, 914) discusses against measurements.

    *Normal.* Restitution e on the normal speed: ``v_n+ = -e v_n``, so ``J_n = m (1 + e)
    (-v . n)``. Real balls' e falls as impacts get faster (the viscoelastic theory of
    Ramirez et al. 1999, Phys. Rev. E 60, 4465, gives ``1 - e ~ v^(1/5)`` at low
    dissipation; measured table-tennis bounces fall by a few hundredths per m/s). Over the
    few m/s of a sport's bounces the law takes that fall as linear in the normal impact
    speed, ``e(v) = e + e_slope (|v_n| - v_ref)``, kept in [0, 1], with ``v_ref`` =
    ``E_REFERENCE_SPEED`` (2.446 m/s, the ITTF drop test's), so that ``e`` is the
    restitution that test measures; ``e_slope`` (s/m, ``estim.Params``) is 0 by default
    (one e at every speed) and fittable (``--also e_slope``). Everything below takes e at
    the impact's own speed.

    *Tangential.* The contact point slips with ``s = v_t - r w x n`` (``v_t = v - (v . n)
    n``). A tangential impulse J_t at the contact point changes the velocity by ``J_t / m``
    and the spin by the torque ``(-r n) x J_t`` over I, so the slip changes by

        ds = J_t / m - r (-r n x J_t / I) x n = (1 + 1 / alpha) J_t / m

    (J_t is tangential: ``(n x J_t) x n = J_t``): an impulse against the slip reduces it
    along its own direction. The slip stops (the ball grips and leaves rolling,
    ``v_t+ = r w+ x n``) if the impulse that stops it, ``m alpha |s| / (1 + alpha)``, is
    within Coulomb's bound; else the ball slides through the whole impact at ``mu J_n``:

        J_t = -m k s,      k = min(mu (1 + e) (-v . n) / |s|,  alpha / (1 + alpha)),    (1)
        v+ = v_t - k s - e (v . n) n,      w+ = w + k (n x s) / (alpha r).

    k is written so that it is regular at zero slip (``mu J_n / |s|`` is then infinite and
    the min takes the rolling branch, whose impulse is 0): values and derivatives are finite
    on both sides of the slide/grip switch and at s = 0.

    Properties (tested): with mu = 0 the tangential velocity and the spin are unchanged; a
    ball that arrives rolling leaves rolling; angular momentum about the contact point,
    ``I w + m (r n) x v``, is unchanged by every impact (the impulse acts at that point); the
    kinetic energy ``m |v|^2 / 2 + I |w|^2 / 2`` never rises for e <= 1.

    *Vanishing bounces.* A series of bounces that dies out on a face leaves the ball rolling
    with the tangential angular momentum about the contact point it had (friction stops the
    slip, whatever mu > 0): ``v = (v_t + alpha r w x n) / (1 + alpha)`` (``settle_spin``; for
    mu = 0 nothing changes).

    This law changes the spin, so it runs where the spin is carried from contact to contact:
    on the ODE path (``estim.forward._ode``), which ``estim.simulate`` takes for it.
    """

    @property
    def couples_spin(self) -> bool:
        return True

    def coefficients(self, params: Params) -> FrictionCoefficients:
        """The contact point is the contact radius ``rho = radius - compression`` from the
        centre (``estim.Params.contact_radius``), so rho is the lever arm of the impulse,
        and the law's inertia ratio is taken about it: ``I / (m rho^2) = alpha (r / rho)^2``
        with ``I = alpha m r^2`` the ball's (every formula above holds with r -> rho, alpha ->
        alpha (r / rho)^2; for a rigid ball, rho = r)."""
        rho = params.contact_radius
        ratio = params.radius / rho
        return FrictionCoefficients(params.e, params.mu, rho, params.inertia * ratio * ratio, params.e_slope)

    def impact(self, v, w, n, c: FrictionCoefficients):
        """Equation (1): ``(v+, w+)``."""
        vn = inner(v, n)
        slip = v - vn * n - c.radius * jnp.cross(w, n)
        s2 = inner(slip, slip)
        s_abs = jnp.sqrt(jnp.where(s2 > 0, s2, 1.0))  # (double where: finite derivative at 0 slip)
        e = c.restitution(vn)
        grip = c.inertia / (1.0 + c.inertia)
        sliding = c.mu * (1.0 + e) * -vn
        k = jnp.where(sliding < grip * s_abs, sliding / s_abs, grip)
        v_plus = v - vn * n - k * slip - e * vn * n
        w_plus = w + k * jnp.cross(n, slip) / (c.inertia * c.radius)
        return v_plus, w_plus

    def reset(self, v, n, c: FrictionCoefficients):
        """The impact of a ball without spin (``impact`` with w = 0)."""
        return self.impact(v, jnp.zeros_like(v), n, c)[0]

    def rebound(self, v, n, c: FrictionCoefficients):
        """``e (-v . n)``, e at the impact's speed."""
        vn = inner(v, n)
        return c.restitution(vn) * -vn

    def settle(self, tangential, c: FrictionCoefficients):
        """A ball without spin: it rolls on at ``v_t / (1 + alpha)`` (``settle_spin`` with
        w = 0)."""
        return jnp.where(c.mu > 0, tangential / (1.0 + c.inertia), tangential)

    def settle_spin(self, tangential, w, n, c: FrictionCoefficients):
        """Rolling with the angular momentum about the contact point: ``v = (v_t + alpha r
        w x n) / (1 + alpha)``, ``w`` its rolling spin ``n x v / r`` plus the spin about n,
        which friction at a point does not change (for mu = 0 nothing changes)."""
        rolling_v = (tangential + c.inertia * c.radius * jnp.cross(w, n)) / (1.0 + c.inertia)
        rolling_w = jnp.cross(n, rolling_v) / c.radius + inner(w, n) * n
        grips = c.mu > 0
        return jnp.where(grips, rolling_v, tangential), jnp.where(grips, rolling_w, w)
