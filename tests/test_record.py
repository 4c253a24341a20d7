"""The packed storage of a Trajectory (estim.forward._record): the views give back exactly what was
packed, a ball's views are the batch's views at its index, and a jitted simulate hands
back the few packed arrays, not one array per field."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_ROUNDING, SEED_T_END, G, run, seed_arrays

import estim
from estim.forward._record import layout_of, pack, unpack
from estim.forward._trajectory import Events, State


def _parts(rng, batch):
    n = int(np.prod(batch))

    def f(*shape):
        return jnp.asarray(rng.normal(size=batch + shape))

    events = Events(
        t=f(5), position=f(5, 3), velocity_pre=f(5, 3), velocity_post=f(5, 3),
        face=jnp.asarray(rng.integers(-1, 90, size=batch + (5,)), jnp.int32),
        kind=jnp.asarray(rng.integers(-1, 2, size=batch + (5,)), jnp.int32),
        count=jnp.asarray(rng.integers(0, 6, size=batch), jnp.int32),
        truncated=jnp.asarray(rng.integers(0, 2, size=batch), bool),
    )
    assert n > 0
    return {"position": f(4, 3), "events": events, "final": State(f(), f(3), f(3)),
            "index": jnp.asarray(rng.integers(0, 2**40, size=batch), jnp.int64) % 1000}


@pytest.mark.parametrize("batch", [(), (3,), (2, 4)])
def test_pack_unpack_round_trip(batch):
    parts = _parts(np.random.default_rng(0), batch)
    layout = layout_of(parts, len(batch))
    numbers, integers = pack(parts, layout, batch)
    assert numbers.shape == batch + (layout.n_numbers,) and numbers.dtype == jnp.float64
    assert integers.shape == batch + (layout.n_integers,) and integers.dtype == jnp.int32
    for name, tree in parts.items():
        for rows in ((numbers, integers), (np.asarray(numbers), np.asarray(integers))):  # JAX or NumPy rows
            back = unpack(*rows, layout, name)
            assert jax.tree.structure(back) == jax.tree.structure(tree)
            for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(tree), strict=True):
                assert a.shape == b.shape and a.dtype == b.dtype
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_trajectory_views_and_indexing(stairs):
    traj = run(stairs, *seed_arrays(stairs), SEED_T_END)  # the suite's padded batch
    # The two rows and the clock (the sample times, then g): what a jitted call hands back.
    assert len(jax.tree.leaves(traj)) == 3
    np.testing.assert_array_equal(np.asarray(traj.ts), np.asarray(traj.clock)[:-1])
    assert float(traj.gravity) == G and float(traj[1].gravity) == G
    np.testing.assert_array_equal(np.asarray(traj[1].ts), np.asarray(traj.ts))
    # Under vmap the clock gains the mapped axis, and so do ts and gravity.
    golf = estim.Params.for_ball(stairs, "golf", e=0.7, mu_t=0.98, velocity=(1.15, 0.0, 0.0))
    mapped = jax.vmap(lambda t: estim.simulate(stairs, golf, t, keep=()))(jnp.array([1.0, 2.0]))
    np.testing.assert_array_equal(np.asarray(mapped.ts), [[0.0, 1.0], [0.0, 2.0]])
    np.testing.assert_array_equal(np.asarray(mapped.gravity), [G, G])
    n = traj.record.shape[0]
    for i in (0, 1, n - 1):
        one = traj[i]
        whole = (traj.position, traj.velocity, traj.events, traj.final, traj.complete)
        for a, b in zip(jax.tree.leaves((one.position, one.velocity, one.events, one.final, one.complete)),
                        [x[i] for x in jax.tree.leaves(whole)], strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(one.evaluate(jnp.array([0.4, 1.1]))[0]),
                                      np.asarray(traj.evaluate(jnp.array([0.4, 1.1]))[0][i]))
    assert traj[:2].record.shape[0] == 2
    # Views of concrete rows are JAX arrays (sliced on the host); of NumPy rows, NumPy arrays.
    assert all(isinstance(x, jax.Array) for x in jax.tree.leaves(traj.events))
    host = jax.tree.map(np.asarray, traj)
    assert all(isinstance(x, np.ndarray) for x in jax.tree.leaves(host.events))
    with pytest.raises(IndexError, match="batch axes"):
        traj[..., 0]
    with pytest.raises(IndexError, match="batch axes"):
        traj[0, 1]


def test_jitted_simulate_returns_the_packed_arrays(stairs):
    golf = estim.Params.for_ball(stairs, "golf", e=0.7, mu_t=0.98, velocity=(1.15, 0, 0))
    out = jax.jit(lambda p: estim.simulate(stairs, p, 2.3))(golf)
    assert [x.shape[-1:] for x in jax.tree.leaves(out)][:1] == [(3,)]  # the clock: ts, then g
    assert len(jax.tree.leaves(out)) == 3
    eager = estim.simulate(stairs, golf, 2.3)
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(eager), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_keep_computes_only_what_it_keeps(stairs):
    balls = estim.Params(jnp.array([0.3, 0.7, 0.95]), 0.98, 0.05, jnp.array([-0.2, 0.0, 1.70]), (1.15, 0.0, 0.0))
    ts = jnp.linspace(0.0, 2.3, 5)
    full = estim.simulate(stairs, balls, 2.3, ts=ts)
    for keep in ((), ("events",), ("samples", "solution"), "samples"):
        part = estim.simulate(stairs, balls, 2.3, ts=ts, keep=keep)
        kept = {keep} if isinstance(keep, str) else set(keep)
        # What is kept is what the full trajectory has (to rounding: another program, so
        # multiply-adds may be fused differently; integers exactly); the rest is an error.
        views = {"final": lambda t: t.final, "samples": lambda t: (t.position, t.velocity),
                 "events": lambda t: t.events, "solution": lambda t: t.solution}
        for name, view in views.items():
            if name == "final" or name in kept:
                for a, b in zip(jax.tree.leaves(view(part)), jax.tree.leaves(view(full)), strict=True):
                    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=BATCH_ROUNDING, atol=BATCH_ROUNDING)
                    assert a.dtype == b.dtype
            else:
                with pytest.raises(ValueError, match=f"keep=.*pass keep=... with '{name}'"):
                    view(part)
        assert part.record.shape[-1] <= full.record.shape[-1]
    assert estim.simulate(stairs, balls, 2.3, keep=()).record.shape[-1] == 7  # t, position, velocity
    with pytest.raises(ValueError, match="keep may name 'samples', 'events', 'solution'.*got 'final'"):
        estim.simulate(stairs, balls, 2.3, keep=("final",))


def test_keep_on_the_ode_path(stairs):
    air = stairs.with_air(estim.Air(density=1.204))
    golf = estim.Params.for_ball(air, "golf", e=0.7, mu_t=0.98, velocity=(1.15, 0, 0))
    full = estim.simulate(air, golf, 1.0)
    part = estim.simulate(air, golf, 1.0, keep=("events",))
    np.testing.assert_allclose(np.asarray(part.final.position), np.asarray(full.final.position),
                               rtol=BATCH_ROUNDING, atol=BATCH_ROUNDING)
    np.testing.assert_allclose(np.asarray(part.events.t), np.asarray(full.events.t), rtol=BATCH_ROUNDING)
    with pytest.raises(ValueError, match="has no solution"):
        part.evaluate(0.5)
