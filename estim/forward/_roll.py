"""A ball rolling over an edge or a corner, in closed form (the ``ROLL`` segment).

A ball pressed onto an edge (the quarter cylinder of radius r around the edge line,
``estim.model._scene``) more than its motion across the edge pulls it away, ``n . a +
|u|^2 / r < 0`` (u its velocity across the edge), stays on the edge: its centre moves on
the circle of radius r around the edge line (the *pivot* axis, horizontal) while its
motion along the axis goes on unchanged. Contact is frictionless between impacts (the
contact law acts at impacts only), so across the axis the centre is a point mass on a
circle under gravity: an inverted pendulum. With theta the angle of the centre from the
vertical above the axis, towards the outside of the edge, and k = g / r, energy gives

    theta'^2 = omega0^2 + 2 k (cos theta0 - cos theta) = B + 4 k s^2,
    s = sin(theta / 2),   B = omega0^2 - 4 k sin^2(theta0 / 2),                   (1)

and the surface pushes on the ball while k cos theta > theta'^2, that is until

    s*^2 = (k - B) / (6 k)                                                       (2)

(cos theta* = (omega0^2 + 2 k cos theta0) / (3 k), the classical particle leaving a
sphere or cylinder: for a ball at rest on the top, theta* = acos(2/3)). There it leaves
the edge tangentially, in flight. B > 0: the ball could pass over the top; moving outwards
it rolls down to s*, moving inwards it rolls back onto the face above the edge, where the
roll ends (the face continues it as a slide). B < 0: it turns at s_t^2 = -B / (4 k) and
rolls down to s*. B = 0 with s = 0 is a ball at rest on the ridge: it stays.

*Time.* From (1), dt = 2 ds / sqrt((1 - s^2) (B + 4 k s^2)), an elliptic integral of the
first kind. With beta = sqrt(|B|), b = beta / (2 sqrt k) and a hyperbolic angle w,

    B > 0:  s = sigma b sinh w,  theta' = sigma beta cosh w   (sigma: +1 outwards, -1 inwards),
    B < 0:  s = b cosh w,        theta' = beta sinh w,                                   (3)

both give dt / dw = 1 / (sqrt k sqrt(1 - s^2)), in [1, sqrt 2] / sqrt k on the quarter
cylinder: w runs with time, regular through the turning point (w = 0 for B < 0), and

    t(w) = sinh(w) R_F(1 - s^2, cosh^2 w, 1) / sqrt k                     (B > 0)
    t(w) = sinh(w) R_F(1 - s^2, 1 - b^2, (1 - b^2) cosh^2 w) / sqrt k     (B < 0)      (4)

with Carlson's symmetric integral R_F (Carlson 1995, Numer. Algorithms 10, 13-26; DLMF
19.16.1 and 19.7.7), from ``int_0^y dt / sqrt((1 - t^2)(1 - m t^2)) = y R_F(1 - y^2,
1 - m y^2, 1)`` with ``m = -4 k / B`` (B > 0) and, for B < 0, the substitution
``s = s_t / sqrt(1 - (1 - s_t^2) sin^2 phi)`` (Byrd and Friedman 1971, 217.00). (4) is
odd in w, smooth in the ball's state, and a segment lasts ``t(w_end) - t(w0)``.
The start angle needs no inverse function: (3) at the start gives

    B > 0:  (sinh w0, cosh w0) = (2 sqrt k sigma s0, |omega0|) / beta,
    B < 0:  (sinh w0, cosh w0) = (omega0, 2 sqrt k s0) / beta.                   (5)

A state at a time inside the roll is found by Newton's method on (4) in w (its
derivative is bounded below, so the iteration is safe), its derivatives by one more
differentiable Newton step at the solution (the implicit-function theorem). Where the ball
has just the energy to reach the top (B -> 0), w0 and w_end grow like log(1 / |B|) and
their times nearly cancel: values keep their accuracy to a few ulps, derivatives lose
about eps / |B| (B = 0 exactly is taken as B = ``RIDGE_B`` k).

A corner (a sphere of radius r around the vertex) gives the same motion where the ball
moves in the vertical plane through the vertex (no angular momentum about the vertical
through it): the pivot axis is then horizontal and perpendicular to that plane. Off that
plane the motion is a spherical pendulum, which estim does not follow: the planner stops
there and says so.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._fold import inner
from ._constants import RF_STEPS, RIDGE_B, ROLL_NEWTONS


def carlson_rf(x, y, z):
    """Carlson's symmetric elliptic integral of the first kind,
    ``R_F(x, y, z) = 1/2 int_0^inf dt / sqrt((t + x)(t + y)(t + z))``, for x, y, z >= 0,
    at most one zero (duplication, then the fifth-order series of Carlson 1995, eq. 2.2)."""

    def step(_, xyz):
        x, y, z = xyz
        sx, sy, sz = jnp.sqrt(x), jnp.sqrt(y), jnp.sqrt(z)
        lam = sx * (sy + sz) + sy * sz
        return 0.25 * (x + lam), 0.25 * (y + lam), 0.25 * (z + lam)

    x, y, z = jax.lax.fori_loop(0, RF_STEPS, step, (x, y, z), unroll=True)
    mean = (x + y + z) / 3.0
    dx, dy = 1.0 - x / mean, 1.0 - y / mean
    dz = -(dx + dy)
    e2 = dx * dy - dz * dz
    e3 = dx * dy * dz
    return (1.0 + e2 * (e2 / 24.0 - 0.1 - 3.0 * e3 / 44.0) + e3 / 14.0) / jnp.sqrt(mean)


class Pendulum:
    """The motion across the pivot axis of one roll, from its start (equations (1)-(5)).

    Built from the angle's half-sine ``s0`` at the start, its rate ``omega0`` and
    ``k = g / r``; everything is elementwise and branch-free (both signs of B are computed
    and selected with guards, so that neither produces NaN in values or derivatives)."""

    def __init__(self, s0, omega0, k):
        self.k, self.sqrt_k = k, jnp.sqrt(k)
        B = omega0 * omega0 - 4.0 * k * s0 * s0
        # At rest on the ridge B = 0: s stays 0 for ever. Moving off it with B = 0 exactly
        # (rounding) is taken as B a hair above 0 (the time depends on B like B log B).
        self.rests = (B == 0.0) & (s0 == 0.0)
        B = jnp.where(B == 0.0, RIDGE_B * k, B)
        self.positive = B > 0
        self.beta = jnp.sqrt(jnp.abs(B))
        self.b = self.beta / (2.0 * self.sqrt_k)
        self.sigma = jnp.where(omega0 < 0, -1.0, 1.0)
        sinh0 = jnp.where(self.positive, 2.0 * self.sqrt_k * self.sigma * s0, omega0) / self.beta
        self.w0 = jnp.arcsinh(sinh0)
        self.t0 = self._time(self.w0)
        s_star = jnp.sqrt(jnp.maximum((k - B) / (6.0 * k), 0.0))
        # Where the roll ends: where the ball leaves the edge (2), or back on top (w = 0)
        # for a ball rolling inwards that passes the top.
        inwards = self.positive & (self.sigma < 0)
        ratio = s_star / self.b
        w_star = jnp.where(self.positive, jnp.arcsinh(ratio), jnp.arccosh(jnp.maximum(ratio, 1.0)))
        self.w_end = jnp.maximum(jnp.where(inwards, 0.0, w_star), self.w0)
        self.reaches_top = inwards
        self.duration = jnp.where(self.rests, jnp.inf, self._time(self.w_end) - self.t0)

    def half_sine(self, w):
        """s = sin(theta / 2) at hyperbolic angle w, equation (3)."""
        return jnp.where(self.positive, self.sigma * self.b * jnp.sinh(w), self.b * jnp.cosh(w))

    def rate(self, w):
        """theta' at hyperbolic angle w, equation (3)."""
        return jnp.where(self.positive, self.sigma * self.beta * jnp.cosh(w), self.beta * jnp.sinh(w))

    def _time(self, w):
        """t(w) of equation (4)."""
        s = self.half_sine(w)
        c2 = jnp.cosh(w) ** 2
        one_b2 = 1.0 - self.b * self.b
        y = jnp.where(self.positive, c2, jnp.maximum(one_b2, 0.0))
        z = jnp.where(self.positive, 1.0, one_b2 * c2)
        return jnp.sinh(w) * carlson_rf(1.0 - s * s, y, z) / self.sqrt_k

    def angle_at(self, tau):
        """Hyperbolic angle w at time tau after the start (0 <= tau <= duration)."""
        target = self.t0 + tau

        def residual(w):
            s = self.half_sine(w)
            return self._time(w) - target, self.sqrt_k * jnp.sqrt(1.0 - s * s)  # (t(w) - target, dw/dt)

        lo, hi = jax.lax.stop_gradient((self.w0, self.w_end))

        def newton(_, w):
            f, slope = jax.lax.stop_gradient(residual(w))
            return jnp.clip(w - f * slope, lo, hi)

        w = jax.lax.fori_loop(0, ROLL_NEWTONS, newton, jax.lax.stop_gradient(self.w0 + self.sqrt_k * tau))
        f, slope = residual(w)  # (differentiable: the implicit-function step)
        return w - f * slope


