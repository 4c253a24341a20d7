"""What a contact law is: the abstract bases every law implements.

A contact law says what happens to a ball's velocity when it touches a face. It is one
object, read from the scene (``estim.forward.laws.law_of``), and the only place that
knows the law: the closed-form planner (``estim.forward._solver``), the trajectory's
samples and events (``estim.forward._trajectory``), the ODE path (``estim.forward._ode``)
and the sensitivities ask the law, never its name, and the native kernels run only the
laws they support (``estim.forward._native.supports``). A new law is one new file with
one final class; nothing else changes.

Two kinds, as diffrax has solvers with and without an error estimate:

- :class:`AbstractContactLaw`: the reset at an impact (``reset``, with its normal speed
  ``rebound``) and the limit of a series of vanishing bounces (``settle``). Such a law
  runs bounce by bounce: every bounce
  is a segment of its own (compute bounded by ``max_segments``), and a ball comes to rest
  where its rebound falls below ``REST_SPEED``.
- :class:`AbstractSummableLaw`: a law whose bounce series on one face has a closed form
  (flight j's start, the counts of bounces within a time or a distance). The planner then
  sums a whole series in one segment, Zeno series included, and the ODE path closes Zeno
  series the same way.

Every method is a pure, differentiable function of JAX arrays: ``reset`` composes with
the implicit-function derivative of the event time into the event-time sensitivities,
and the series' closed forms are differentiated in the planner's replay. A law reads its
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
from jaxtyping import Array, Float, PyTree

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
    def summable(self) -> bool:
        """Whether the law's bounce series on one face have a closed form
        (:class:`AbstractSummableLaw`); if not, the planner goes bounce by bounce."""
        return isinstance(self, AbstractSummableLaw)


class Series(NamedTuple):
    """A bounce series on one face, as it starts after a bounce: the face's unit normal,
    gravity split into its normal part ``a_n = a . n < 0`` (pressing the ball onto the
    face) and tangential part ``a_t``, the post-bounce normal speed ``w > 0`` and
    tangential velocity ``u``, and the first flight's duration ``period = 2 w / |a_n|``.
    Between bounces every flight is a parabola, whatever the law."""

    normal: Float[Array, "3"]
    a_n: Float[Array, ""]
    a_t: Float[Array, "3"]
    w: Float[Array, ""]
    u: Float[Array, "3"]
    period: Float[Array, ""]


def series(v, normal, a) -> Series:
    """The series that starts with post-bounce velocity ``v`` on a face of normal ``normal``
    under gravity ``a``."""
    a_n = inner(a, normal)
    w = inner(v, normal)
    return Series(normal, a_n, a - a_n * normal, w, v - w * normal, 2.0 * w / -a_n)


class AbstractSummableLaw(AbstractContactLaw):
    """A contact law whose bounce series on one face sum in closed form.

    Implement ``flight_start`` (where flight j of a series begins), the three counts
    ``bounces_within``, ``landings_within`` and ``flights_longer``, and ``accumulates``;
    ``state_at``, ``series_end`` and ``bounce`` are built from them.

    The planner relies on two properties of a summable law on a face that supports the
    ball (checked for the factor law with 0 <= e, mu_t <= 1): no flight of a series is
    longer or higher than the first (its flights stay in the slab of the first apex), and
    on an upward face the landing points move monotonically along the first flight's
    direction (so the first and last landings bound them all).
    """

    @abc.abstractmethod
    def flight_start(self, s: Series, j: Float[Array, ""], c: PyTree):
        """``(t, x, v)``: time offset, displacement and velocity at the start of flight j,
        just after bounce j (j = 0: the series' start; j may be inf, the accumulation
        point of a series that accumulates). Differentiable in s and c."""

    @abc.abstractmethod
    def bounces_within(self, y: Float[Array, ""], c: PyTree) -> Float[Array, ""]:
        """The largest whole n >= 0 such that the first n flights of a series last at most
        ``y`` first flights in all (``y = duration / s.period``; inf if every n does).
        Not differentiated: a count."""

    @abc.abstractmethod
    def landings_within(self, y: Float[Array, ""], c: PyTree) -> Float[Array, ""]:
        """The largest whole n >= 0 such that, on a horizontal face, the first n flights
        travel at most ``y`` times the first flight's travel ``|u| period`` along the
        face (inf if every n does). Not differentiated."""

    @abc.abstractmethod
    def flights_longer(self, period: Float[Array, ""], shortest: float, c: PyTree) -> Float[Array, ""]:
        """How many flights of a series whose first flight lasts ``period`` last at least
        ``shortest`` (inf if all of them). Not differentiated: which bounces of a summed
        series are listed as events."""

    @abc.abstractmethod
    def accumulates(self, c: PyTree):
        """Whether a series on a face that supports the ball accumulates (infinitely many
        bounces in finite time, Zeno), e.g. e < 1."""

    def state_at(self, s: Series, tau, c: PyTree, n_max):
        """Displacement and velocity ``tau`` after the series began (at most n_max
        bounces): flight j's start, then its parabola."""
        j = self.bounces_within(tau / s.period, c)
        j = jnp.minimum(jnp.minimum(j, n_max), MAX_COUNT)  # n_max may be inf
        t_j, x_j, v_j = self.flight_start(s, j, c)
        tau_j = tau - t_j
        displacement = x_j + v_j * tau_j + 0.5 * (s.a_t + s.a_n * s.normal) * tau_j**2
        return displacement, v_j + (s.a_t + s.a_n * s.normal) * tau_j

    def series_end(self, s: Series, n, c: PyTree):
        """Duration, displacement and velocity after bounce n (n = inf: the Zeno limit,
        where the normal speed is 0)."""
        duration, displacement, velocity = self.flight_start(s, n, c)
        finite = jnp.isfinite(n)
        velocity = jnp.where(finite, velocity, velocity - inner(velocity, s.normal) * s.normal)
        return duration, displacement, velocity

    def bounce(self, s: Series, j, c: PyTree):
        """Bounce j (from 1): time offset, displacement, velocity before and after, and the
        start (time offset, displacement, velocity) of the flight that ends at it."""
        t, x, post = self.flight_start(s, j, c)
        t_s, x_s, v_s = self.flight_start(s, j - 1.0, c)
        tau = t - t_s
        pre = v_s + (s.a_t + s.a_n * s.normal) * tau
        return t, x, pre, post, (t_s, x_s, v_s)


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
