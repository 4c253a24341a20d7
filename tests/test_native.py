"""The native kernels (estim/forward/_kernels.cc) against the JAX solver they port.

On the CPU, ``estim.simulate``, the fit and the sensitivities run the closed-form primal
on the native kernels and replay its structure in JAX for derivatives (estim.forward._native);
the rest of the suite tests that path against closed forms, finite differences and known
parameters. Here the independent truth is the JAX solver itself (``estim.forward._solver``,
``estim.forward._trajectory``, the path estim takes on other backends): the same discrete
structure, bit for bit, and the same numbers to rounding, ball by ball, over balls drawn
to hit every kind of segment, in both geometries. Where a ball's path is ill-conditioned
(micro-bounces on an edge's curve, a roll's energy near the top of its edge, a rebound at
REST_SPEED to 1%) the tests say so and by how much.
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ROOT, box_distance, grad_final_x, jac_args, jax_path
from test_exact_geometry import dropped_on_corners, sliding_off_treads

import estim
from estim.forward import _native
from estim.forward._constants import CONTACT, REST_SPEED
from estim.forward._contact import contact_normals
from estim.forward._record import pack, unpack
from estim.forward._simulate import flat_params
from estim.forward._solver import plan as jax_plan
from estim.forward.laws import FactorLaw

# Rounding: the kernel evaluates every closed form in the order the JAX code writes it,
# but its log, expm1 and pow are the C library's, not XLA's (which differ in the last
# bit), and a difference of an ulp in one event time carries through the later bounces.
# Measured over the balls below: at most 9.4e-14 relative to max(1, |x|) (s, m, m/s;
# 1.4e-13 on the scenes with exact edges);
# 1e-12 leaves a factor 10 and still catches any wrong formula, whose errors are of the
# size of the quantities themselves.
ROUNDING = 1e-12
# A roll's time and state pass through XLA's sinh, cosh and asinh (an ulp from the C
# library's) and through the pendulum's energy B = omega^2 - 4 k sin^2(theta / 2), a
# difference of nearly equal terms for a ball that just makes it over an edge
# (estim.forward._roll): over the rolls below at most 3e-12 s, 7e-13 m and 4e-11 m/s apart.
ROLLING = 1e-10


def test_kernels_are_built_and_used():
    """The install built estim/forward/_kernels.cc (it needs a C++ compiler; without one estim
    installs and runs the JAX solver), and on the CPU estim uses it."""
    assert _native.available(), "estim.forward._kernels was not built: pip install -e . needs a C++ compiler"
    assert jax.default_backend() == "cpu" and _native.active()


def balls_in(scene: estim.Scene, n: int, seed: int) -> estim.Params:
    """n balls released outside every solid: random radii, e and mu_t over [0, 1] with a
    share at the ends (e = 0 sticks, e = 1 never settles, mu_t = 1 slides off edges),
    slow and fast throws in every direction, some dropped at rest, over the whole scene;
    a third with a compression (a contact radius from 0.5 r to 1.3 r)."""
    rng = np.random.default_rng(seed)
    lo = np.minimum(np.min(np.asarray(scene.box_centre - scene.box_half), axis=0), -1.0)
    hi = np.maximum(np.max(np.asarray(scene.box_centre + scene.box_half), axis=0), 1.0)
    r = rng.choice([0.02, 0.05, 0.08, 0.2], n)
    pos = rng.uniform(lo - 0.3, hi + 0.6, (n, 3))
    pos[:, 1] = rng.choice([0.0, 0.0, rng.uniform(lo[1], hi[1])], n)
    pos[:, 2] = rng.uniform(0.1, hi[2] + 1.0, n)
    vel = rng.normal(0.0, 2.0, (n, 3)) * rng.choice([0.0, 0.3, 1.0, 5.0], (n, 1))
    e = np.where(rng.random(n) < 0.15, rng.choice([0.0, 1.0], n), rng.uniform(0, 1, n))
    mu = np.where(rng.random(n) < 0.2, 1.0, rng.uniform(0, 1, n))
    compression = np.where(rng.random(n) < 1 / 3, rng.uniform(-0.3, 0.5, n) * r, 0.0)
    depth = np.min(box_distance(pos, scene.box_centre, scene.box_half), axis=-1, initial=np.inf)
    height = np.min(pos @ np.asarray(scene.plane_normal).T - np.asarray(scene.plane_offset), axis=-1, initial=np.inf)
    reach = r - compression + 1e-6
    ok = (depth > reach) & (height > reach)
    return estim.Params(e[ok], mu[ok], r[ok], pos[ok], vel[ok], compression=compression[ok])


def yard(geometry: str) -> estim.Scene:
    return estim.Scene.from_arrays(
        boxes={"wall": ((3.1, 0.0, 0.5), (0.1, 2.0, 0.5)), "block": ((1.0, 0.5, 0.25), (0.25, 0.25, 0.25))},
        planes={"ground": ((0.0, 0.0, 1.0), 0.0), "side": ((0.0, -1.0, 0.0), -1.5)},
        gravity=9.81, geometry=geometry,
    )


# The kernels run both geometries: the seed's (a box is its faces; the seed scene declares
# it, the drop is given it) and exact edges and corners, with their rolls.
SCENES = {
    "stairs": lambda: estim.load_scene(ROOT / "data" / "scenes" / "stairs.xml"),
    "drop": lambda: estim.load_scene(ROOT / "data" / "scenes" / "drop.xml").with_geometry("seed"),
    "yard": lambda: yard("seed"),
    "stairs_exact": lambda: estim.load_scene(ROOT / "data" / "scenes" / "stairs_exact.xml"),
    "yard_exact": lambda: yard("exact"),
}


def test_exact_geometry_runs_on_the_kernels():
    """A scene with exact edges runs on the kernels; a law they do not implement (the
    friction law of the table-tennis scene) on the JAX planner, and the kernels' own entry
    point refuses it, saying why."""
    exact = estim.load_scene(ROOT / "data" / "scenes" / "stairs_exact.xml")
    assert exact.geometry == "exact" and _native.supports(FactorLaw(), exact) and _native.runs(exact)
    table = estim.load_scene(ROOT / "data" / "scenes" / "table_tennis.xml").with_air(None)
    assert not _native.runs(table)
    with pytest.raises(ValueError, match="do not support the contact law FrictionLaw"):
        _native.plan(table, estim.Params(0.5, 0.9, 0.02, (0.0, 0.0, 0.3), (1.0, 0.0, 0.0)), 1.0, 16)


def micro_bounces(scene: estim.Scene, plan, i: int) -> np.ndarray:
    """For each contact of ball i's plan, its normal speed after the impact (NaN where a
    segment ends otherwise)."""
    face, reason = np.asarray(plan.decisions.face[i]), np.asarray(plan.decisions.reason[i])
    normals = np.asarray(contact_normals(scene, np.maximum(face, 0), plan.segments.p1[i]))
    speed = np.abs(np.sum(np.asarray(plan.segments.v1_post[i]) * normals, axis=-1))
    return np.where(reason == CONTACT, speed, np.nan)


T_END, S = 3.0, 48  # the plans of the balls below


@pytest.fixture(scope="module")
def made():
    """What ``scene_balls`` made, by scene: pytest makes an indirectly parametrised fixture
    again for each parameter set that names the same scene."""
    return {}


@pytest.fixture(scope="module", params=list(SCENES))
def scene_balls(request, made):
    """A scene, 300 balls in it and their plans by the JAX planner (10-25 s a scene on
    exact geometry, made once for the tests of the scene)."""
    name = request.param
    if name not in made:
        scene = SCENES[name]()
        params = balls_in(scene, 300, seed=list(SCENES).index(name))
        made[name] = scene, params, jax.jit(jax.vmap(lambda p: jax_plan(scene, p, T_END, S)))(flat_params(params))
    return made[name]


def test_plan_matches_the_jax_planner(scene_balls):
    """The kernel's plan of each ball is the JAX planner's: every decision (kind, support,
    bounce count, why the segment ends, face) bit for bit, every segment to rounding."""
    scene, params, ref = scene_balls
    native = _native.plan(scene, params, T_END, S)
    kinds = set(np.unique(np.asarray(ref.decisions.kind)).tolist())
    assert kinds == ({0, 1, 2, 3, 4} if scene.geometry == "exact" else {0, 1, 2, 3}), \
        "the balls should make flights, trains, slides (and rolls over edges)"
    same = np.ones(params.e.shape[0], bool)
    for name in ("kind", "support", "n", "reason", "face", "n_segments", "complete"):
        holder = native if name in ("n_segments", "complete") else native.decisions
        a, b = np.asarray(getattr(holder, name)), np.asarray(getattr(ref if holder is native else ref.decisions, name))
        same &= np.all((a == b).reshape(a.shape[0], -1), axis=1)
    # Where the two part ways, it is at a rounding's distance from a threshold: a bounce on
    # an edge whose rebound is REST_SPEED to 1% (the ball rolls on one path, bounces once more
    # on the other; found once in 300 balls on the exact staircase).
    for i in np.flatnonzero(~same):
        first = np.argmax(np.asarray(native.decisions.kind[i]) != np.asarray(ref.decisions.kind[i]))
        assert abs(micro_bounces(scene, ref, i)[first - 1] / REST_SPEED - 1) < 0.01, f"ball {i} parts at slot {first}"
    assert np.mean(same) > 0.99
    # Bounces on an edge's curve magnify a difference in their state at each bounce (the
    # curve turns it into the next bounce's normal): a series of micro-bounces on an edge
    # (normal speeds below 1 mm/s) carries an ulp of the first to 1e-8 s and 1e-8 m/s
    # (both paths are as right). Elsewhere the numbers agree to rounding.
    ill = np.array([np.nanmin(micro_bounces(scene, ref, i), initial=np.inf) < 1e-3 for i in range(same.size)])
    for name in ("t0", "p0", "v0", "acc", "t1", "p1", "v1", "v1_post", "normal", "pivot"):
        a, b = np.asarray(getattr(native.segments, name)), np.asarray(getattr(ref.segments, name))
        np.testing.assert_allclose(a[same & ~ill], b[same & ~ill], rtol=ROUNDING, atol=ROUNDING, err_msg=name)
        np.testing.assert_allclose(a[same & ill], b[same & ill], rtol=1e-6, atol=1e-6, err_msg=name)


# Both sets of rolls below: 96 balls, 96 segments, the end time traced, so that their JAX
# plans and JAX-path samples are one program each (about 30 s of compile, 2-core machine).
ROLL_SEGMENTS = 96
roll_plans = jax.jit(jax.vmap(lambda scene, p, t_end: jax_plan(scene, p, t_end, ROLL_SEGMENTS), in_axes=(None, 0, None)))


@pytest.mark.parametrize("balls", ["sliding_off_treads", "dropped_on_corners"])
def test_rolls_match_the_jax_planner(balls):
    """Balls sliding off the treads of the exact staircase roll over edges, along them and
    onto corners; balls dropped onto corners roll over them off the vertical plane through
    the vertex (the spherical pendulum), then over edges (tests/test_exact_geometry.py
    checks them against geometry, energy and the ODE path): the kernels' plans are the JAX
    planner's, decision for decision, and their samples agree to rounding."""
    scene = SCENES["stairs_exact"]()
    params = sliding_off_treads(96, seed=1) if balls == "sliding_off_treads" else dropped_on_corners(96, seed=2)
    t_end, segments = (3.0 if balls == "sliding_off_treads" else 1.5), ROLL_SEGMENTS
    native = _native.plan(scene, params, t_end, segments)
    ref = roll_plans(scene, flat_params(params), t_end)
    kinds = np.asarray(ref.decisions.kind)
    spherical = np.any((kinds == 4) & np.all(np.asarray(ref.segments.normal) == 0, axis=-1), axis=1)
    assert np.sum(np.any(kinds == 4, axis=1)) >= 50 and np.all(np.asarray(ref.complete))
    assert np.sum(spherical) >= (50 if balls == "dropped_on_corners" else 0)
    for name in ("kind", "support", "n", "reason", "face"):
        np.testing.assert_array_equal(getattr(native.decisions, name), getattr(ref.decisions, name), err_msg=name)
    np.testing.assert_array_equal(native.complete, ref.complete)
    # (Over a corner near the plane through its vertex the spherical pendulum's closed form
    # loses digits to r - z2 ~ L^2, a difference of nearly equal numbers (estim.forward._roll.
    # Spherical): a roll with L = 4e-5 m^2/s ended 2e-13 s apart on the two sides, by their
    # sin, cos, asin and atan2, which a 1.5 s slide after it carried to 2e-10 m.)
    tol = ROLLING if balls == "sliding_off_treads" else 1e-9
    for name in ("t1", "p1", "v1", "v1_post", "normal", "pivot"):
        np.testing.assert_allclose(getattr(native.segments, name), getattr(ref.segments, name),
                                   rtol=tol, atol=tol, err_msg=name)
    ts = np.linspace(0.0, t_end, 301)
    traj = estim.simulate(scene, params, t_end, ts=ts, max_segments=segments, throw=False, keep=("samples",))
    with jax_path():
        ref_traj = estim.simulate(scene, params, t_end, ts=ts, max_segments=segments, throw=False, keep=("samples",))
    np.testing.assert_allclose(traj.position, ref_traj.position, rtol=tol, atol=tol)
    np.testing.assert_allclose(traj.velocity, ref_traj.velocity, rtol=tol, atol=tol)


