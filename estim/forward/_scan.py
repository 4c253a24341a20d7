"""A scan that does the work of only the items in use.

Both solvers record a solution in fixed-size slots (``max_segments`` segments, ``max_steps``
ODE steps) and replay it with ``lax.scan`` for derivatives. A ball uses only some slots:
7 of 48 segments for the seed's golf ball, about 500 of 2048 steps in still air. A plain
scan pays for every slot. ``scan_used`` cuts the slots into ``C ~ sqrt(S)`` chunks and
skips (``lax.cond``) each chunk that starts past the last slot in use, so the work is that
of the used slots plus at most one chunk, and ``S / C`` branch decisions.

Where the skipped chunks are cheap (a branch inside one compiled loop kernel, the ODE
path's replay) and the slots used few (a table-tennis shot: 19 of 2048 ODE steps), a smaller
chunk wastes fewer steps: the ODE path takes chunks of ``REPLAY_CHUNK`` (16) steps.

The skip is a real branch only where the number of used slots is one number for the whole
batch: inside ``vmap`` a per-ball count turns ``cond`` into ``select``, which runs both
branches (correct, no saving). So the ODE path plans all balls first and passes the batch's
largest count; the closed-form path simulates one ball at a time (``estim.forward._simulate``) and
passes the ball's own. The scan stays a scan, so reverse mode works as before.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np


def scan_used(f: Callable, init, xs, n_used, idle: Callable, fill, chunk: int | None = None):
    """``lax.scan(f, init, xs)`` for a scan whose items from ``n_used`` on are idle.

    An idle item (``fill``, and every item of ``xs`` from index ``n_used``) must leave the
    carry unchanged, and ``f`` must return ``idle(carry)`` for it: chunks made of idle items
    only are not run but filled with ``idle(carry)``. ``n_used`` may be traced; where it is
    batched the result is still exact. ``chunk``: items per chunk (default ``sqrt(S)``).
    """
    length = jax.tree.leaves(xs)[0].shape[0]
    chunk = max(1, math.isqrt(length) if chunk is None else min(int(chunk), length))
    n_chunks = -(-length // chunk)
    pad = n_chunks * chunk - length

    def pad_and_split(x, x_fill):
        # NumPy items (slot indices) stay NumPy: constants of the program, not kernels
        # that compute them at every call.
        xp = np if isinstance(x, np.ndarray) and isinstance(x_fill, int | np.ndarray) else jnp
        x = xp.concatenate([x, xp.broadcast_to(x_fill, (pad,) + x.shape[1:]).astype(x.dtype)])
        return x.reshape((n_chunks, chunk) + x.shape[1:])

    chunks = jax.tree.map(pad_and_split, xs, fill)

    def run(carry, xs_c):
        return jax.lax.scan(f, carry, xs_c)

    def skip(carry, xs_c):
        out = idle(carry)
        return carry, jax.tree.map(lambda y: jnp.broadcast_to(y, (chunk,) + jnp.shape(y)), out)

    def body(carry, inp):
        k, xs_c = inp
        return jax.lax.cond(k * chunk < n_used, run, skip, carry, xs_c)

    carry, ys = jax.lax.scan(body, init, (np.arange(n_chunks), chunks))
    ys = jax.tree.map(lambda y: y.reshape((n_chunks * chunk,) + y.shape[2:])[:length], ys)
    return carry, ys
