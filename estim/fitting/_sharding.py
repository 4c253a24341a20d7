"""The batch axis of a fit (balls, clips) split over devices with ``jax.sharding``.

A fit's work is one program over its units: each unit's simulation and linearisation
(:func:`per_unit`), then steps whose reductions over units are sums. Placing the unit axis
on a one-axis :class:`jax.sharding.Mesh` splits the program over the devices: each device
runs the units it holds (``jax.shard_map``), and XLA turns the sums into all-reduces. The
batch is padded to a multiple of the number of devices with units whose samples are all
masked (they contribute nothing). On several hosts (``jax.distributed``) every process
builds its own shards from the same host arrays and gathers the results back.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["gather", "mesh_of", "padded_size", "per_unit", "place"]

AXIS = "units"


def mesh_of(devices=None) -> Mesh | None:
    """A one-axis mesh over ``devices`` (default: every device JAX sees), or ``None`` for
    a single device (the program then runs unsharded)."""
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("no devices to run on")
    return Mesh(np.array(devices), (AXIS,)) if len(devices) > 1 else None


def padded_size(n: int, mesh: Mesh | None) -> int:
    """``n`` rounded up to a multiple of the mesh's devices."""
    k = 1 if mesh is None else mesh.size
    return -(-n // k) * k


def place(x, mesh: Mesh | None):
    """Put a ``(units, ...)`` array on the mesh, split along its first axis
    (``jax.make_array_from_callback``: each process supplies its own shards)."""
    x = np.asarray(x)
    if mesh is None:
        return jnp.asarray(x)
    sharding = NamedSharding(mesh, PartitionSpec(AXIS, *([None] * (x.ndim - 1))))
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])


def per_unit(fn, mesh: Mesh | None, *xs):
    """``fn`` applied to each unit of ``xs`` (pytrees of arrays with the units on their
    first axis), one unit after the other (``jax.lax.map``); on a mesh, each device maps
    over the units it holds (``jax.shard_map``).

    A loop, not ``vmap``: a unit's simulation is an event loop full of branches, and a
    batch of it would run every branch of each ``cond`` for every unit and every loop as
    long as the longest unit's, and trace the whole loop once more for the batch (``estim
    fit`` of one table-tennis shot from process start: 20 s batched, 11 s as a loop, with
    the same values; 20 pixel drops fitted together: 7.0 s batched, 6.6 s as a loop,
    compiled; 2-core reference machine, jax 0.10.2)."""

    def local(*xs):
        return jax.lax.map(lambda x: fn(*x), xs)

    if mesh is None:
        return local(*xs)
    return jax.shard_map(local, mesh=mesh, in_specs=PartitionSpec(AXIS), out_specs=PartitionSpec(AXIS),
                         check_vma=False)(*xs)


def gather(tree):
    """Host (NumPy) copies of the arrays of ``tree``, from every process in a multi-host run."""
    if jax.process_count() > 1:  # several processes (tests/test_pooled.py runs two)
        return multihost_utils.process_allgather(tree, tiled=True)
    return jax.device_get(tree)
