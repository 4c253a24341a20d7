"""The one entry point: simulate any number of balls in a scene."""

from __future__ import annotations

import concurrent.futures
from collections.abc import Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .._config import (
    CLOSED_FORM_COMPILE,
    ODE_COMPILE,
    ODE_OPTIMISED,
    jit,
    keep_loop,
    require_x64,
    top_level,
)
from ..model._params import PARAM_CHECKS, UNREAD_BY_KERNELS_CHECKS, Params, check_t_end
from ..model._scene import Scene
from . import _native, _ode
from ._balls import ball_parts, check_outside, flat_params, inside, map_balls
from ._contact import has_edges
from ._dispatch import NATIVE, ODE, path
from ._ode import OdeSettings
from ._record import layout_of, pack, unpack
from ._solver import plan
from ._trajectory import (
    KEEP,
    Trajectory,
    check_keep,
)
from .laws import law_of

__all__ = ["simulate"]


def simulate(
    scene: Scene,
    params: Params,
    t_end: float | ArrayLike,
    *,
    ts: Float[ArrayLike, " times"] | None = None,
    solver: diffrax.AbstractSolver | None = None,
    rtol: float = _ode.RTOL,
    atol: float = _ode.ATOL,
    max_steps: int = _ode.MAX_STEPS,
    contact_slack: float = _ode.SLACK,
    max_segments: int = 48,
    max_events: int = 64,
    throw: bool = True,
    keep: Sequence[str] | None = None,
) -> Trajectory:
    """Simulate balls bouncing in a scene over ``[0, t_end]``.

    The scene decides the physics, and so the path:

    - *gravity only* (no ``scene.air``): every flight is a parabola and every contact time
      the root of a quadratic, so the result is exact to rounding and no contact can be
      missed; bounce series (including Zeno series with infinitely many bounces) are summed
      in closed form (``estim.forward._solver``). No ODE solver runs.
    - *with air* (drag, wind, Magnus; ``estim.model._air``): flights are integrated with a
      diffrax solver, contacts located by root finding under a step bound that skips none
      (``estim.forward._ode``).

    Either way the result is differentiable (``jax.grad``, ``jax.jacfwd``) with respect to
    every field of ``params``, ``t_end``, the sample times and the scene geometry;
    derivatives of event times are the event-time sensitivities of the hybrid system.

    What a bounce does is the scene's contact law (``Scene.law``, ``estim.forward.laws``; the
    seed's e and mu_t law by default). A law whose bounce series have a closed form (the
    seed's) has them summed, Zeno series included; any other law is followed bounce by
    bounce, bounded by ``max_segments`` (``max_steps``). The native kernels run the
    closed-form path where they support the law (``estim.forward._native.supports``).

    Args:
        scene: the scene (:func:`estim.load_scene`).
        params: per-ball parameters; all balls of a batch are simulated in one call.
        t_end: final time (s), > 0.
        ts: sample times in ``[0, t_end]``; default ``[0, t_end]``.
        solver: a diffrax Runge-Kutta solver for the ODE path (default ``diffrax.Tsit5()``
            when the scene has air). Passing one for a gravity-only scene forces the ODE
            path (to compare it with the closed form).
        rtol: relative tolerance of the ODE path's step-size control (error per step
            scaled by ``atol + rtol |y|``, y = (position, velocity)).
        atol: absolute tolerance of the ODE path's step-size control.
        max_steps: static bound on the ODE path's steps per ball (accepted and rejected).
        contact_slack: on the ODE path, how far (m) the integrated path may stray within a
            step from the parabola its contacts are predicted on: no contact deeper than
            this is ever skipped (``estim.forward._ode``). The tolerances and the slack are traced:
            changing them does not recompile.
        max_segments: static bound on the closed-form segments per ball (a segment is a
            flight, a whole bounce series on one face, or a slide). Bounded compute: a ball
            that would need more is reported (``throw``).
        max_events: static size of the event list per ball.
        throw: raise if a ball needs more than ``max_segments``; otherwise return with
            ``complete = False`` for that ball.
        keep: what to compute and return besides the final state: any of ``"samples"``
            (position and velocity at ``ts``), ``"events"`` and ``"solution"`` (the dense
            solution, for ``Trajectory.evaluate``); default all three. A trajectory is
            stored packed (``estim.Trajectory``), so a jitted function that uses only part
            of it still computes all it keeps: keep only what you use (10,000 balls,
            final states only: about 6 times faster). A derivative computes only what
            it keeps too (``jax.jacfwd`` of the golf ball's final x: about 27 us with
            ``keep=()``, 61 us with the default; docs/pages/speed.md).

    Returns:
        A :class:`Trajectory`.

    Raises:
        ValueError: impossible inputs, named: parameters out of range or not finite, t_end
            not a finite time > 0, ts outside ``[0, t_end]``, a ball that starts inside a
            solid, bounds below 1. With concrete values these are checked in Python before
            the call; inside a user's ``jit`` (traced values) the same checks run in the
            compiled program, which raises with the same message.
        RuntimeError: a ball needed more than ``max_segments`` (``max_steps``) and
            ``throw`` is set (inside ``jit``, the program raises as above).

    Example:
        >>> scene = estim.load_scene("data/scenes/stairs.xml")
        >>> golf = estim.Params.for_ball(scene, "golf", e=0.7, mu_t=0.98, velocity=(1.15, 0, 0))
        >>> traj = estim.simulate(scene, golf, 2.3)
        >>> traj.final.position  # doctest: +SKIP
    """
    require_x64()
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be an estim.Scene (estim.load_scene), got {type(scene).__name__}")
    if not isinstance(params, Params):
        raise TypeError(f"params must be an estim.Params, got {type(params).__name__}")
    check_t_end(t_end)
    keep = check_keep(keep)
    for name, value in (("max_segments", max_segments), ("max_events", max_events), ("max_steps", max_steps)):
        if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1):
            raise ValueError(f"{name} must be an integer >= 1 (a static bound), got {value!r}")
    # Inside a transformation (jit, grad, make_jaxpr...) every value is traced; at top level,
    # concrete inputs stay NumPy until the compiled call (each eager JAX op costs a dispatch).
    traced = not top_level() or any(
        isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((scene, params, t_end, ts)))
    xp = jnp if traced else np
    t_end = xp.asarray(t_end, dtype=np.float64)
    if ts is None:
        ts = xp.stack([xp.zeros(()), t_end])
    ts = xp.asarray(ts, dtype=np.float64)
    if ts.ndim != 1:
        raise ValueError(f"ts must be one-dimensional, got shape {ts.shape}")
    if not isinstance(ts, jax.core.Tracer) and not isinstance(t_end, jax.core.Tracer):
        tv = np.asarray(ts)
        if not np.all(np.isfinite(tv)) or np.any(tv < 0) or np.any(tv > float(t_end)):
            raise ValueError(f"ts must be finite and lie in [0, t_end={float(t_end)}]")
    check_outside(scene, params)
    _check_effects(scene, params)
    if solver is not None and not (
        isinstance(solver, diffrax.AbstractRungeKutta)
        and getattr(solver.tableau, "b_error", None) is not None
        and not getattr(solver.tableau, "implicit", False)
    ):
        raise TypeError(
            "solver must be an explicit diffrax Runge-Kutta solver with an error estimate "
            f"(diffrax.Tsit5(), Dopri5(), Dopri8(), Bosh3()), got {solver!r}"
        )
    if not (rtol > 0 and atol > 0 and contact_slack > 0):
        raise ValueError(
            f"rtol, atol and contact_slack must be > 0, got rtol={rtol!r}, atol={atol!r}, "
            f"contact_slack={contact_slack!r}"
        )
    # Called with concrete values, the inputs were checked above and completion is checked
    # below, in Python: the compiled program then has no host callbacks and can live in
    # JAX's persistent compilation cache. Inside a user's jit/grad the checks run in-graph.
    route = path(scene, solver)
    if route == ODE:
        rk = solver or diffrax.Tsit5()
        settings = OdeSettings(rk, jnp.asarray(rtol, dtype=jnp.float64), jnp.asarray(atol, dtype=jnp.float64),
                               jnp.asarray(contact_slack, dtype=jnp.float64), int(max_steps))
        solve = solve_ode if traced else _solve_ode_apart
        traj = solve(scene, params, t_end, ts, settings, max_events, throw and traced, keep)
        message = _INCOMPLETE_ODE
    else:
        traj = solve_closed_form(scene, params, t_end, ts, max_segments, max_events, throw and traced, keep,
                                 route == NATIVE)
        message = _INCOMPLETE
    # (Read from NumPy views of the rows: no eager JAX operation.)
    if throw and not traced:
        complete = unpack(np.asarray(traj.record), np.asarray(traj.flags), traj.layout, "complete")
        if not np.all(complete):
            raise RuntimeError(message)
    return traj


