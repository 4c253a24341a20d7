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
plane the motion is the spherical pendulum, equations (6)-(8) of ``Spherical``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._fold import inner
from ._constants import RF_STEPS, RIDGE_B, ROLL_NEWTONS, SPHERE_STEPS


def carlson_rf(x, y, z):
    """Carlson's symmetric elliptic integral of the first kind,
    ``R_F(x, y, z) = 1/2 int_0^inf dt / sqrt((t + x)(t + y)(t + z))``, for x, y, z >= 0,
    at most one zero (duplication, then the fifth-order series of Carlson 1995, eq. 2.2)."""

    def step(_, xyz):
        x, y, z = xyz
        sx, sy, sz = jnp.sqrt(x), jnp.sqrt(y), jnp.sqrt(z)
        lam = sx * (sy + sz) + sy * sz
        return 0.25 * (x + lam), 0.25 * (y + lam), 0.25 * (z + lam)

    x, y, z = jax.lax.fori_loop(0, RF_STEPS, step, (x, y, z))
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


def carlson_rc(x, y):
    """Carlson's degenerate integral ``R_C(x, y) = R_F(x, y, y)``, for x >= 0, y > 0
    (duplication, then the series of Carlson 1995, eq. 2.49)."""

    def step(_, xy):
        x, y = xy
        lam = 2.0 * jnp.sqrt(x) * jnp.sqrt(y) + y
        return 0.25 * (x + lam), 0.25 * (y + lam)

    x, y = jax.lax.fori_loop(0, RF_STEPS, step, (x, y))
    mean = (x + 2.0 * y) / 3.0
    s = (y - mean) / mean
    return (1.0 + s * s * (0.3 + s * (1.0 / 7.0 + s * (0.375 + s * 9.0 / 22.0)))) / jnp.sqrt(mean)


def carlson_rj(x, y, z, p):
    """Carlson's symmetric elliptic integral of the third kind,
    ``R_J(x, y, z, p) = 3/2 int_0^inf dt / ((t + p) sqrt((t + x)(t + y)(t + z)))``, for
    x, y, z >= 0 (at most one zero) and p > 0 (duplication, then the series of Carlson
    1995, eq. 2.39)."""

    def step(_, carry):
        x, y, z, p, total, scale = carry
        sx, sy, sz = jnp.sqrt(x), jnp.sqrt(y), jnp.sqrt(z)
        lam = sx * (sy + sz) + sy * sz
        alpha = (p * (sx + sy + sz) + sx * sy * sz) ** 2
        beta = p * (p + lam) ** 2
        total = total + scale * carlson_rc(alpha, beta)
        return 0.25 * (x + lam), 0.25 * (y + lam), 0.25 * (z + lam), 0.25 * (p + lam), total, 0.25 * scale

    zero = 0.0 * (x + y + z + p)
    x, y, z, p, total, scale = jax.lax.fori_loop(0, RF_STEPS, step, (x, y, z, p, zero, zero + 1.0))
    mean = 0.2 * (x + y + z + 2.0 * p)
    dx, dy, dz, dp = 1.0 - x / mean, 1.0 - y / mean, 1.0 - z / mean, 1.0 - p / mean
    ea = dx * (dy + dz) + dy * dz
    eb = dx * dy * dz
    ec = dp * dp
    ed = ea - 3.0 * ec
    ee = eb + 2.0 * dp * (ea - ec)
    series = (1.0 + ed * (-3.0 / 14.0 + 0.75 * 3.0 / 22.0 * ed - 1.5 * 3.0 / 26.0 * ee)
              + eb * (1.0 / 6.0 + dp * (-6.0 / 22.0 + dp * 3.0 / 26.0))
              + dp * ea * (1.0 / 3.0 - dp * 3.0 / 22.0) - dp * ec / 3.0)
    return 3.0 * total + scale * series / (mean * jnp.sqrt(mean))


