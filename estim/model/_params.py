"""The parameter container: everything that, with a scene, determines a ball's motion."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._scene import Scene

__all__ = ["Params"]

# Drag coefficient of a smooth sphere at Reynolds numbers 1e3-2e5 (ping-pong to bocce in
# flight); see estim.model._air.
DRAG_COEFFICIENT = 0.47
# I / (m r^2) of a solid sphere; a thin spherical shell (a table-tennis ball) has 2/3.
SOLID_INERTIA = 0.4


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _has_text(x) -> bool:
    return isinstance(x, (str, bytes)) or (isinstance(x, (list, tuple)) and any(map(_has_text, x)))


def _float64(name: str, x) -> Array:
    """``x`` as a float64 array; text is refused, not parsed (a number read from a file as a
    string is a bug upstream)."""
    if _has_text(x):
        raise TypeError(f"Params.{name} must be numbers, got {x!r}")
    return jnp.asarray(x, dtype=jnp.float64)


class Params(eqx.Module):
    """Per-ball parameters and release state; every field may carry batch dimensions.

    Attributes:
        e: coefficient of restitution, 0 <= e <= 1 (normal velocity -> -e times itself).
        mu_t: tangential coefficient, 0 <= mu_t <= 1 (tangential velocity -> mu_t times
            itself at every impact).
        radius: ball radius r > 0 (m).
        position: release position of the centre (m), shape ``(*batch, 3)``.
        velocity: release velocity (m/s), shape ``(*batch, 3)``.
        mass: ball mass m > 0 (kg); needed only in a scene with air (``Params.for_ball``
            takes it from the scene), else ``None``.
        drag_coefficient: C_D >= 0 of the quadratic drag (``estim.model._air``), 0.47 (a
            smooth sphere) by default; used only in a scene with air.
        spin: angular velocity (rad/s), shape ``(*batch, 3)``, at release: for the Magnus
            force, and for a contact law that couples spin (``estim.forward.laws.FrictionLaw``);
            zero by default, and it must stay zero in a scene where it has no effect.
        lift_factor: factor f_L >= 0 on the Magnus lift coefficient (``estim.model._air``),
            1 (the textbook curve) by default; used only in a scene with air.
        mu: Coulomb friction coefficient mu >= 0 of a contact law with friction
            (``estim.forward.laws.FrictionLaw``); 0 (frictionless) by default.
        inertia: the ball's moment of inertia as a ratio ``I / (m r^2)``, in (0, 1]: 2/5
            for a solid sphere (the default), 2/3 for a thin shell; ``Params.for_ball``
            takes it from the scene (the ball body's inertia).
        e_slope: how the restitution of a law that reads it changes with the impact's normal
            speed (s/m; negative: e falls as impacts get faster), 0 (e the same at every
            speed) by default (``estim.forward.laws.FrictionLaw``).
        compression: how much closer than its radius the ball's centre comes to a solid at
            a contact (m), 0 (a rigid ball) by default: every contact, and the lever arm of
            a law's friction, use the *contact radius* ``radius - compression``
            (:attr:`contact_radius`); drag and lift keep ``radius``. Negative values are an
            effective contact radius larger than the ball, which no real ball has but which
            a tracker that reads the centre high, or a surface a little higher than the
            scene says, look like.

    Impossible values (NaN, e outside [0, 1], r <= 0, ...) raise ``ValueError`` here when
    the values are concrete, and inside ``jit`` when :func:`estim.simulate` runs.
    """

    e: Float[Array, "*batch"]
    mu_t: Float[Array, "*batch"]
    radius: Float[Array, "*batch"]
    position: Float[Array, "*batch 3"]
    velocity: Float[Array, "*batch 3"]
    # (Next to the fields the native kernels read: they take the contact radius from the
    # first row of a ball's packed parameters, estim.forward._balls.param_rows.)
    compression: Float[Array, "*batch"]
    mass: Float[Array, "*batch"] | None
    drag_coefficient: Float[Array, "*batch"]
    spin: Float[Array, "*batch 3"]
    mu: Float[Array, "*batch"]
    inertia: Float[Array, "*batch"]
    lift_factor: Float[Array, "*batch"]
    e_slope: Float[Array, "*batch"]

    def __init__(self, e, mu_t, radius, position, velocity, *, mass=None,
                 drag_coefficient=DRAG_COEFFICIENT, spin=(0.0, 0.0, 0.0), mu=0.0, inertia=SOLID_INERTIA,
                 lift_factor=1.0, e_slope=0.0, compression=0.0):
        self.e = _float64("e", e)
        self.mu_t = _float64("mu_t", mu_t)
        self.radius = _float64("radius", radius)
        self.position = _float64("position", position)
        self.velocity = _float64("velocity", velocity)
        self.compression = _float64("compression", compression)
        self.mass = None if mass is None else _float64("mass", mass)
        self.drag_coefficient = _float64("drag_coefficient", drag_coefficient)
        self.spin = _float64("spin", spin)
        self.mu = _float64("mu", mu)
        self.inertia = _float64("inertia", inertia)
        self.lift_factor = _float64("lift_factor", lift_factor)
        self.e_slope = _float64("e_slope", e_slope)

    def __check_init__(self):
        for name in ("position", "velocity", "spin"):
            x = getattr(self, name)
            if x.ndim == 0 or x.shape[-1] != 3:
                raise ValueError(f"Params.{name} must have a last axis of length 3 (x, y, z), got shape {x.shape}")
        fields = {"e": self.e.shape, "mu_t": self.mu_t.shape, "radius": self.radius.shape,
                  "position": self.position.shape[:-1], "velocity": self.velocity.shape[:-1],
                  "drag_coefficient": self.drag_coefficient.shape, "spin": self.spin.shape[:-1],
                  "mu": self.mu.shape, "inertia": self.inertia.shape, "lift_factor": self.lift_factor.shape,
                  "e_slope": self.e_slope.shape, "compression": self.compression.shape}
        if self.mass is not None:
            fields["mass"] = self.mass.shape
        try:
            np.broadcast_shapes(*fields.values())
        except ValueError:
            shapes = ", ".join(f"{k} {v}" for k, v in fields.items() if v != ())
            raise ValueError(f"Params: the fields' batch shapes do not broadcast together ({shapes}); "
                             "give every field the same batch shape, or a scalar") from None
        checks = (
            ("e", self.e, lambda x: (x >= 0) & (x <= 1), "must lie in [0, 1]"),
            ("mu_t", self.mu_t, lambda x: (x >= 0) & (x <= 1), "must lie in [0, 1]"),
            ("radius", self.radius, lambda x: x > 0, "must be > 0 (metres)"),
            ("position", self.position, lambda x: np.isfinite(x), "must be finite"),
            ("velocity", self.velocity, lambda x: np.isfinite(x), "must be finite"),
            ("drag_coefficient", self.drag_coefficient, lambda x: x >= 0, "must be >= 0"),
            ("spin", self.spin, lambda x: np.isfinite(x), "must be finite"),
            ("mu", self.mu, lambda x: x >= 0, "must be >= 0"),
            ("inertia", self.inertia, lambda x: (x > 0) & (x <= 1), "must lie in (0, 1] (I / (m r^2))"),
            ("lift_factor", self.lift_factor, lambda x: x >= 0, "must be >= 0"),
            ("e_slope", self.e_slope, lambda x: np.isfinite(x), "must be finite"),
            ("compression", self.compression, lambda x: np.isfinite(x), "must be finite"),
        )
        if self.mass is not None:
            checks += (("mass", self.mass, lambda x: x > 0, "must be > 0 (kg)"),)
        for name, x, ok, what in checks:
            if _concrete(x):
                xv = np.asarray(x)
                bad = ~(np.isfinite(xv) & ok(xv))
                if np.any(bad):
                    raise ValueError(f"Params.{name} {what}; got {xv[bad].ravel()[:4].tolist()}")
        if _concrete(self.radius) and _concrete(self.compression):
            r, c = np.broadcast_arrays(np.asarray(self.radius), np.asarray(self.compression))
            bad = ~(c < r)
            if np.any(bad):
                raise ValueError("Params.compression must be less than the radius (the contact radius, "
                                 f"radius - compression, must be > 0); got compression {c[bad].ravel()[:4].tolist()} "
                                 f"for radius {r[bad].ravel()[:4].tolist()}")

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return np.broadcast_shapes(  # shapes only: NumPy takes 3 us, jnp 8 us
            self.e.shape, self.mu_t.shape, self.radius.shape,
            self.position.shape[:-1], self.velocity.shape[:-1],
            () if self.mass is None else self.mass.shape,
            self.drag_coefficient.shape, self.spin.shape[:-1], self.mu.shape, self.inertia.shape,
            self.lift_factor.shape, self.e_slope.shape, self.compression.shape,
        )

    @property
    def contact_radius(self) -> Float[Array, "*batch"]:
        """``radius - compression``: how far from a solid the centre is at a contact."""
        return self.radius - self.compression

    @classmethod
    def for_ball(
        cls,
        scene: Scene,
        ball: str,
        *,
        e,
        mu_t,
        velocity=(0.0, 0.0, 0.0),
        position=None,
        drag_coefficient=None,
        spin=(0.0, 0.0, 0.0),
        mu=0.0,
        lift_factor=1.0,
        e_slope=0.0,
        compression=0.0,
    ) -> Params:
        """Parameters of the scene's ball ``ball`` (radius, mass and inertia from the
        scene); the release position defaults to the ball's position in the scene file."""
        spec = scene.ball(ball)
        if position is None:
            position = spec.position
        if drag_coefficient is None:
            drag_coefficient = DRAG_COEFFICIENT
        return cls(e, mu_t, spec.radius, position, velocity, mass=spec.mass,
                   drag_coefficient=drag_coefficient, spin=spin, mu=mu, inertia=spec.inertia,
                   lift_factor=lift_factor, e_slope=e_slope, compression=compression)