_INCOMPLETE = (
    "a ball needed more closed-form segments than max_segments, or it would roll over an "
    "edge that is not horizontal (not followed in closed form; give the scene air, or a diffrax "
    "solver, for the ODE path, which follows it), or its path entered a solid (a degenerate contact the closed forms missed); increase "
    "max_segments (a ball bouncing where no series can be summed, against an edge or "
    "between walls, takes a segment per bounce), move the ball off the degenerate point, "
    "or pass throw=False and inspect Trajectory.complete"
)


_INCOMPLETE_ODE = (
    "a ball needed more ODE steps than max_steps; increase max_steps or loosen rtol/atol, "
    "or pass throw=False and inspect Trajectory.complete"
)


@jit(options=ODE_COMPILE, optimised=ODE_OPTIMISED)
def solve_ode(scene, params, t_end, ts, settings, max_events, checks, keep):
    """The ODE path as one program (what a user's jit or grad gets). Ball by ball, as on
    the closed-form path: each ball's step loop is a loop of its own (vectorised over
    balls, every step of every ball ran the branches of all: the seed's three balls in
    still air took 21.6 ms instead of 2.4), its replay runs only the steps it uses
    (estim.forward._scan), and it writes only the parts it keeps, packed. (A ball with bad
    inputs still ends: its step loop is bounded by max_steps.)"""
    return _packed_balls(scene, params, t_end, ts, checks, keep, _INCOMPLETE_ODE,
                         lambda prm: _ode.ball_parts(scene, prm, t_end, ts, settings, max_events, keep))