# Every part on every scene; the layouts of what a caller keeps on one scene of each
# geometry (without and with edges: the two record layouts), each a program of its own.
KEEPS = {"all": None, "final": (), "events": ("events",), "samples+solution": ("samples", "solution")}


@pytest.fixture(scope="module")
def jax_trajectories():
    """The JAX path's whole trajectory of each scene's balls, by scene: what a layout keeps
    is its parts (about 12 s of compile per layout on exact geometry, 2-core machine)."""
    return {}


@pytest.mark.parametrize(("scene_balls", "keep"),
                         [pytest.param(name, KEEPS[k], id=f"{name}-{k}")
                          for name in SCENES for k in (KEEPS if name.startswith("stairs") else ["all"])],
                         indirect=["scene_balls"])
def test_trajectory_matches_the_jax_path(scene_balls, keep, jax_trajectories):
    """Samples, events, final state, completion and dense solution, packed: the kernel's
    rows are the JAX path's (integers bit for bit, numbers to rounding, padding alike), in
    the layout the JAX path gives what the caller keeps."""
    scene, params, plans = scene_balls
    ts = np.linspace(0.0, T_END, 37)
    traj = estim.simulate(scene, params, T_END, ts=ts, keep=keep, throw=False)
    with jax_path():
        if id(scene) not in jax_trajectories:
            jax_trajectories[id(scene)] = estim.simulate(scene, params, T_END, ts=ts, throw=False)
        layout = jax.eval_shape(lambda: estim.simulate(scene, params, T_END, ts=ts, keep=keep, throw=False)).layout
    whole = jax_trajectories[id(scene)]
    parts = {name: unpack(whole.record, whole.flags, whole.layout, name) for name, _, _ in layout.parts}
    record, flags = (np.asarray(x) for x in pack(parts, layout, whole.record.shape[:-1]))
    assert traj.layout == layout
    # (The balls whose plans part at a threshold, or that micro-bounce on an edge, as in
    # test_plan_matches_the_jax_planner: compared there.)
    ok = np.array([np.nanmin(micro_bounces(scene, plans, i), initial=np.inf) >= 1e-3
                   for i in range(params.e.shape[0])])
    np.testing.assert_array_equal(traj.flags[ok], flags[ok])
    np.testing.assert_allclose(traj.record[ok], record[ok], rtol=ROUNDING, atol=ROUNDING)


