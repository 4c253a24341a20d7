"""A bounce that depends on spin: Coulomb friction at the contact point, sliding or gripping."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ...model._params import Params
from .._contact import inner
from ._base import AbstractSeriesLaw, Series
from ._geometric import flights_at_least, geometric_count, geometric_sum, safe_power

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


class FrictionLaw(AbstractSeriesLaw):
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

    *Bounce series* (``AbstractSeriesLaw``). On a horizontal face (no tangential gravity)
    with one e (``e_slope`` = 0) a series has a closed form. After a bounce the normal speed
    is w > 0 and flight j lasts ``T0 e^j`` (``T0 = 2 w / g``), as under the factor law. In
    flight neither the tangential velocity nor the spin changes, so neither does the slip
    s; bounce k (k >= 1), whose normal speed is ``w e^(k-1)``, reduces |s| along its own
    direction by ``(1 + 1/alpha) mu (1 + e) w e^(k-1) = C e^(k-1)`` while that is less than
    |s| (it slides) and stops it otherwise (it grips; the ball leaves rolling, and every
    later impact has zero slip and no tangential impulse: it rolls on). With ``sigma =
    |s|`` and ``G(e, k) = (1 - e^k) / (1 - e)``, the bounces 1..m slide, where m is the
    largest whole number with ``C G(e, m) <= sigma``, and bounce m + 1 grips (the slip
    decays geometrically: ``sigma - C G(e, k)``). After bounce j the slip has fallen by

        D_j = min(C G(e, j), sigma) s / sigma                                          (2)

    (D_j = s once gripped), and by (1) the velocity and spin have moved with it:

        u_j = u - alpha / (1 + alpha) D_j,      w_j = w + n x D_j / ((1 + alpha) r).

    Flight i travels ``T0 e^i u_i``; with ``q = min(j, m + 1)`` (the flights before the
    grip) and ``sum_{i<q} e^i G(e, i) = e G(e, q) G(e, q - 1) / (1 + e)`` (from
    ``G(e^2, q) = G(e, q) (1 + e^q) / (1 + e)``), flight j starts at

        t_j = T0 G(e, j),
        X_j = T0 [u G(e, j) - alpha / (1 + alpha) (C e G(e, q) G(e, q - 1) / (1 + e) s / sigma
                                                    + (G(e, j) - G(e, q)) s)].

    For e < 1 the series accumulates at ``T0 / (1 - e)``; its limit (j = inf) is the
    ball rolling as ``settle_spin`` leaves it, ``D_inf = s`` (for mu > 0), whether or not
    the bounces gripped first (a ball still sliding when its bounces die out is stopped by
    friction in the contact that follows, ``settle_spin``). Every u_j lies on the segment
    from u to ``u_inf``, as ``AbstractSeriesLaw`` requires. On an inclined face, or with
    ``e_slope`` != 0, the flights change the slip or the ratio of successive flights is not
    e: such a series goes bounce by bounce (``sums``). So does every series in air, where the
    ODE path sums only the factor law's (``estim.forward._ode._sums_series``).

    This law changes the spin, so it runs where the spin is carried from contact to contact:
    on the ODE path (``estim.forward._ode``), which ``estim.simulate`` takes for it. Its
    landings do not move along one line (the slip turns the velocity), so it is not an
    ``AbstractSummableLaw``: the closed-form planner does not sum its series.
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

    def sums(self, s: Series, c: FrictionCoefficients):
        """A series on a horizontal face (``a_t = 0``) with one e (``e_slope = 0``)."""
        return (inner(s.a_t, s.a_t) == 0.0) & (c.e_slope == 0.0)

    def flight_start(self, s: Series, j, c: FrictionCoefficients):
        """``(t_j, X_j, u_j + w e^j n, w_j)`` of the class docstring."""
        e, n = c.e, s.normal
        slip = s.u - c.radius * jnp.cross(s.spin, n)
        s2 = inner(slip, slip)
        sigma = jnp.sqrt(jnp.where(s2 > 0, s2, 1.0))  # (double where: finite derivative at 0 slip)
        unit = jnp.where(s2 > 0, slip / sigma, 0.0)
        big_c = (1.0 + 1.0 / c.inertia) * c.mu * (1.0 + e) * s.w
        # m, the last bounce that slides (inf: every bounce, mu = 0 included; 0 at zero slip).
        y = jnp.where(s2 > 0, jnp.where(big_c > 0, sigma / jnp.where(big_c > 0, big_c, 1.0), jnp.inf), 0.0)
        m = geometric_count(e, jax.lax.stop_gradient(y))
        g_j = geometric_sum(e, j)
        t = s.period * g_j
        finite = jnp.isfinite(t)  # false only for e = 1, j = inf: never reached
        g_j = jnp.where(finite, g_j, 0.0)
        limit = jnp.isinf(j)
        # (2): the slip's fall; in the limit the ball rolls (settle_spin).
        reduction = jnp.where(limit, jnp.where(c.mu > 0, slip, 0.0), jnp.where(j <= m, big_c * g_j * unit, slip))
        q = jnp.where(finite, jnp.minimum(j, m + 1.0), 0.0)  # the flights before the grip
        g_q = geometric_sum(e, q)
        sliding = big_c * e * g_q * geometric_sum(e, jnp.maximum(q - 1.0, 0.0)) / (1.0 + e) * unit
        # (G(e, j) - G(e, q) is 0 where q = j, inf - inf for an endless slide at j = inf.)
        gripped = jnp.where(q < j, g_j - g_q, 0.0) * slip
        beta = c.inertia / (1.0 + c.inertia)
        displacement = s.period * (s.u * g_j - beta * (sliding + gripped))
        velocity = s.u - beta * reduction + s.w * safe_power(e, j) * n
        spin = s.spin + jnp.cross(n, reduction) / ((1.0 + c.inertia) * c.radius)
        return t, displacement, velocity, spin

    def bounces_within(self, y, c: FrictionCoefficients):
        """Flights last ``T0 e^j``: the largest n with ``G(e, n) <= y``."""
        return geometric_count(c.e, y)

    def flights_longer(self, period, shortest, c: FrictionCoefficients):
        """Flight j lasts ``period e^j``: ``flights_at_least``."""
        return flights_at_least(c.e, period, shortest)

    def accumulates(self, c: FrictionCoefficients):
        return c.e < 1