# At top level the ODE path is two programs, each ball's step loop (``_ode_plans``) and
# what follows from its plan (``_ode_finish``: samples, events, packing), which a first
# call compiles side by side, the second from the first's shapes (``_solve_ode_apart``).
# The seed's three balls in still air, every part kept: 2.7-2.9 s to the first result as
# one program, 1.75-2.04 s as two (of which the step loop is 0.55 s of tracing and 1.35 s
# of compiling; 2-core development machine, AMD EPYC, session 37). The values are the one
# program's to rounding: the second program takes the plan's nodes as they are
# (``_ode.nodes_of``), and the two compile into other fusions than the one program.
@jit(options=ODE_COMPILE, optimised=ODE_OPTIMISED, static_argnames=())
def _ode_plans(scene, params, t_end, settings):
    return map_balls(lambda prm: _ode.plan(scene, prm, t_end, settings), flat_params(params))


@jit(options=ODE_COMPILE, optimised=ODE_OPTIMISED, static_argnames=("max_events", "checks", "keep"))
def _ode_finish(scene, params, t_end, ts, settings, plans, max_events, checks, keep):
    return _packed_balls(scene, params, t_end, ts, checks, keep, _INCOMPLETE_ODE,
                         lambda prm, pl: _ode.finish(scene, prm, t_end, ts, settings, max_events, pl, pl.n_steps, keep),
                         plans)