@pytest.mark.parametrize("geometry", ["seed", "exact"])
def test_derivatives_match_the_jax_path(geometry):
    """Forward and reverse mode through the kernel (its tangent replays the structure in
    JAX) give the JAX path's derivatives: final state, event times and samples with
    respect to e, mu_t, the release velocity and the sample times (a third of the balls
    compressed), on the staircase of either geometry. Both paths differentiate the same
    replay of a plan (``estim.forward._solver.segments_of``: the plan enters as values), so
    their forward modes are compared, and the kernel's reverse mode with its forward mode
    (the final x of each ball without compression with respect to its e, mu_t and vx0):
    the JAX path's reverse mode is the transpose of the same code (and its program would
    compile for about 105 s on exact geometry, 2-core machine)."""
    stairs = SCENES["stairs" if geometry == "seed" else "stairs_exact"]()
    params = balls_in(stairs, 40 if geometry == "seed" else 16, seed=7)
    ts = jnp.linspace(0.0, 2.0, 9)

    def outputs(e, mu_t, velocity, ts):
        p = estim.Params(e, mu_t, params.radius, params.position, velocity, compression=params.compression)
        traj = estim.simulate(stairs, p, 2.0, ts=ts, throw=False)
        return traj.final.position, jnp.where(jnp.isfinite(traj.events.t), traj.events.t, 0.0), traj.position

    args = (params.e, params.mu_t, params.velocity, ts)
    argnums = tuple(range(len(args)))
    jac = jax.jacfwd(outputs, argnums=argnums)(*args)
    with jax_path():
        jac_ref = jax.jacfwd(outputs, argnums=argnums)(*args)
    # (On exact geometry a ball whose bounces die out on an edge before it rolls over it
    # magnifies the last bit of each bounce, as test_plans_match_the_jax_planner allows for:
    # one ball here, its later event times' derivatives 7e-9 apart, 3e-8 relative, since
    # session 36, whose JAX programs round that ball an ulp differently (not from R_F's
    # unrolling: restored, it stayed 7e-9; the kernels' side did not change).)
    tol = 1e-9 if geometry == "seed" else 1e-7
    for x, y in zip(jax.tree.leaves(jac), jax.tree.leaves(jac_ref), strict=True):
        np.testing.assert_allclose(x, y, rtol=tol, atol=tol)
    # Reverse mode: each uncompressed ball's final x with respect to its (e, mu_t, vx0),
    # by conftest's compiled program (``grad_final_x``, the ball alone, padded), which
    # test_hard_cases and test_simulate run on these staircases (its reverse-mode program
    # compiles for 1-2 minutes a staircase: once a run, from the run's cache), against
    # the forward Jacobian's entries.
    diagonal = np.arange(params.e.shape[0])
    forward = np.stack([jac[0][0][diagonal, 0, diagonal], jac[0][1][diagonal, 0, diagonal],
                        jac[0][2][diagonal, 0, diagonal, 0]], axis=1)
    plain = np.flatnonzero(np.asarray(params.compression) == 0)
    assert plain.size >= params.e.shape[0] // 2
    for k in plain:
        padded, _ = jac_args(params.e[k], params.mu_t[k], params.radius[k], params.position[k],
                             params.velocity[k], 2.0)
        np.testing.assert_allclose(grad_final_x(stairs, *padded), forward[k], rtol=1e-9, atol=1e-12,
                                   err_msg=f"ball {k}")
    # (assert_allclose takes NaN for NaN: the final state's derivatives are finite in both
    # modes, which a NaN in both alike, as a roll off an edge from rest had, breaks.)
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(jac[0]))


