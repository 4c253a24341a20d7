"""What a contact law is: the abstract bases every law implements.

A contact law says what happens to a ball's velocity when it touches a face. It is one
object, read from the scene (``estim.forward.laws.law_of``), and the only place that
knows the law: the closed-form planner (``estim.forward._solver``), the trajectory's
samples and events (``estim.forward._trajectory``), the ODE path (``estim.forward._ode``)
and the sensitivities ask the law, never its name, and the native kernels run only the
laws they support (``estim.forward._native.supports``). A new law is one new file with
one final class; nothing else changes.

Three kinds, as diffrax has solvers with and without an error estimate:

- :class:`AbstractContactLaw`: the reset at an impact (``reset``, with its normal speed
  ``rebound``) and the limit of a series of vanishing bounces (``settle``). Such a law
  runs bounce by bounce: every bounce is a segment (a step on the ODE path) of its own
  (compute bounded by ``max_segments``), and a ball comes to rest where its rebound falls
  below ``REST_SPEED``.
- :class:`AbstractSeriesLaw`: a law whose bounce series on one horizontal face have a
  closed form (flight j's start, spin included, and the counts of bounces within a time).
  The ODE path then closes a Zeno series in one step (``estim.forward._ode``).
- :class:`AbstractSummableLaw`: a series law whose landings also move along one line (the
  count of bounces within a distance). The closed-form planner then sums a whole series in
  one segment, Zeno series included.

Every method is a pure, differentiable function of JAX arrays: ``reset`` composes with
the implicit-function derivative of the event time into the event-time sensitivities,
and the series' closed forms are differentiated in the replays. A law reads its
numbers from the ball's :class:`estim.Params` once (``coefficients``), and every other
method takes that pytree ``c``: the dense solution keeps it per ball
(``Trajectory.solution.coefficients``). A law's own fields are static settings (a law is
a static field of the scene, so it must be hashable: numbers and tuples, not arrays).

Spin. A law that couples spin and velocity (``couples_spin``, e.g.
:class:`estim.forward.laws.FrictionLaw`) implements ``impact``, the pair (velocity, spin)
after an impact, and ``settle_spin``; every other law leaves the spin as it is (the
defaults below). The spin is carried from contact to contact on the ODE path
(``estim.forward._ode``), which ``estim.simulate`` takes for a law that couples spin.
"""

from __future__ import annotations

import abc
import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PyTree

from ...model._params import Params
from .._constants import MAX_COUNT, REST_SPEED
from .._contact import inner