# The checks of ``Params.__check_init__`` as they run inside ``jit``: a message and what
# holds, elementwise, for valid parameters (NaN fails every one).
PARAM_CHECKS = (
    ("e must lie in [0, 1]", lambda p: (p.e >= 0) & (p.e <= 1)),
    ("mu_t must lie in [0, 1]", lambda p: (p.mu_t >= 0) & (p.mu_t <= 1)),
    ("radius must be > 0, and compression less than the radius",
     lambda p: (p.radius > 0) & (p.contact_radius > 0)),
    ("position must be finite", lambda p: jnp.isfinite(p.position)),
    ("velocity must be finite", lambda p: jnp.isfinite(p.velocity)),
    ("mass must be > 0", lambda p: True if p.mass is None else p.mass > 0),
    ("drag_coefficient must be >= 0", lambda p: p.drag_coefficient >= 0),
    ("spin must be finite", lambda p: jnp.isfinite(p.spin)),
)
# Those of the parameters that the native kernels never read (they run the factor law in a
# vacuum alone), so do not check; estim.forward._simulate lists them last.
UNREAD_BY_KERNELS_CHECKS = (
    ("mu must be >= 0", lambda p: p.mu >= 0),
    ("inertia must lie in (0, 1]", lambda p: (p.inertia > 0) & (p.inertia <= 1)),
    ("lift_factor must be >= 0", lambda p: p.lift_factor >= 0),
    ("e_slope must be finite", lambda p: jnp.isfinite(p.e_slope)),
)


def check_t_end(t_end) -> None:
    """``t_end`` is one finite time > 0 (its value is checked when concrete; inside a
    user's jit, ``estim.simulate`` checks it in the program)."""
    if isinstance(t_end, (str, bytes)):
        raise TypeError(f"t_end must be a number (seconds), got {t_end!r}")
    shape = np.shape(t_end)
    if shape != ():
        raise ValueError(f"t_end must be a single time (a scalar), got shape {shape}; "
                         "every ball of a batch runs to the same t_end")
    if _concrete(t_end):
        value = float(np.asarray(t_end))
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"t_end must be a finite time > 0 (seconds), got {value!r}")
