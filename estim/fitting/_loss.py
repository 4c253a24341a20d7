"""Residuals between the model and observed positions, and robust losses.

For samples ``y_i`` (metres) observed at times ``t_i`` with a mask of valid coordinates,
the residuals are ``r_i = x(t_i; theta) - y_i`` on valid coordinates and 0 elsewhere. A
robust loss ``sum_i rho(r_i / s)`` with a scale s (the noise level) keeps tracker outliers
from dragging the fit:

- ``"l2"``: rho(u) = u^2 / 2;
- ``"huber"``: rho(u) = u^2/2 for |u| <= c, c |u| - c^2/2 beyond, c = 1.345 (95% efficiency
  at Gaussian noise; Huber 1964);
- ``"cauchy"``: rho(u) = c^2/2 log(1 + (u/c)^2), c = 2.385 (95% efficiency; Holland and
  Welsch 1977). Gross outliers get a weight ~ (c s / r)^2, i.e. almost none.

Minimising a robust loss by Gauss-Newton is iteratively reweighted least squares: each step
solves a weighted least-squares problem with weights ``w(u) = rho'(u) / u``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["ROBUST_LOSSES", "robust_curvature", "robust_loss", "robust_weight"]

ROBUST_LOSSES = ("l2", "huber", "cauchy")
_HUBER_C = 1.345
_CAUCHY_C = 2.385


def array_namespace(x):
    """jax.numpy for JAX arrays (inside traced programs), numpy otherwise: host-side
    arithmetic on a few numbers stays NumPy instead of compiling JAX operations one by one."""
    return jnp if isinstance(x, jax.Array) else np


def robust_loss(u, kind: str):
    """rho(u) for standardised residuals u = r / s."""
    xp = array_namespace(u)
    if kind == "l2":
        return 0.5 * u * u
    if kind == "huber":
        a = xp.abs(u)
        return xp.where(a <= _HUBER_C, 0.5 * u * u, _HUBER_C * a - 0.5 * _HUBER_C**2)
    if kind == "cauchy":
        return 0.5 * _CAUCHY_C**2 * xp.log1p((u / _CAUCHY_C) ** 2)
    raise ValueError(f"unknown robust loss {kind!r}; choose one of {ROBUST_LOSSES}")


def robust_weight(u, kind: str):
    """IRLS weight rho'(u) / u."""
    xp = array_namespace(u)
    if kind == "l2":
        return xp.ones_like(u)
    if kind == "huber":
        a = xp.abs(u)
        return xp.where(a <= _HUBER_C, 1.0, _HUBER_C / xp.maximum(a, _HUBER_C))
    if kind == "cauchy":
        return 1.0 / (1.0 + (u / _CAUCHY_C) ** 2)
    raise ValueError(f"unknown robust loss {kind!r}; choose one of {ROBUST_LOSSES}")


def robust_curvature(u, kind: str):
    """rho''(u), the slope of the influence function psi(u) = rho'(u) = u w(u): the
    weight of a residual in the Hessian of the loss (the "bread" of an M-estimator's
    covariance, Huber 1967), where IRLS uses w(u). Negative for the Cauchy loss beyond
    |u| = c, 0 for Huber's beyond c."""
    xp = array_namespace(u)
    if kind == "l2":
        return xp.ones_like(u)
    if kind == "huber":
        return xp.where(xp.abs(u) <= _HUBER_C, 1.0, 0.0)
    if kind == "cauchy":
        a2 = (u / _CAUCHY_C) ** 2
        return (1.0 - a2) / (1.0 + a2) ** 2
    raise ValueError(f"unknown robust loss {kind!r}; choose one of {ROBUST_LOSSES}")
