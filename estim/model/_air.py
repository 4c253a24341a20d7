"""Forces of the air on a ball in flight: quadratic drag, linear (viscous) drag, wind, Magnus.

A scene asks for air with MuJoCo's ``<option density=... viscosity=... wind=...>`` (see
``estim.model._scene``); a scene without it has none of these forces and is solved in closed form
(``estim.forward._solver``). With air, the acceleration of a ball of radius r, mass m, velocity v and
angular velocity omega (``Params.spin``) is

    a = g + a_quad + a_lin + a_magnus,     w = v - wind (velocity relative to the air),

    a_quad   = -(rho C_D A / (2 m)) |w| w,                 A = pi r^2,              (1)
    a_lin    = -(6 pi eta r / m) w,                                                   (2)
    a_magnus = f_L (rho A r / (2 m)) kappa(S) (omega x w), S = r |omega| / |w|,       (3)
    kappa(S) = C_L(S) / S = min(1.5, 0.6 + 0.09 / S).

(1) is Newton's quadratic drag with the drag coefficient ``Params.drag_coefficient``
(C_D ~ 0.47 for a smooth sphere at Reynolds numbers 1e3-2e5; a golf ball's dimples give
~0.25 above Re ~ 5e4). (2) is Stokes' law for a sphere in a fluid of dynamic viscosity
eta, dominant only at Reynolds numbers below ~1 (never for a ball in air; it is here because
MuJoCo's ``viscosity`` option asks for it). (3) is the Magnus lift
``F = (1/2) rho A C_L |w|^2`` along ``omega x w / |omega x w|`` with the lift coefficient of
Sawicki, Hubbard & Stronge (Am. J. Phys. 71, 1152 (2003)): C_L = 1.5 S for S < 0.1 and
0.09 + 0.6 S above, continuous at S = 0.1, scaled by the lift factor ``f_L``
(``Params.lift_factor``, 1 by default: real balls differ from the textbook curve, by their
seams, fuzz or surface, and a fit can estimate f_L as it estimates C_D). Written with
kappa = C_L / S the force is smooth in omega and w, and zero without spin. Spin is constant in flight: the torque of the air on
the ball changes it over seconds (no decay is modelled). At impacts the scene's contact law
may change it (the friction law does: ``estim.forward.laws.FrictionLaw``; the ODE path carries
the spin from contact to contact).

How MuJoCo's own ``<option density viscosity wind>`` maps to this: MuJoCo's default
("inertia") fluid model replaces a body by the box of equal inertia; for a solid sphere of
radius r that box has sides s = r sqrt(12/5) ~ 1.549 r. Its quadratic drag acts per axis
with the box's face area s^2 = 2.4 r^2 and coefficient 1, i.e. C_D = 2.4 / pi ~ 0.76 in (1)
(applied component-wise, ``|w_i| w_i`` instead of ``|w| w``), and its viscous drag uses the
mean side as diameter, 3 pi eta s = 0.77 (6 pi eta r) in (2). estim uses the sphere laws above
with a per-ball C_D instead, because a fitted C_D is what users compare with the literature.
The inertia model has no Magnus force. MuJoCo's ellipsoid model (``fluidshape="ellipsoid"``
on the ball's geom) has one, ``f_M = C_M rho V omega x v`` with the volume V = 4 pi r^3 / 3
and C_M its fifth ``fluidcoef`` (1 by default), beside an added-mass force that for a sphere
(added mass rho V / 2, Lamb 1932) contributes ``-(rho V / 2) omega x v``. Together,
``(C_M - 1/2) rho V omega x v`` is (3) with ``f_L kappa = 8 (C_M - 1/2) / 3``: 4/3 for
MuJoCo's defaults, f_L = 0.89 at low spin ratios (kappa = 1.5), a constant where estim's C_L
saturates with S. The added mass also adds rho V / 2 to the ball's inertia (0.7% of a
table-tennis ball's mass), and MuJoCo's angular drag slows the spin, which estim holds
constant in flight (MuJoCo documentation, "Fluid forces").
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._fold import inner

__all__ = ["Air", "acceleration", "spin_for_lift", "spinless_acceleration", "step_bounds"]


class Air(eqx.Module):
    """The air of a scene (MJCF ``<option density viscosity wind>``).

    Attributes:
        density: rho (kg/m^3), 1.2 for air at 20 C; switches on quadratic drag and Magnus.
        viscosity: eta (Pa s), 1.8e-5 for air; switches on linear (Stokes) drag.
        wind: velocity of the air (m/s).
    """

    density: Float[Array, ""]
    viscosity: Float[Array, ""]
    wind: Float[Array, "3"]

    def __init__(self, density=0.0, viscosity=0.0, wind=(0.0, 0.0, 0.0)):
        self.density = jnp.asarray(density, dtype=jnp.float64)
        self.viscosity = jnp.asarray(viscosity, dtype=jnp.float64)
        self.wind = jnp.asarray(wind, dtype=jnp.float64)


# kappa(S) = min(KAPPA_MAX, LIFT_SLOPE + LIFT_OFFSET / S): C_L = 0.09 + 0.6 S above S = 0.1,
# 1.5 S below (eq. (3)).
KAPPA_MAX, LIFT_SLOPE, LIFT_OFFSET = 1.5, 0.6, 0.09


def lift_ratio(radius, omega2, speed):
    """kappa(S) = C_L(S) / S of eq. (3) with S = r |omega| / speed (1.5 without spin).

    Takes |omega|^2 so that the derivative at zero spin is finite (no sqrt of 0)."""
    spinning = omega2 > 0
    omega = jnp.sqrt(jnp.where(spinning, omega2, 1.0))
    return jnp.where(spinning, jnp.minimum(KAPPA_MAX, LIFT_SLOPE + LIFT_OFFSET * speed / (radius * omega)), KAPPA_MAX)


def spin_for_lift(air: Air, radius: float, mass: float, velocity, lift, lift_factor: float = 1.0):
    """The spin (rad/s, NumPy) perpendicular to the relative velocity ``w`` whose Magnus
    acceleration (eq. (3)) is the part of ``lift`` (m/s^2) perpendicular to w: eq. (3)
    inverted, for a start read off a flight's curvature.

    With c = f_L rho A r / (2 m) and |omega| = S |w| / r, eq. (3) reads
    |a_M| = c kappa(S) |omega| |w| = c C_L(S) |w|^2 / r, so C_L = |a_M| r / (c |w|^2), and
    C_L(S) inverts piecewise: S = C_L / 1.5 below C_L = 0.15, S = (C_L - 0.09) / 0.6 above.
    The direction: for omega perpendicular to w, w x (omega x w) = |w|^2 omega, so omega
    points along w x a_M. The spin along w moves nothing in flight and is left at 0.
    """
    w = np.asarray(velocity, dtype=np.float64) - np.asarray(air.wind)
    speed2 = float(w @ w)
    c = lift_factor * float(air.density) * math.pi * radius**3 / (2.0 * mass)
    if not (speed2 > 0 and c > 0):
        return np.zeros(3)
    a = np.asarray(lift, dtype=np.float64)
    a_perp = a - (a @ w) * w / speed2
    lift_coefficient = float(np.linalg.norm(a_perp)) * radius / (c * speed2)
    knee = KAPPA_MAX * LIFT_OFFSET / (KAPPA_MAX - LIFT_SLOPE)  # C_L where the two pieces meet (0.15)
    s = lift_coefficient / KAPPA_MAX if lift_coefficient < knee else (lift_coefficient - LIFT_OFFSET) / LIFT_SLOPE
    axis = np.cross(w, a_perp)
    norm = float(np.linalg.norm(axis))
    return np.zeros(3) if norm == 0 else (s * math.sqrt(speed2) / radius) * axis / norm


def air_acceleration(air: Air, radius, mass, drag_coefficient, spin, velocity, lift_factor=1.0):
    """``a_quad + a_lin + a_magnus`` of eqs. (1)-(3) (m/s^2), for one ball."""
    w = velocity - air.wind
    speed = jnp.sqrt(inner(w, w) + 1e-300)  # smooth at w = 0, where every term vanishes
    area = jnp.pi * radius**2
    quad = -(air.density * drag_coefficient * area / (2.0 * mass)) * speed * w
    lin = -(6.0 * jnp.pi * air.viscosity * radius / mass) * w
    kappa = lift_ratio(radius, inner(spin, spin), speed)
    magnus = (lift_factor * air.density * area * radius / (2.0 * mass)) * kappa * jnp.cross(spin, w)
    return quad + lin + magnus


# For NumPy callers (the starts read off a track): compiled once per process. Called eagerly,
# each call dispatched its thirty-odd JAX operations one by one, and the first compiled each
# of them (about 0.3 s of a camera fit's first call; 0.2 s of a compiled one's 0.46 s).
air_acceleration_compiled = jax.jit(air_acceleration)


def spinless_acceleration(air: Air, radius: float, mass: float, drag_coefficient: float):
    """``v -> air_acceleration`` of a ball without spin, NumPy in and out (the starts'
    drag at a flight's velocity). The constants go in as float64 arrays once: one compiled
    signature for every caller, and no conversion at each of a start's thousand calls."""
    constants = [jnp.asarray(c, dtype=jnp.float64) for c in (radius, mass, drag_coefficient, np.zeros(3))]

    def acceleration(velocity) -> np.ndarray:
        return np.asarray(air_acceleration_compiled(air, *constants, velocity))

    return acceleration


def acceleration(air: Air | None, gravity, radius, mass, drag_coefficient, spin, velocity, lift_factor=1.0):
    """Total acceleration of a ball in flight: gravity (along -z) plus the air's forces."""
    g = jnp.array([0.0, 0.0, -1.0]) * gravity
    if air is None:
        return g + 0.0 * velocity
    return g + air_acceleration(air, radius, mass, drag_coefficient, spin, velocity, lift_factor)


def step_bounds(air: Air | None, gravity, radius, mass, drag_coefficient, spin, velocity, h, lift_factor=1.0):
    """Bounds over a flight of duration ``h`` from ``velocity``: ``(A, L)`` with
    ``|a(t)| <= A`` all along it and ``L`` a Lipschitz constant of the air's acceleration
    over every velocity it can reach. Then the path stays within

        |q(tau) - q_par(tau)| <= L A tau^3 / 6,      0 <= tau <= h,                    (4)

    of the parabola ``q_par(tau) = p + v tau + a(v) tau^2 / 2`` of its initial
    acceleration, since ``q - q_par = int_0^tau (tau - s) (a(v(s)) - a(v)) ds`` and
    ``|a(v(s)) - a(v)| <= L |v(s) - v| <= L A s``.

    Derivation. Relative to the air, ``w = v - wind`` changes as ``dw/dt = a``; drag
    (1)-(2) points against w and Magnus (3) across it, so ``d|w|/dt <= g`` and
    ``|w(t)| <= W = |w(0)| + g h``. Over ``|w| <= W``:

    - ``|a| <= g + k W^2 + c W + M |omega| W`` with k, c, M the factors of (1), (2),
      (3) (M with f_L) and kappa <= 1.5;
    - the Jacobian of ``-k |w| w`` is ``-k (|w| I + w w^T / |w|)``, of norm ``2 k |w|``;
      that of (2) has norm c; that of (3) is
      ``M (kappa [omega]_x + kappa'(S) (omega x w) w^T / |w| ...)``, which the two branches
      of kappa bound by ``M (1.5 |omega| + 0.09 W / r)`` (``KAPPA_MAX``, ``LIFT_OFFSET``).

    Gravity and wind are constant and drop out of L. A scene without air has
    ``L = 0``: the parabola is the path."""
    g = gravity
    if air is None:
        return g + 0.0 * h, 0.0 * h
    w = velocity - air.wind
    big_w = jnp.sqrt(inner(w, w)) + g * h
    area = jnp.pi * radius**2
    k = air.density * drag_coefficient * area / (2.0 * mass)
    c = 6.0 * jnp.pi * air.viscosity * radius / mass
    omega = jnp.sqrt(inner(spin, spin))
    m = lift_factor * air.density * area * radius / (2.0 * mass)
    a_max = g + k * big_w**2 + c * big_w + KAPPA_MAX * m * omega * big_w
    lipschitz = 2.0 * k * big_w + c + m * (KAPPA_MAX * omega + LIFT_OFFSET * big_w / radius)
    return a_max, lipschitz
