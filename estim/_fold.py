"""Reductions over short axes, written out as elementwise operations.

Where estim's event loops are compiled into one XLA:CPU kernel (``estim._config``), each
``reduce`` in them (a ``jnp.sum``, ``min``, ``any``...) brings a reducer computation of its
own, and XLA:CPU's runtime creates and frees a handle for each value of each such
computation at *every call* of the program (its thread-local buffers, in
``CpuPjRtRawLoadedExecutable::Execute``), whether or not the call runs it: about 0.1 us per
value, three values per reducer. The table-tennis shot's forward program had 129 reducers,
387 of its 632 buffers (``perf`` put 30% of its time per call in the runtime's
``CreateConstantMemory`` and the freeing of those handles). Written out as elementwise
operations, a reduction fuses into the kernel around it and costs nothing per call; but it
makes the program larger (XLA fuses what it reduces into each term), so estim writes out
only the reductions that are many: the air's, in the vector field that every Runge-Kutta
stage of every step calls (34 of the 129), and the few of the ODE path's step. Written out
everywhere (the contact search's reductions over a scene's faces too), the shot's forward
took 100 us instead of 105-108 us but its fit program grew by 13% instead of 5.5%.

Axes of up to ``LONGEST`` entries are written out; a longer one is reduced as usual.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

__all__ = ["inner", "total", "least", "some", "first_least"]

# The longest axis written out.
LONGEST = 8


def _halving(op, x, axis: int, reduce):
    """``x`` reduced along ``axis`` by ``op`` (associative, commutative and exact: min, or)
    in halves, ``op(first half, second half)`` until one entry is left."""
    x = jnp.asarray(x)
    if not 0 < x.shape[axis] <= LONGEST:
        return reduce(x, axis=axis)
    x = jnp.moveaxis(x, axis, -1)
    while x.shape[-1] > 1:
        n = x.shape[-1]
        half = n // 2
        head = op(x[..., :half], x[..., half : 2 * half])
        x = jnp.concatenate([head, x[..., 2 * half :]], axis=-1) if n % 2 else head
    return x[..., 0]


def total(x, axis: int = -1):
    """``jnp.sum(x, axis)``, summed left to right (the rounding of a loop)."""
    x = jnp.asarray(x)
    if not 0 < x.shape[axis] <= LONGEST:
        return jnp.sum(x, axis=axis)
    x = jnp.moveaxis(x, axis, -1)
    out = x[..., 0:1]
    for i in range(1, x.shape[-1]):
        out = out + x[..., i : i + 1]
    return jnp.squeeze(out, -1)


def least(x, axis: int = -1):
    """``jnp.min(x, axis)`` (NaN wins, as there)."""
    return _halving(jnp.minimum, x, axis, jnp.min)


def some(x, axis: int = -1) -> Bool[Array, "..."]:
    """``jnp.any(x, axis)``."""
    return _halving(jnp.logical_or, jnp.asarray(x, bool), axis, jnp.any)


def first_least(x, axis: int = -1) -> Int[Array, "..."]:
    """``jnp.argmin(x, axis)`` (int32): the first index of the least entry (with a NaN, an
    index in range, not necessarily the NaN's)."""
    x = jnp.moveaxis(jnp.asarray(x), axis, -1)
    n = x.shape[-1]
    if not 0 < n <= LONGEST:
        return jnp.argmin(x, axis=-1).astype(jnp.int32)
    return least(jnp.where(x == least(x)[..., None], jnp.arange(n, dtype=jnp.int32), n - 1))


def inner(x: Float[Array, "*n 3"], y: Float[Array, "*n 3"]) -> Float[Array, "*n"]:
    """``x . y`` over the last axis, written out: XLA:CPU compiles a ``dot`` as a call into
    a linear-algebra library, and one such call in an event loop keeps the whole loop from
    being compiled into a single kernel (``estim._config``). One product, then its
    components summed left to right: the same rounding as ``x0 y0 + x1 y1 + x2 y2`` (and
    the native kernels'), in half the operations of that form for JAX to differentiate and
    XLA to compile (the table-tennis shot's fit program: 15,200 instead of 19,600;
    ``jnp.sum`` of the product would make 13,700, but its reduction order under ``vmap``
    differed from the kernels' by an ulp)."""
    return total(x * y)