class Roll:
    """One roll about the horizontal line through ``pivot`` along ``axis`` (unit, with
    ``up x axis`` pointing away from the solid: theta grows that way) of a ball that starts
    it at p0 with velocity v0, under gravity g: across the axis the pendulum of equations
    (1)-(5), along it uniform motion."""

    def __init__(self, pivot, axis, p0, v0, g):
        up = jnp.array([0.0, 0.0, 1.0])
        d = p0 - pivot
        self.pivot, self.axis = pivot, axis
        self.along, self.u = inner(d, axis), inner(v0, axis)
        arm = d - self.along * axis
        self.r = jnp.sqrt(inner(arm, arm))
        self.out = jnp.cross(up, axis)  # (horizontal, away from the solid)
        theta = jnp.arctan2(inner(arm, self.out), arm[2])
        omega = inner(v0, jnp.cos(theta) * self.out - jnp.sin(theta) * up) / self.r
        self.motion = Pendulum(jnp.sin(0.5 * theta), omega, g / self.r)

    @property
    def duration(self):
        """Time to the roll's end: where the ball leaves the edge or is back on top of it
        (inf for a ball at rest on the ridge)."""
        return self.motion.duration

    @property
    def reaches_top(self):
        """Whether the roll ends back on top of the edge (else the ball leaves it)."""
        return self.motion.reaches_top

    def state(self, tau):
        """Position and velocity ``tau`` after the start (to the roll's end, then held)."""
        motion = self.motion
        end = jnp.where(jnp.isfinite(motion.duration), motion.duration, tau)
        w = motion.angle_at(jnp.where(motion.rests, 0.0, jnp.clip(tau, 0.0, end)))
        s = jnp.where(motion.rests, 0.0, motion.half_sine(w))
        rate = jnp.where(motion.rests, 0.0, motion.rate(w))
        cos_t = 1.0 - 2.0 * s * s
        sin_t = 2.0 * s * jnp.sqrt(jnp.maximum(1.0 - s * s, 0.0))
        up = jnp.array([0.0, 0.0, 1.0])
        base = self.pivot + (self.along + self.u * tau) * self.axis
        p = base + self.r * (sin_t * self.out + cos_t * up)
        v = self.u * self.axis + self.r * rate * (cos_t * self.out - sin_t * up)
        return p, v