def test_vmap_over_the_scene_and_t_end(stairs):
    """Under jax.vmap the kernel broadcasts whatever is batched (here the end time, and the
    staircase's geometry, moved as a whole): each item as its own call."""
    golf = estim.Params(0.7, 0.98, 0.05, (-0.2, 0.0, 1.7), (1.15, 0.0, 0.0))
    t_ends = jnp.array([0.5, 1.3, 2.3])
    shifts = jnp.array([0.0, 0.07, -0.05])

    def final(t_end, shift):
        scene = estim.Scene(stairs.box_centre.at[:, 0].add(shift), stairs.box_half, stairs.plane_normal,
                            stairs.plane_offset, stairs.gravity, stairs.names, stairs.face_solid,
                            stairs.face_direction)
        traj = estim.simulate(scene, golf, t_end, ts=jnp.linspace(0.0, 0.5, 5), keep=("samples", "events"))
        return traj.final.position, traj.events.t, traj.position

    batched = jax.vmap(final)(t_ends, shifts)
    batched_t = jax.vmap(final, in_axes=(0, None))(t_ends, 0.02)
    for k in range(3):
        for got, want in zip(batched, final(t_ends[k], shifts[k]), strict=True):
            np.testing.assert_array_equal(got[k], want)
        for got, want in zip(batched_t, final(t_ends[k], 0.02), strict=True):
            np.testing.assert_array_equal(got[k], want)