def _solve_ode_apart(scene, params, t_end, ts, settings, max_events, checks, keep):
    """``solve_ode`` as its two programs; on their first call both compile at once, the
    step loop's on a thread of its own while the second is traced and compiled."""
    ahead = _ode_plans.ahead(scene, params, t_end, settings)
    if ahead is not None:
        shapes, compile_plans = ahead
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            compiling = pool.submit(compile_plans)
            after = _ode_finish.ahead(scene, params, t_end, ts, settings, shapes, max_events=max_events,
                                      checks=checks, keep=keep)
            if after is not None:
                after[1]()
            compiling.result()
    plans = _ode_plans(scene, params, t_end, settings)
    return _ode_finish(scene, params, t_end, ts, settings, plans, max_events=max_events, checks=checks, keep=keep)


def _check_effects(scene: Scene, params: Params) -> None:
    """What the air needs (a mass), and what only the air or a law that couples spin gives
    meaning to (spin)."""
    if scene.air is not None and params.mass is None:
        raise ValueError(
            "this scene has air (drag), which needs each ball's mass: build the parameters "
            "with Params.for_ball(scene, ...) or pass Params(..., mass=...)"
        )
    if scene.air is None and not law_of(scene).couples_spin and not isinstance(params.spin, jax.core.Tracer):
        if np.any(np.asarray(params.spin) != 0):
            raise ValueError(
                "Params.spin is set but the scene has no air and its contact law ignores spin, so "
                "the spin changes nothing: add <option density=...> to the scene (Magnus), declare "
                "the friction law (<custom><text name=\"estim:law\" data=\"friction\"/></custom>), "
                "or drop the spin"
            )


@jit(options=CLOSED_FORM_COMPILE, static_argnames=("max_segments", "max_events", "checks", "keep", "native"))
def solve_closed_form(scene, params, t_end, ts, max_segments, max_events, checks, keep, native):
    batch = params.batch_shape
    g = scene.gravity

    def unflat(x):
        return x.reshape(batch + x.shape[1:])

    if native and _native.supports(law_of(scene), scene):
        # The primal on the native kernels, derivatives replayed in JAX (estim.forward._native);
        # the kernel runs the argument checks too, and fails with their message. (``native``
        # asks for the kernels; what they do not support runs in JAX below.)
        record, flags = _native.trajectory_rows(scene, params, t_end, ts, max_segments, max_events, keep, checks,
                                                _INPUT_CHECKS + (_INCOMPLETE,))
        layout = _native.trajectory_layout(ts.shape[0], max_segments, max_events, keep, has_edges(scene))
        return Trajectory(ts=ts, record=unflat(record), flags=unflat(flags), gravity=g, layout=layout)

    # Ball by ball, in one loop that XLA:CPU compiles as a single kernel (estim._config):
    # each ball's plan, its samples, and only the events it lists (on the seed scene 9, 6
    # and 4 of 64 slots); a ball's derivatives replay its own segments. With one ball at a
    # time the branches of a segment (lax.cond in estim.forward._solver) are branches, not both
    # sides computed and one selected as under vmap. Vectorised over balls, the seed's 3
    # balls took 329 us, 10,000 balls 309 ms; this way 235 us and 174 ms (docs/pages/
    # speed.md). A ball's result does not depend on the other balls of its batch. The loop
    # writes each ball's result as the packed rows of a Trajectory, so that the program is
    # the loop and little else, and returns a few arrays.
    def parts_of(prm):
        pl = plan(scene, prm, t_end, max_segments)
        return ball_parts(scene, prm, t_end, ts, pl, max_events, keep)

    return _packed_balls(scene, params, t_end, ts, checks, keep, _INCOMPLETE, parts_of)