class AbstractContactLaw(eqx.Module):
    """A contact law: the velocity after a ball touches a face.

    Implement ``coefficients``, ``reset``, ``rebound`` and ``settle``; ``contact_velocity``
    is built from them. Subclass :class:`AbstractSummableLaw` instead when the law's bounce
    series on one face have a closed form.
    """

    @abc.abstractmethod
    def coefficients(self, params: Params) -> PyTree[Float[Array, "*batch"]]:
        """The numbers this law reads from the parameters (e.g. e and mu_t), as a pytree
        of arrays with the parameters' batch axes. Every other method takes it as ``c``."""

    @abc.abstractmethod
    def reset(self, v: Float[Array, "3"], n: Float[Array, "3"], c: PyTree) -> Float[Array, "3"]:
        """Post-impact velocity of a ball that hits a face of unit outward normal n with
        velocity v (``v . n < 0``). Differentiable in v, n and c."""

    @abc.abstractmethod
    def rebound(self, v: Float[Array, "3"], n: Float[Array, "3"], c: PyTree) -> Float[Array, ""]:
        """The normal speed after an impact at v on a face of normal n, ``reset(v, n, c) . n``
        (>= 0), written out: it decides whether the ball comes to rest
        (``contact_velocity``), and a law writes it in its own terms (``e (-v . n)``)
        rather than as the product with n, which rounds differently on inclined faces."""

    @abc.abstractmethod
    def settle(self, tangential: Float[Array, "3"], c: PyTree) -> Float[Array, "3"]:
        """Velocity of a ball whose bounces on a face that supports it have died out, from
        its tangential velocity at the last impact: the limit of infinitely many vanishing
        bounces (``contact_velocity``)."""

    def reads(self) -> frozenset[str]:
        """The :class:`estim.Params` fields ``coefficients`` reads (``{"e", "mu_t"}`` for
        the factor law): read off the traced program of ``coefficients``, so it cannot
        disagree with it. A fit estimates only the law's coefficients a scene's law reads
        (``estim.fitting._registry.acts``). Traced once per law (a fit asks for every
        parameter of every ball it reports)."""
        return _reads(self)

    @property
    def couples_spin(self) -> bool:
        """Whether an impact changes the spin or depends on it (``impact``)."""
        return False

    def impact(self, v: Float[Array, "3"], w: Float[Array, "3"], n: Float[Array, "3"],
               c: PyTree) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
        """Velocity and spin (angular velocity) after an impact at velocity v and spin w on
        a face of unit outward normal n: ``reset``, the spin unchanged, unless the law
        couples spin."""
        return self.reset(v, n, c), w

    def settle_spin(self, tangential: Float[Array, "3"], w: Float[Array, "3"], n: Float[Array, "3"],
                    c: PyTree) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
        """``settle`` with the spin: velocity and spin of a ball whose bounces on a face of
        normal n have died out (the spin unchanged, unless the law couples spin)."""
        return self.settle(tangential, c), w

    def contact_velocity(self, v: Float[Array, "3"], n: Float[Array, "3"], a: Float[Array, "3"],
                         c: PyTree) -> Float[Array, "3"]:
        """``contact_state``'s velocity, of a ball without spin."""
        return self.contact_state(v, jnp.zeros_like(v), n, a, c)[0]

    def contact_state(self, v: Float[Array, "3"], w: Float[Array, "3"], n: Float[Array, "3"],
                      a: Float[Array, "3"], c: PyTree) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
        """Velocity and spin after touching a face of normal n under acceleration a.

        Touching with a normal speed below ``REST_SPEED`` is not an impact: the normal
        component is dropped and nothing else changes. An impact whose ``rebound`` is below
        ``REST_SPEED`` on a face that supports the ball (``n . a < 0``) ends a bounce
        series: it stands for the limit of infinitely many vanishing bounces, ``settle``
        (for the factor law the ball keeps its tangential velocity only if mu_t = 1, which
        makes e = 0 the limit of e -> 0: the ball sticks where it lands).
        """
        vn = inner(v, n)
        tangential = v - vn * n
        impact = -vn > REST_SPEED
        bounced = self.impact(v, w, n, c)
        settles = (self.rebound(v, n, c) <= REST_SPEED) & (inner(n, a) < 0)
        settled = self.settle_spin(tangential, w, n, c)
        return tuple(jnp.where(impact, jnp.where(settles, s, b), o)
                     for s, b, o in zip(settled, bounced, (tangential, w), strict=True))

    @property
    def closes_series(self) -> bool:
        """Whether the law's bounce series on one face have a closed form in time
        (:class:`AbstractSeriesLaw`); if not, the ODE path goes bounce by bounce."""
        return isinstance(self, AbstractSeriesLaw)

    @property
    def summable(self) -> bool:
        """Whether the closed-form planner sums the law's bounce series
        (:class:`AbstractSummableLaw`); if not, it goes bounce by bounce."""
        return isinstance(self, AbstractSummableLaw)


class Series(NamedTuple):
    """A bounce series on one face, as it starts after a bounce: the face's unit normal,
    gravity split into its normal part ``a_n = a . n < 0`` (pressing the ball onto the
    face) and tangential part ``a_t``, the post-bounce normal speed ``w > 0`` and
    tangential velocity ``u``, the first flight's duration ``period = 2 w / |a_n|``, and
    the ball's spin. Between bounces every flight is a parabola, whatever the law."""

    normal: Float[Array, "3"]
    a_n: Float[Array, ""]
    a_t: Float[Array, "3"]
    w: Float[Array, ""]
    u: Float[Array, "3"]
    period: Float[Array, ""]
    spin: Float[Array, "3"]


def series(v, normal, a, spin=None) -> Series:
    """The series that starts with post-bounce velocity ``v`` and spin ``spin`` (none: 0)
    on a face of normal ``normal`` under gravity ``a``."""
    a_n = inner(a, normal)
    w = inner(v, normal)
    spin = jnp.zeros_like(v) if spin is None else spin
    return Series(normal, a_n, a - a_n * normal, w, v - w * normal, 2.0 * w / -a_n, spin)