def test_a_large_batch_runs_in_parallel_with_the_same_results(stairs):
    """Large batches are shared among XLA's threads; a ball's result does not depend on
    which thread or batch it ran in (bit for bit)."""
    params = flat_params(balls_in(stairs, 1500, seed=3))
    n = params.e.shape[0]
    assert n > 256  # (the kernels share a batch among threads in blocks of 64 balls)
    ts = np.linspace(0.0, 2.0, 5)
    whole = estim.simulate(stairs, params, 2.0, ts=ts, throw=False)
    plans = _native.plan(stairs, params, 2.0, 48)
    for start in range(0, n, 100):
        part = jax.tree.map(lambda x, s=start: x[s:s + 100], params)
        one = estim.simulate(stairs, part, 2.0, ts=ts, throw=False)
        np.testing.assert_array_equal(whole.record[start:start + 100], one.record)
        np.testing.assert_array_equal(whole.flags[start:start + 100], one.flags)
        np.testing.assert_array_equal(plans.segments.p1[start:start + 100],
                                      _native.plan(stairs, part, 2.0, 48).segments.p1)


def test_checks_inside_jit_on_the_jax_path(stairs):
    """The JAX path checks the arguments inside jit as the kernel does, with the same
    message (tests/test_simulate.py checks them on the kernel)."""
    golf = stairs.ball("golf")

    @jax.jit
    def final(t_end):
        p = estim.Params(0.7, 0.98, golf.radius, jnp.array([-0.2, 0.0, 1.7]), jnp.array([1.15, 0.0, 0.0]))
        return estim.simulate(stairs, p, t_end, keep=("samples",)).final.position

    with jax_path():
        np.testing.assert_allclose(final(1.0), final.__wrapped__(1.0), rtol=0, atol=1e-12)
        with pytest.raises(Exception, match="t_end must be a finite time > 0"):
            jax.block_until_ready(final(-1.0))


@pytest.mark.parametrize("native", [True, False])
def test_an_empty_batch(stairs, native):
    """No balls, no work, the right shapes (the JAX path's packing failed on it before)."""
    none = estim.Params(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
    with contextlib.nullcontext() if native else jax_path():
        traj = estim.simulate(stairs, none, 1.0, ts=np.linspace(0.0, 1.0, 4))
    assert traj.final.position.shape == (0, 3) and traj.position.shape == (0, 4, 3)
    assert traj.events.t.shape == (0, 64)
