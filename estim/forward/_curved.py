"""Contact times on the curved pieces of a box grown by the ball's radius: its edges and
corners (``estim.model._scene``, equation (1)).

Piece m of a box (two or three nonzero components) is the set of centres at distance r
from the box's edge or vertex ``anchor = c + m h`` (the free axis of an edge, where
m_i = 0, does not count):

    D(q) = |M (q - anchor)|^2 - r^2 = 0,        M = diag(|m|).

Along a parabola ``q(tau) = p + v tau + a tau^2 / 2`` the vector
``P(tau) = M (q(tau) - anchor) = A + B tau + C tau^2`` (A = M (p - anchor), B = M v,
C = M a / 2) makes D a polynomial of degree four:

    D(tau)    = |P|^2 - r^2,
    D'(tau)   = 2 P . P',
    D''(tau)  = 2 (P' . P' + 2 P . C),     a quadratic: 12 |C|^2 tau^2 + 12 (B . C) tau + 2 (|B|^2 + 2 A . C),
    D'''(tau) = 12 P' . C,                 linear, zero at s0 = -(B . C) / (2 |C|^2).

The ball enters the piece where D falls through zero. Every root is found, none missed:

1. the roots of D'' (closed form) and s0 split [0, T] into at most four intervals on which
   D' is monotone and of one convexity; each holds at most one root of D', found by
   bisection and then Newton's method started from the end where ``D' D''' > 0`` (Fourier's
   condition: the iterates approach the root monotonically, from that side, and never leave
   the bracket);
2. those critical points of D and the roots of D'' split [0, T] into at most six intervals
   on which D is monotone and of one convexity; an interval where D goes from positive to
   non-positive holds exactly one entering root, found the same way.

The search runs over the window ``[start, T]`` the caller gives (where the flight can be near
the piece at all, before its earliest contact with a flat face, after which nothing
matters), T at most Cauchy's bound ``1 + max_k |c_k| / c_4`` on every root. Where
C = 0 (a vertical edge in vacuum, or a slide) D is a quadratic with one entering root in
closed form. D and its derivatives are evaluated from P, not from the expanded
coefficients, so that they keep their precision near the surface.

The time found is differentiable by the implicit-function theorem: with tau* held fixed,
``tau = tau* - (D(tau*; theta) - D(tau*)) / D'(tau*)`` has the value tau* and the
derivative ``-dD/dtheta / D'`` of the event time, as on a flat face.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._fold import inner
from ._constants import CURVED_BISECTIONS, CURVED_NEWTONS

__all__ = ["entering_times", "piece_normal", "distance_terms"]



def distance_terms(p, v, a, anchor, mask):
    """``A, B, C`` of ``P(tau) = A + B tau + C tau^2`` (module docstring)."""
    return mask * (p - anchor), mask * v, 0.5 * mask * a


def _poly(A, B, C, r):
    """D and its derivatives at tau, for tau with one more axis than A (the intervals)."""
    A, B, C = A[..., None, :], B[..., None, :], C[..., None, :]

    def at(tau):
        t = tau[..., None]
        P = A + B * t + C * t * t
        dP = B + 2.0 * C * t
        return P, dP

    def D(tau):
        P, dP = at(tau)
        return inner(P, P) - r[..., None] ** 2, 2.0 * inner(P, dP), 2.0 * (inner(dP, dP) + 2.0 * inner(P, C))

    def dD(tau):  # halves of D', D'', D'''
        P, dP = at(tau)
        return inner(P, dP), inner(dP, dP) + 2.0 * inner(P, C), 6.0 * inner(dP, C)

    return D, dD


def _bracketed_root(f, lo, hi):
    """The root of f in each bracket [lo, hi] (f(lo), f(hi) of opposite signs, f monotone
    and of one convexity there; f returns value, slope and curvature)."""

    def bisect(_, b):
        lo, hi, f_lo = b
        mid = 0.5 * (lo + hi)
        f_mid = f(mid)[0]
        right = (f_mid > 0) == (f_lo > 0)  # the sign changes in [mid, hi]
        return jnp.where(right, mid, lo), jnp.where(right, hi, mid), jnp.where(right, f_mid, f_lo)

    lo, hi, _ = jax.lax.fori_loop(0, CURVED_BISECTIONS, bisect, (lo, hi, f(lo)[0]))
    value, _, curvature = f(lo)
    start = jnp.where(value * curvature > 0, lo, hi)

    def newton(_, t):
        value, slope, _ = f(t)
        ok = slope != 0
        return jnp.clip(t - jnp.where(ok, value / jnp.where(ok, slope, 1.0), 0.0), lo, hi)

    return jax.lax.fori_loop(0, CURVED_NEWTONS, newton, start)


def _quadratic_roots(a2, a1, a0):
    """Real roots of ``a2 t^2 + a1 t + a0`` (a2 > 0), NaN where none, smaller first."""
    disc = a1 * a1 - 4.0 * a2 * a0
    s = jnp.sqrt(jnp.where(disc > 0, disc, 0.0))
    q = -0.5 * (a1 + jnp.where(a1 >= 0, s, -s))  # no cancellation (Numerical Recipes 5.6)
    safe_q = jnp.where(q != 0, q, 1.0)
    r1, r2 = q / jnp.where(a2 != 0, a2, 1.0), jnp.where(q != 0, a0 / safe_q, 0.0)
    lo, hi = jnp.minimum(r1, r2), jnp.maximum(r1, r2)
    real = (disc > 0) & (a2 != 0)
    return jnp.where(real, lo, jnp.nan), jnp.where(real, hi, jnp.nan)


def _sorted(x):
    """``x`` sorted along its last axis (a few entries, no NaN), by a sorting network of
    minima and maxima (odd-even transposition: n rounds sort n entries; Knuth, TAOCP vol. 3,
    5.3.4). XLA:CPU runs ``sort`` as a call into its runtime library, and one such call in
    an event loop keeps the whole loop from being compiled into a single kernel
    (``estim._config``): with ``jnp.sort`` here a table-tennis shot in air took 280 us
    instead of 75."""
    xs = [x[..., i] for i in range(x.shape[-1])]
    for r in range(len(xs)):
        for i in range(r % 2, len(xs) - 1, 2):
            xs[i], xs[i + 1] = jnp.minimum(xs[i], xs[i + 1]), jnp.maximum(xs[i], xs[i + 1])
    return jnp.stack(xs, axis=-1)


def _intervals(breaks, start, horizon):
    """Sorted interval ends: the start, the breaks within [start, horizon] (others moved to
    the horizon), the horizon."""
    h, s = horizon[..., None], start[..., None]
    inside = jnp.isfinite(breaks) & (breaks > s) & (breaks < h)
    pts = _sorted(jnp.where(inside, breaks, h))
    return jnp.concatenate([s, pts], axis=-1), jnp.concatenate([pts, h], axis=-1)


def entering_times(
    A: Float[Array, "*f 3"], B: Float[Array, "*f 3"], C: Float[Array, "*f 3"],
    r: Float[Array, "*f"], start: Float[Array, "*f"], horizon: Float[Array, "*f"],
) -> Float[Array, "*f 6"]:
    """Every time in ``(start, horizon]`` (``start >= 0``) at which D (module docstring)
    falls through zero, in increasing order, ``inf`` in unused slots. Values only (see
    ``implicit_time``)."""
    c4 = inner(C, C)
    quartic = c4 > 0
    c4s = jnp.where(quartic, c4, 1.0)
    c3, c2 = 2.0 * inner(B, C), inner(B, B) + 2.0 * inner(A, C)
    c1, c0 = 2.0 * inner(A, B), inner(A, A) - r * r
    cauchy = 1.0 + jnp.maximum(jnp.maximum(jnp.abs(c3), jnp.abs(c2)), jnp.maximum(jnp.abs(c1), jnp.abs(c0))) / c4s
    T = jnp.where(quartic, jnp.maximum(jnp.minimum(horizon, cauchy), start), 1.0)
    start = jnp.where(quartic, start, 0.0)
    D, dD = _poly(A, B, C, r)

    # 1. Critical points of D.
    sa, sb = _quadratic_roots(6.0 * c4s, 6.0 * inner(B, C), inner(B, B) + 2.0 * inner(A, C))
    s0 = -inner(B, C) / (2.0 * c4s)
    lo, hi = _intervals(jnp.stack([sa, s0, sb], axis=-1), start, T)
    d_lo, d_hi = dD(lo)[0], dD(hi)[0]
    change = (d_lo > 0) != (d_hi > 0)
    crit = jnp.where(change, _bracketed_root(dD, lo, jnp.where(change, hi, lo)), jnp.nan)

    # 2. Entering roots of D between them.
    lo, hi = _intervals(jnp.concatenate([crit, jnp.stack([sa, sb], axis=-1)], axis=-1), start, T)
    enters = (D(lo)[0] > 0) & (D(hi)[0] <= 0) & (hi > lo)
    roots = jnp.where(enters, _bracketed_root(D, lo, jnp.where(enters, hi, lo)), jnp.inf)

    # C = 0: D = |B|^2 tau^2 + 2 A.B tau + |A|^2 - r^2 enters once, at its smaller root,
    # written 2 c0 / (-c1 + s) free of cancellation (it enters only if c0 > 0 > c1).
    disc = c1 * c1 - 4.0 * c2 * c0
    s = jnp.sqrt(jnp.where(disc > 0, disc, 0.0))
    ok = (disc > 0) & (c0 > 0) & (c1 < 0)
    flat = jnp.where(ok, 2.0 * c0 / jnp.where(ok, s - c1, 1.0), jnp.inf)
    flat = jnp.where(flat <= jnp.maximum(horizon, start), flat, jnp.inf)
    only = jnp.full_like(roots, jnp.inf).at[..., 0].set(flat)
    return jnp.where(quartic[..., None], roots, only)


def implicit_time(tau_star, A, B, C, r):
    """The root ``tau_star`` of D (found with values only) as a differentiable function of
    A, B, C and r: its value is tau_star, its derivative ``-dD/dtheta / D'(tau_star)``."""
    t = jax.lax.stop_gradient(tau_star)
    P = A + B * t + C * t * t
    value = inner(P, P) - r * r
    slope = jax.lax.stop_gradient(2.0 * inner(P, B + 2.0 * C * t))
    ok = slope < 0
    return t - jnp.where(ok, (value - jax.lax.stop_gradient(value)) / jnp.where(ok, slope, -1.0), 0.0)


def piece_normal(q, anchor, mask):
    """Unit outward normal of a curved piece at the centre q: from the nearest point of the
    edge or vertex to q."""
    P = mask * (q - anchor)
    n = jnp.sqrt(inner(P, P))
    return P / jnp.where(n > 0, n, 1.0)[..., None]
