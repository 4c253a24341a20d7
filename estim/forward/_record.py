"""Per-ball records: a pytree of arrays stored as one row of numbers and one of integers.

A jitted function hands back every array of its result as a buffer of its own, and on the
CPU each costs about 1.5 us (a device buffer, a Python array object); XLA also runs one
more small kernel per array a loop writes. A trajectory is some 30 arrays per ball
(samples, events, final state, the dense solution), so :class:`estim.Trajectory` stores
them packed, and reads them back through views:

    >>> layout = layout_of({"final": state, "events": events}, batch_ndim=1)
    >>> numbers, integers = pack({"final": state, "events": events}, layout, (n,))
    >>> unpack(numbers, integers, layout, "events")  # events again (same shapes, dtypes)

Floating-point leaves go to the numbers (float64), integer and boolean leaves to the
integers (int32; booleans come back as booleans). Slicing a view is free inside ``jit``
and one small operation per leaf outside it.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class Leaf(NamedTuple):
    """Where one leaf lives: columns ``start:stop`` of the numbers or the integers."""

    integer: bool
    start: int
    stop: int
    shape: tuple[int, ...]  # the leaf's shape after the batch axes
    dtype: str


class Layout(NamedTuple):
    """The static description of packed named trees (hashable: it is part of a pytree's
    structure, as a static field)."""

    parts: tuple[tuple[str, Any, tuple[Leaf, ...]], ...]  # (name, treedef, leaves)
    n_numbers: int
    n_integers: int


def layout_of(parts: dict[str, Any], batch_ndim: int) -> Layout:
    """The layout of the named trees ``parts``, whose leaves all start with ``batch_ndim``
    batch axes, one after the other in the rows."""
    numbers = integers = 0
    laid = []
    for name, tree in parts.items():
        flat, treedef = jax.tree.flatten(tree)
        leaves = []
        for x in flat:
            shape = tuple(np.shape(x)[batch_ndim:])
            dtype = np.dtype(jnp.result_type(x))
            size = math.prod(shape)
            integer = not jnp.issubdtype(dtype, jnp.floating)
            start = integers if integer else numbers
            leaves.append(Leaf(integer, start, start + size, shape, dtype.name))
            if integer:
                integers += size
            else:
                numbers += size
        laid.append((name, treedef, tuple(leaves)))
    return Layout(tuple(laid), numbers, integers)


def pack(parts: dict[str, Any], layout: Layout, batch_shape: tuple[int, ...] = ()):
    """The rows of ``parts`` (laid out by ``layout``): ``(numbers, integers)`` of shapes
    ``(*batch, n_numbers)`` float64 and ``(*batch, n_integers)`` int32."""
    numbers, integers = [], []
    for (name, _, leaves) in layout.parts:
        for x, leaf in zip(jax.tree.leaves(parts[name]), leaves, strict=True):
            row = jnp.reshape(x, batch_shape + (leaf.stop - leaf.start,))  # (not -1: a batch may be empty)
            if leaf.integer:
                integers.append(row.astype(jnp.int32))
            else:
                numbers.append(row.astype(jnp.float64))

    def join(rows, dtype):
        return jnp.concatenate(rows, axis=-1) if rows else jnp.zeros(batch_shape + (0,), dtype)

    return join(numbers, jnp.float64), join(integers, jnp.int32)


def unpack(numbers, integers, layout: Layout, name: str):
    """The tree ``name`` of ``layout`` from the rows ``numbers`` and ``integers`` (NumPy
    or JAX arrays, any batch shape)."""
    batch = numbers.shape[:-1]
    treedef, leaves = next((t, ls) for n, t, ls in layout.parts if n == name)
    out = []
    for leaf in leaves:
        rows = integers if leaf.integer else numbers
        x = rows[..., leaf.start:leaf.stop].reshape(batch + leaf.shape)
        out.append(x != 0 if leaf.dtype == "bool" else x.astype(leaf.dtype))
    return jax.tree.unflatten(treedef, out)
