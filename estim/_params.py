"""The parameter container: everything that, with a scene, determines a ball's motion."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._scene import Scene

__all__ = ["Params"]

# Drag coefficient of a smooth sphere at Reynolds numbers 1e3-2e5 (ping-pong to bocce in
# flight); see estim._effects.
DRAG_COEFFICIENT = 0.47


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


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
        drag_coefficient: C_D >= 0 of the quadratic drag (``estim._effects``), 0.47 (a
            smooth sphere) by default; used only in a scene with air.
        spin: angular velocity (rad/s), shape ``(*batch, 3)``, for the Magnus force; zero by
            default, and it must stay zero in a scene without air, where it has no effect.

    Impossible values (NaN, e outside [0, 1], r <= 0, ...) raise ``ValueError`` here when
    the values are concrete, and inside ``jit`` when :func:`estim.simulate` runs.
    """

    e: Float[Array, "*batch"]
    mu_t: Float[Array, "*batch"]
    radius: Float[Array, "*batch"]
    position: Float[Array, "*batch 3"]
    velocity: Float[Array, "*batch 3"]
    mass: Float[Array, "*batch"] | None
    drag_coefficient: Float[Array, "*batch"]
    spin: Float[Array, "*batch 3"]

    def __init__(self, e, mu_t, radius, position, velocity, *, mass=None,
                 drag_coefficient=DRAG_COEFFICIENT, spin=(0.0, 0.0, 0.0)):
        self.e = jnp.asarray(e, dtype=jnp.float64)
        self.mu_t = jnp.asarray(mu_t, dtype=jnp.float64)
        self.radius = jnp.asarray(radius, dtype=jnp.float64)
        self.position = jnp.asarray(position, dtype=jnp.float64)
        self.velocity = jnp.asarray(velocity, dtype=jnp.float64)
        self.mass = None if mass is None else jnp.asarray(mass, dtype=jnp.float64)
        self.drag_coefficient = jnp.asarray(drag_coefficient, dtype=jnp.float64)
        self.spin = jnp.asarray(spin, dtype=jnp.float64)

    def __check_init__(self):
        for name in ("position", "velocity", "spin"):
            x = getattr(self, name)
            if x.ndim == 0 or x.shape[-1] != 3:
                raise ValueError(f"Params.{name} must have a last axis of length 3 (x, y, z), got shape {x.shape}")
        checks = (
            ("e", self.e, lambda x: (x >= 0) & (x <= 1), "must lie in [0, 1]"),
            ("mu_t", self.mu_t, lambda x: (x >= 0) & (x <= 1), "must lie in [0, 1]"),
            ("radius", self.radius, lambda x: x > 0, "must be > 0 (metres)"),
            ("position", self.position, lambda x: np.isfinite(x), "must be finite"),
            ("velocity", self.velocity, lambda x: np.isfinite(x), "must be finite"),
            ("drag_coefficient", self.drag_coefficient, lambda x: x >= 0, "must be >= 0"),
            ("spin", self.spin, lambda x: np.isfinite(x), "must be finite"),
        )
        if self.mass is not None:
            checks += (("mass", self.mass, lambda x: x > 0, "must be > 0 (kg)"),)
        for name, x, ok, what in checks:
            if _concrete(x):
                xv = np.asarray(x)
                bad = ~(np.isfinite(xv) & ok(xv))
                if np.any(bad):
                    raise ValueError(f"Params.{name} {what}; got {xv[bad].ravel()[:4].tolist()}")

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return np.broadcast_shapes(  # shapes only: NumPy takes 3 us, jnp 8 us
            self.e.shape, self.mu_t.shape, self.radius.shape,
            self.position.shape[:-1], self.velocity.shape[:-1],
            () if self.mass is None else self.mass.shape,
            self.drag_coefficient.shape, self.spin.shape[:-1],
        )

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
    ) -> Params:
        """Parameters of the scene's ball ``ball`` (radius and mass from the scene); the
        release position defaults to the ball's position in the scene file."""
        spec = scene.ball(ball)
        if position is None:
            position = spec.position
        if drag_coefficient is None:
            drag_coefficient = DRAG_COEFFICIENT
        return cls(e, mu_t, spec.radius, position, velocity, mass=spec.mass,
                   drag_coefficient=drag_coefficient, spin=spin)


# The checks of ``Params.__check_init__`` as they run inside ``jit``: a message and what
# holds, elementwise, for valid parameters (NaN fails every one).
PARAM_CHECKS = (
    ("e must lie in [0, 1]", lambda p: (p.e >= 0) & (p.e <= 1)),
    ("mu_t must lie in [0, 1]", lambda p: (p.mu_t >= 0) & (p.mu_t <= 1)),
    ("radius must be > 0", lambda p: p.radius > 0),
    ("position must be finite", lambda p: jnp.isfinite(p.position)),
    ("velocity must be finite", lambda p: jnp.isfinite(p.velocity)),
    ("mass must be > 0", lambda p: True if p.mass is None else p.mass > 0),
    ("drag_coefficient must be >= 0", lambda p: p.drag_coefficient >= 0),
    ("spin must be finite", lambda p: jnp.isfinite(p.spin)),
)


def invalid_params(params: Params) -> Int[Array, ""]:
    """0 if ``params`` pass every check of ``PARAM_CHECKS``, else 1 + the index of the
    first that fails (for any ball)."""
    bad = jnp.stack([~jnp.all(ok(params)) for _, ok in PARAM_CHECKS])
    return jnp.where(jnp.any(bad), jnp.argmax(bad) + 1, 0).astype(jnp.int32)


def check_runtime(params: Params, t_end) -> Params:
    """The checks of ``Params.__check_init__``, inside ``jit``: one ``eqx.branched_error_if``
    (each is a kernel of its own in the compiled program) naming the first that fails."""
    code = invalid_params(params)
    return eqx.branched_error_if(params, code > 0, jnp.maximum(code - 1, 0), [m for m, _ in PARAM_CHECKS])


def check_t_end(t_end) -> None:
    if _concrete(t_end):
        value = float(np.asarray(t_end))
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"t_end must be a finite time > 0 (seconds), got {value!r}")
