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

    Impossible values (NaN, e outside [0, 1], r <= 0, ...) raise ``ValueError`` here when
    the values are concrete, and inside ``jit`` when :func:`estim.simulate` runs.
    """

    e: Float[Array, "*batch"]
    mu_t: Float[Array, "*batch"]
    radius: Float[Array, "*batch"]
    position: Float[Array, "*batch 3"]
    velocity: Float[Array, "*batch 3"]

    def __init__(self, e, mu_t, radius, position, velocity):
        self.e = jnp.asarray(e, dtype=jnp.float64)
        self.mu_t = jnp.asarray(mu_t, dtype=jnp.float64)
        self.radius = jnp.asarray(radius, dtype=jnp.float64)
        self.position = jnp.asarray(position, dtype=jnp.float64)
        self.velocity = jnp.asarray(velocity, dtype=jnp.float64)

    def __check_init__(self):
        for name in ("position", "velocity"):
            x = getattr(self, name)
            if x.ndim == 0 or x.shape[-1] != 3:
                raise ValueError(f"Params.{name} must have a last axis of length 3 (x, y, z), got shape {x.shape}")
        checks = (
            ("e", self.e, lambda x: (x >= 0) & (x <= 1), "must lie in [0, 1]"),
            ("mu_t", self.mu_t, lambda x: (x >= 0) & (x <= 1), "must lie in [0, 1]"),
            ("radius", self.radius, lambda x: x > 0, "must be > 0 (metres)"),
            ("position", self.position, lambda x: np.isfinite(x), "must be finite"),
            ("velocity", self.velocity, lambda x: np.isfinite(x), "must be finite"),
        )
        for name, x, ok, what in checks:
            if _concrete(x):
                xv = np.asarray(x)
                bad = ~(np.isfinite(xv) & ok(xv))
                if np.any(bad):
                    raise ValueError(f"Params.{name} {what}; got {xv[bad].ravel()[:4].tolist()}")

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return jnp.broadcast_shapes(
            self.e.shape, self.mu_t.shape, self.radius.shape,
            self.position.shape[:-1], self.velocity.shape[:-1],
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
    ) -> Params:
        """Parameters of the scene's ball ``ball`` (radius from the scene); the release
        position defaults to the ball's position in the scene file."""
        spec = scene.ball(ball)
        if position is None:
            position = spec.position
        return cls(e, mu_t, spec.radius, position, velocity)


def check_runtime(params: Params, t_end) -> Params:
    """The checks of ``Params.__check_init__``, inside ``jit`` (``eqx.error_if``)."""
    e = eqx.error_if(params.e, ~((params.e >= 0) & (params.e <= 1)), "e must lie in [0, 1]")
    mu = eqx.error_if(params.mu_t, ~((params.mu_t >= 0) & (params.mu_t <= 1)), "mu_t must lie in [0, 1]")
    r = eqx.error_if(params.radius, ~(params.radius > 0), "radius must be > 0")
    p = eqx.error_if(params.position, ~jnp.all(jnp.isfinite(params.position)), "position must be finite")
    v = eqx.error_if(params.velocity, ~jnp.all(jnp.isfinite(params.velocity)), "velocity must be finite")
    return Params(e, mu, r, p, v)


def check_t_end(t_end) -> None:
    if _concrete(t_end):
        value = float(np.asarray(t_end))
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"t_end must be a finite time > 0 (seconds), got {value!r}")