def _third_kind(n, sin_psi, cos_psi, delta2):
    """Legendre's incomplete integral of the third kind
    ``Pi(n; psi | m) = int_0^psi dt / ((1 - n sin^2 t) sqrt(1 - m sin^2 t))`` with
    ``delta2 = 1 - m sin^2 psi``, for 1 - n sin^2 psi > 0 (DLMF 19.25.14)."""
    s2 = sin_psi * sin_psi
    c2 = cos_psi * cos_psi
    return sin_psi * carlson_rf(c2, delta2, 1.0) + n / 3.0 * s2 * sin_psi * carlson_rj(c2, delta2, 1.0, 1.0 - n * s2)


class Spherical:
    """A ball rolling over a corner out of the vertical plane through its vertex: its
    centre on the sphere of radius r about the vertex V, pressed onto it, under gravity
    (the spherical pendulum, inverted; frictionless between impacts, as on an edge).

    With d = p - V = (rho cos phi, rho sin phi, z), rho^2 = r^2 - z^2, the energy
    ``E = |v|^2 / 2 + g z`` and the angular momentum about the vertical
    ``L = d_x v_y - d_y v_x`` (per unit mass) are conserved, and
    ``|v|^2 = r^2 z'^2 / rho^2 + L^2 / rho^2`` gives

        r^2 z'^2 = P(z) = 2 (E - g z)(r^2 - z^2) - L^2 = 2 g (z - z1)(z2 - z)(z3 - z),    (6)

    three real roots z1 < z2 < z3 (P(+-r) = -L^2 < 0 <= P(z0)), the motion between z1 and
    z2 (the highest point). The surface pushes while ``g z / r > |v|^2 / r``, that is down
    to ``z* = 2 E / (3 g)`` (as on an edge, equation (2)), where the ball leaves in flight.
    With ``z = z2 - (z2 - z1) sin^2 psi``, psi growing with time (negative while the ball
    rises), (6) becomes ``dt = K dpsi / sqrt(1 - m sin^2 psi)``,
    ``K = 2 r / sqrt(2 g (z3 - z2))``, ``m = -(z2 - z1) / (z3 - z2) <= 0``:

        t(psi) = K sin(psi) R_F(cos^2 psi, 1 - m sin^2 psi, 1)                          (7)

    (DLMF 19.25.5; regular in psi, dt/dpsi within [K / sqrt(1 - m), K]), and
    ``phi' = L / rho^2``, with ``1 / (r^2 - z^2) = (1 / (r - z) + 1 / (r + z)) / (2 r)``,

        phi(psi) = L K / (2 r) (Pi(n1; psi | m) / (r - z2) + Pi(n2; psi | m) / (r + z2)),
        n1 = -(z2 - z1) / (r - z2),   n2 = (z2 - z1) / (r + z2),                     (8)

    Legendre's integral of the third kind in Carlson's form (``_third_kind``, DLMF
    19.25.14; Byrd and Friedman 1971). The start needs no inverse function: from (6),
    ``sin psi0 = -r z0' / sqrt(2 g (z0 - z1)(z3 - z0)(z2 - z1))`` and
    ``cos psi0 = sqrt((z0 - z1) / (z2 - z1))``.

    The roll ends where the ball leaves (psi* at z*) or leaves the corner's region: its
    centre's horizontal offset from the vertex crosses 0 along x or y (the octant of the
    corner's direction ``signs``), where it goes on over the edge there (``exit_axis``;
    never along z: z* > 0). phi is monotonic (L keeps its sign), so that crossing is found
    by bracketed Newton steps on (8) in psi, and made differentiable by one more step
    (the implicit-function theorem), as a time inside the roll is on (7).

    The roots of the cubic (6) come from the trigonometric formula, each refined by
    Newton steps on P. Near L = 0 (the plane through the vertex, ``roll_axis``'s planar
    case, which ``Roll`` follows) and near E = g r (just the energy to reach the top) two
    roots meet and their derivatives lose digits; values stay finite.
    """

    def __init__(self, vertex, p0, v0, g, signs=None):
        d = p0 - vertex
        self.vertex, self.g = vertex, g
        r2 = inner(d, d)
        self.r = r = jnp.sqrt(r2)
        z0, dz0 = d[2], v0[2]
        energy = 0.5 * inner(v0, v0) + g * z0
        self.L = L = d[0] * v0[1] - d[1] * v0[0]
        # z^3 + a z^2 + b z + c = P(z) / (2 g)
        a, b, c = -energy / g, -r2, (2.0 * energy * r2 - L * L) / (2.0 * g)
        q = (a * a - 3.0 * b) / 9.0
        rr = (2.0 * a * a * a - 9.0 * a * b + 27.0 * c) / 54.0
        sq = jnp.sqrt(jnp.maximum(q, 0.0))
        cube = sq * q
        theta = jnp.arccos(jnp.clip(rr / jnp.where(cube > 0, cube, 1.0), -1.0, 1.0))
        roots = [-2.0 * sq * jnp.cos((theta + 2.0 * jnp.pi * k) / 3.0) - a / 3.0 for k in (0, 2, 1)]

        def polish(z):
            for _ in range(2):
                f = ((z + a) * z + b) * z + c
                df = (3.0 * z + 2.0 * a) * z + b
                z = z - jnp.where(df != 0, f / jnp.where(df != 0, df, 1.0), 0.0)
            return z

        z1, z2, z3 = (polish(z) for z in roots)
        self.z1, self.z2, self.z3 = z1, z2, z3
        span = z2 - z1
        self.K = 2.0 * r / jnp.sqrt(2.0 * g * (z3 - z2))
        self.m = -span / (z3 - z2)
        self.n1, self.n2 = -span / (r - z2), span / (r + z2)
        sin0 = -r * dz0 / jnp.sqrt(2.0 * g * (z0 - z1) * (z3 - z0) * span)
        cos0 = jnp.sqrt(jnp.maximum((z0 - z1) / span, 0.0))
        self.psi0 = jnp.arctan2(sin0, cos0)
        self.t0, self.phi_psi0 = self._time(self.psi0), self._azimuth(self.psi0)
        self.phi0 = jnp.arctan2(d[1], d[0])
        # Where it leaves the surface: z* = 2 E / (3 g), on the falling side (psi >= 0).
        s_star2 = jnp.clip((z2 - 2.0 * energy / (3.0 * g)) / span, 0.0, 1.0)
        # (A ball not pressed at its start leaves at once.)
        pressed = 3.0 * g * z0 >= 2.0 * energy
        psi_star = jnp.where(pressed, jnp.maximum(jnp.arcsin(jnp.sqrt(s_star2)), self.psi0), self.psi0)
        self.exit_axis = jnp.int32(-1)
        psi_end = psi_star
        if signs is not None:
            # The corner's octant, mirrored onto x, y >= 0: the angle beta from the x axis
            # grows with L' = sx sy L, towards the y axis (x crosses 0: axis 0), or falls to
            # the x axis (y crosses 0: axis 1).
            x0, y0 = signs[0] * d[0], signs[1] * d[1]
            turn = signs[0] * signs[1] * L
            beta0 = jnp.arctan2(y0, x0)
            room = jnp.where(turn > 0, 0.5 * jnp.pi - beta0, beta0)
            psi_exit, crosses = self._crossing(room, self.psi0, psi_star)
            self.exit_axis = jnp.where(crosses, jnp.where(turn > 0, 0, 1), -1).astype(jnp.int32)
            psi_end = jnp.where(crosses, psi_exit, psi_star)
        self.psi_end = psi_end
        self.duration = self._time(psi_end) - self.t0

    def _time(self, psi):
        """t(psi) of equation (7)."""
        s, c = jnp.sin(psi), jnp.cos(psi)
        return self.K * s * carlson_rf(c * c, 1.0 - self.m * s * s, 1.0)

    def _azimuth(self, psi):
        """phi(psi) of equation (8), from psi = 0."""
        s, c = jnp.sin(psi), jnp.cos(psi)
        delta2 = 1.0 - self.m * s * s
        # (Both integrals in one call: one copy of R_J's loops in the program.)
        pi = _third_kind(jnp.stack([self.n1, self.n2]), s, c, delta2)
        return self.L * self.K / (2.0 * self.r) * (pi[0] / (self.r - self.z2) + pi[1] / (self.r + self.z2))

    def _height(self, psi):
        s = jnp.sin(psi)
        return self.z2 - (self.z2 - self.z1) * s * s

    def _crossing(self, room, lo, hi):
        """The psi in [lo, hi] at which |phi(psi) - phi(lo)| reaches ``room`` (bracketed
        Newton steps, values; then one differentiable step), and whether it lies there."""

        def turned(psi):
            return jnp.abs(self._azimuth(psi) - self.phi_psi0)

        def rate(psi):  # |dphi / dpsi| = |L| / rho^2 dt / dpsi
            z = self._height(psi)
            s = jnp.sin(psi)
            return jnp.abs(self.L) / (self.r * self.r - z * z) * self.K / jnp.sqrt(1.0 - self.m * s * s)

        fixed = jax.lax.stop_gradient
        crosses = fixed(turned(hi) >= room)
        a, b = fixed((lo, hi))
        target = fixed(room)

        def step(_, abx):
            a, b, x = abx
            f = fixed(turned(x)) - target
            a, b = jnp.where(f < 0, x, a), jnp.where(f < 0, b, x)
            newton = x - f / fixed(rate(x))
            x = jnp.where((newton > a) & (newton < b), newton, 0.5 * (a + b))
            return a, b, x

        _, _, x = jax.lax.fori_loop(0, SPHERE_STEPS, step, (a, b, 0.5 * (a + b)))
        x = jnp.where(crosses, x, b)
        return x - (turned(x) - room) / rate(x), crosses

    def state(self, tau):
        """Position and velocity ``tau`` after the start (to the roll's end, then held)."""
        tau = jnp.clip(tau, 0.0, self.duration)
        target = self.t0 + tau

        def residual(psi):
            s = jnp.sin(psi)
            return self._time(psi) - target, jnp.sqrt(1.0 - self.m * s * s) / self.K  # (t - target, dpsi/dt)

        lo, hi = jax.lax.stop_gradient((self.psi0, self.psi_end))

        def newton(_, psi):
            f, slope = jax.lax.stop_gradient(residual(psi))
            return jnp.clip(psi - f * slope, lo, hi)

        psi = jax.lax.fori_loop(0, ROLL_NEWTONS, newton, jax.lax.stop_gradient(self.psi0 + tau / self.K))
        f, slope = residual(psi)
        psi = psi - f * slope
        s, c = jnp.sin(psi), jnp.cos(psi)
        z = self._height(psi)
        dz = -(self.z2 - self.z1) * 2.0 * s * c * jnp.sqrt(1.0 - self.m * s * s) / self.K
        rho2 = self.r * self.r - z * z
        rho = jnp.sqrt(rho2)
        phi = self.phi0 + self._azimuth(psi) - self.phi_psi0
        dphi = self.L / rho2
        drho = -z * dz / rho
        cp, sp = jnp.cos(phi), jnp.sin(phi)
        p = self.vertex + jnp.stack([rho * cp, rho * sp, z])
        v = jnp.stack([drho * cp - rho * dphi * sp, drho * sp + rho * dphi * cp, dz])
        return p, v


def spherical_stand_in(spherical, vertex, p, v, r, g):
    """(p, v) where ``spherical``, else a state on the sphere of radius r about ``vertex``
    that is a spherical roll (pressed, off the plane through the vertex): the inputs of a
    ``Spherical`` that will not be used, harmless (no NaN in the cotangents of a branch not
    taken)."""
    p_s = vertex + r * jnp.array([0.6, 0.0, 0.8])
    v_s = jnp.sqrt(g * r) * jnp.array([0.0, 0.1, 0.0])
    return jnp.where(spherical, p, p_s), jnp.where(spherical, v, v_s)


def roll_state(spherical, plane: Roll, sphere: Spherical, tau):
    """Position and velocity ``tau`` into a roll: ``sphere``'s where ``spherical``, else
    ``plane``'s."""
    p_r, v_r = plane.state(tau)
    p_s, v_s = sphere.state(tau)
    return jnp.where(spherical, p_s, p_r), jnp.where(spherical, v_s, v_r)