class AbstractSeriesLaw(AbstractContactLaw):
    """A contact law whose bounce series on one horizontal face have a closed form.

    Implement ``flight_start`` (where flight j of a series begins, spin included), the
    counts ``bounces_within`` and ``flights_longer``, and ``accumulates``; a law whose
    series close only in some cases also ``sums``. ``flight_state``, ``state_at``,
    ``series_end`` and ``bounce`` are built from them.

    The ODE path (``estim.forward._ode``) relies on two properties of such a law on a
    horizontal face that supports the ball: no flight of a series is longer or higher than
    the first, and the tangential velocity moves monotonically along one segment from the
    first flight's to that of the series' limit (``flight_start`` at j = inf, taken where the
    series does not accumulate too), so that up to any flight the landings lie in the
    triangle of the first flight's velocity and that flight's, which it can check.
    """

    @abc.abstractmethod
    def flight_start(self, s: Series, j: Float[Array, ""], c: PyTree):
        """``(t, x, v, w)``: time offset, displacement, velocity and spin at the start of
        flight j, just after bounce j (j = 0: the series' start; j may be inf, the
        accumulation point of a series that accumulates). Differentiable in s and c."""

    def sums(self, s: Series, c: PyTree) -> Bool[Array, ""]:
        """Whether this series has the closed form (every series, unless the law says
        otherwise)."""
        return jnp.bool_(True)

    @abc.abstractmethod
    def bounces_within(self, y: Float[Array, ""], c: PyTree) -> Float[Array, ""]:
        """The largest whole n >= 0 such that the first n flights of a series last at most
        ``y`` first flights in all (``y = duration / s.period``; inf if every n does).
        Not differentiated: a count."""

    @abc.abstractmethod
    def flights_longer(self, period: Float[Array, ""], shortest: float, c: PyTree) -> Float[Array, ""]:
        """How many flights of a series whose first flight lasts ``period`` last at least
        ``shortest`` (inf if all of them). Not differentiated: which bounces of a summed
        series are listed as events."""

    @abc.abstractmethod
    def accumulates(self, c: PyTree):
        """Whether a series on a face that supports the ball accumulates (infinitely many
        bounces in finite time, Zeno), e.g. e < 1."""

    def flight_state(self, s: Series, j, tau, c: PyTree):
        """Time offset, displacement, velocity and spin of the series at time ``tau`` after
        it began, in flight j: flight j's start, then its parabola (``tau`` None: at the
        flight's start; j = inf: the Zeno limit, whose normal speed is 0)."""
        t_j, x_j, v_j, w_j = self.flight_start(s, j, c)
        if tau is None:
            t, displacement, velocity = t_j, x_j, v_j
        else:
            a = s.a_t + s.a_n * s.normal
            dt = jnp.where(jnp.isfinite(j), tau - t_j, 0.0)
            t, displacement, velocity = t_j + dt, x_j + v_j * dt + 0.5 * a * dt**2, v_j + a * dt
        velocity = jnp.where(jnp.isfinite(j), velocity, velocity - inner(velocity, s.normal) * s.normal)
        return t, displacement, velocity, w_j

    def state_at(self, s: Series, tau, c: PyTree, n_max):
        """Displacement, velocity and spin ``tau`` after the series began (at most n_max
        bounces)."""
        j = self.bounces_within(tau / s.period, c)
        j = jnp.minimum(jnp.minimum(j, n_max), MAX_COUNT)  # n_max may be inf
        return self.flight_state(s, j, tau, c)[1:]

    def series_end(self, s: Series, n, c: PyTree):
        """Duration, displacement, velocity and spin after bounce n (n = inf: the Zeno
        limit, where the normal speed is 0)."""
        return self.flight_state(s, n, None, c)

    def bounce(self, s: Series, j, c: PyTree):
        """Bounce j (from 1): time offset, displacement, velocity before and after, spin
        before and after, and the start (time offset, displacement, velocity) of the flight
        that ends at it."""
        t, x, post, w_post = self.flight_start(s, j, c)
        t_s, x_s, v_s, w_pre = self.flight_start(s, j - 1.0, c)
        tau = t - t_s
        pre = v_s + (s.a_t + s.a_n * s.normal) * tau
        return t, x, pre, post, w_pre, w_post, (t_s, x_s, v_s)


class AbstractSummableLaw(AbstractSeriesLaw):
    """A series law whose landings on a face move along one line: the closed-form planner
    (``estim.forward._solver``) sums its series.

    Implement, besides :class:`AbstractSeriesLaw`'s methods, ``landings_within``.

    The planner relies on two properties of a summable law on a face that supports the
    ball (checked for the factor law with 0 <= e, mu_t <= 1): no flight of a series is
    longer or higher than the first (its flights stay in the slab of the first apex), and
    on an upward face the landing points move monotonically along the first flight's
    direction (so the first and last landings bound them all).
    """

    @abc.abstractmethod
    def landings_within(self, y: Float[Array, ""], c: PyTree) -> Float[Array, ""]:
        """The largest whole n >= 0 such that, on a horizontal face, the first n flights
        travel at most ``y`` times the first flight's travel ``|u| period`` along the
        face (inf if every n does). Not differentiated."""


@functools.cache
def _reads(law: AbstractContactLaw) -> frozenset[str]:
    """``law.reads()``, traced once per law (laws are field-free modules, so equal and
    hashable)."""
    probe = Params(0.5, 0.5, 1.0, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), mass=1.0)
    leaves, structure = jax.tree_util.tree_flatten_with_path(probe)
    closed = jax.make_jaxpr(lambda *x: law.coefficients(jax.tree.unflatten(structure, x)))(
        *(leaf for _, leaf in leaves))
    used = {id(v) for eqn in closed.jaxpr.eqns for v in eqn.invars}
    used |= {id(v) for v in closed.jaxpr.outvars}
    return frozenset(path[0].name for (path, _), var in zip(leaves, closed.jaxpr.invars, strict=True)
                     if id(var) in used)
