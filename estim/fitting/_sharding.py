"""The batch axis of a fit (balls, clips) split over devices with ``jax.sharding``.

A fit's work is one batched program over its units (``vmap``), and every reduction over
units is a sum; placing the unit axis on a one-axis :class:`jax.sharding.Mesh` lets XLA
split the program over the devices and turn those sums into all-reduces, with no change to
the program. The batch is padded to a multiple of the number of devices with units whose
samples are all masked (they contribute nothing). On several hosts
(``jax.distributed``) every process builds its own shards from the same host arrays and
gathers the results back.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["gather", "mesh_of", "padded_size", "place"]

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


def gather(tree):
    """Host (NumPy) copies of the arrays of ``tree``, from every process in a multi-host run."""
    if jax.process_count() > 1:  # pragma: no cover - needs several hosts
        return multihost_utils.process_allgather(tree, tiled=True)
    return jax.device_get(tree)