def _packed_balls(scene, params, t_end, ts, checks, keep, incomplete: str, parts_of, *per_ball) -> Trajectory:
    """One ball at a time (``estim.forward._balls.map_balls``): ``parts_of(params, *items)``,
    the ball's Trajectory parts (items: its entries of ``per_ball``), packed into its rows;
    with ``checks``, the argument checks and completion of every ball, raised once for the
    whole call (``incomplete``: the message of a ball left incomplete)."""
    layouts = []  # the layout of a ball's rows, found while tracing its loop body

    def ball(prm, *items):
        parts = parts_of(prm, *items)
        layouts.append(layout_of(parts, 0))
        rows = pack(parts, layouts[-1])
        if not checks:
            return rows
        # The ball's first failing input check (1-based), else len(_INPUT_CHECKS) + 1 if it
        # is left incomplete, else 0.
        code = _input_code(scene, prm, t_end, ts)
        return rows + (jnp.where(code > 0, code, jnp.where(parts["complete"], 0, len(_INPUT_CHECKS) + 1)),)

    record, flags, *code = map_balls(ball, flat_params(params), *per_ball)
    if keep != frozenset(KEEP):  # (check_keep made keep a frozenset)
        # For one ball XLA replaces the loop by its body and drops whatever the caller
        # leaves unused: with every part kept, that is what lets a function of the final
        # state alone skip the rest. Where the caller said what to keep, the loop stays a
        # loop: one kernel, where the body is a few dozen (jacfwd of the golf ball's final
        # x, 6 kernels instead of 37; docs/pages/speed.md).
        record = keep_loop(record)
    if checks:
        # One check for the whole call, after the loop (each eqx.error_if is a kernel of
        # its own): the smallest nonzero code of the balls, if any.
        messages = list(_INPUT_CHECKS) + [incomplete]
        first = jnp.min(jnp.where(code[0] > 0, code[0], len(messages) + 1))
        fails = first <= len(messages)
        record = eqx.branched_error_if(record, fails, jnp.where(fails, first - 1, 0), messages)
    batch = params.batch_shape
    return Trajectory(ts=ts, record=record.reshape(batch + record.shape[1:]),
                      flags=flags.reshape(batch + flags.shape[1:]), gravity=scene.gravity, layout=layouts[-1])


# The argument checks of `simulate`, as they run inside a user's jit (outside it, the same
# checks run in Python before the call, with the offending values in the message).
_INPUT_CHECKS = tuple(message for message, _ in PARAM_CHECKS) + (
    "t_end must be a finite time > 0 (seconds)",
    "ts must be finite and lie in [0, t_end]",
    "a ball starts inside a solid: release it outside every solid",
) + tuple(message for message, _ in UNREAD_BY_KERNELS_CHECKS)


def _input_code(scene: Scene, prm: Params, t_end, ts):
    """0 if one ball's inputs pass every check of ``_INPUT_CHECKS``, else 1 + the index of
    the first that fails."""
    inside_box, inside_plane = inside(jnp, scene, prm.position[None], prm.contact_radius[None])
    passes = [ok(prm) for _, ok in PARAM_CHECKS] + [
        jnp.isfinite(t_end) & (t_end > 0),
        jnp.isfinite(ts) & (ts >= 0) & (ts <= t_end),
        ~jnp.concatenate([jnp.ravel(inside_box), jnp.ravel(inside_plane)]),
    ] + [ok(prm) for _, ok in UNREAD_BY_KERNELS_CHECKS]
    # Every entry of every check in one array, and one reduction (min) of the failing
    # entries' check numbers: a reduction per check costs each call of the program
    # (estim._fold).
    passes = [jnp.ravel(x) for x in passes]
    number = np.concatenate([np.full(x.shape[0], i + 1, np.int32) for i, x in enumerate(passes)])
    none = len(_INPUT_CHECKS) + 1
    first = jnp.min(jnp.where(jnp.concatenate(passes), none, number))
    return jnp.where(first == none, 0, first).astype(jnp.int32)
