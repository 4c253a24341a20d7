"""Levenberg-Marquardt as an optax gradient transformation.

For a robust least-squares loss ``L(theta) = sum_i rho(r_i(theta) / s)``, one step of
iteratively reweighted Gauss-Newton with Levenberg-Marquardt damping solves

    (J^T W J + lambda diag(J^T W J)) delta = -J^T W r,        W = diag(w(r_i / s)),

where J is the Jacobian of the residuals and w the robust weight ``rho'(u)/u``
(Levenberg 1944, Marquardt 1963; IRLS: Holland and Welsch 1977). The damping lambda shrinks
by ``decrease`` after a step that lowered the loss and grows by ``increase`` after one that
did not, so the method moves between Gauss-Newton (fast near the optimum, where the loss is
nearly quadratic) and short gradient steps (safe far from it).

In optax's form: ``init(params) -> state`` and ``update(grads, state, params, *, jacobian,
residuals, weights, value) -> (updates, state)``. ``value`` is the loss at ``params``; the
transformation remembers the best point seen and, when ``value`` is worse, steps back from
the current point to it with more damping (the step is computed from the stored Jacobian).
So each iteration costs one residual-and-Jacobian evaluation. ``grads`` is unused (the
gradient is ``J^T W r``).

Example:
    >>> opt = levenberg_marquardt()
    >>> state = opt.init(theta)
    >>> r, J = residuals(theta), jax.jacfwd(residuals)(theta)
    >>> updates, state = opt.update(None, state, theta, jacobian=J, residuals=r,
    ...                             weights=jnp.ones_like(r), value=0.5 * r @ r)
    >>> theta = optax.apply_updates(theta, updates)
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import optax


class LevenbergMarquardtState(NamedTuple):
    best_params: jnp.ndarray
    best_value: jnp.ndarray
    best_gradient: jnp.ndarray  # J^T W r at the best point
    best_hessian: jnp.ndarray  # J^T W J at the best point
    damping: jnp.ndarray


def levenberg_marquardt(
    damping: float = 1e-3, increase: float = 4.0, decrease: float = 3.0
) -> optax.GradientTransformationExtraArgs:
    """Levenberg-Marquardt steps on iteratively reweighted residuals (see module docstring)."""

    def init(params):
        n = params.shape[0]
        return LevenbergMarquardtState(
            best_params=params,
            best_value=jnp.asarray(jnp.inf, params.dtype),
            best_gradient=jnp.zeros(n, params.dtype),
            best_hessian=jnp.zeros((n, n), params.dtype),
            damping=jnp.asarray(damping, params.dtype),
        )

    def update(grads, state, params=None, *, jacobian, residuals, weights, value, **extra):
        del grads, extra
        Jw = jacobian * jnp.sqrt(weights)[:, None]
        gradient = Jw.T @ (residuals * jnp.sqrt(weights))
        hessian = Jw.T @ Jw
        better = jnp.isfinite(value) & (value < state.best_value)
        lam = jnp.where(better, state.damping / decrease, state.damping * increase)
        base = jnp.where(better, params, state.best_params)
        g = jnp.where(better, gradient, state.best_gradient)
        H = jnp.where(better, hessian, state.best_hessian)
        damped = H + jnp.diag(lam * (jnp.diag(H) + 1e-12))
        step = -jnp.linalg.solve(damped, g)
        step = jnp.where(jnp.all(jnp.isfinite(step)), step, 0.0)
        new_state = LevenbergMarquardtState(
            best_params=base,
            best_value=jnp.where(better, value, state.best_value),
            best_gradient=g,
            best_hessian=H,
            damping=lam,
        )
        return base + step - params, new_state

    return optax.GradientTransformationExtraArgs(init, update)
