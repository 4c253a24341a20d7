"""Fit e, mu_t and the release speed per ball from tracked positions, with uncertainty.

The pipeline, per ball (all balls of a data set run together in one program, one ball after
the other: ``estim.fitting._sharding.per_unit``):

1. **Start from the data** (``estim.fitting._initial``): split the track into flights in the
   ball's plane of travel, read e, mu_t, the release point and velocity off them; every
   parameter's start, default and transform comes from the registry
   (``estim.fitting._registry``). The loss is rough in the parameters (a bounce moving
   onto the next tread changes the rest of the trajectory), so starting close matters more
   than any optimiser.
2. **Grow the time window**: fit the data up to the third resolved bounce first, then all.
3. **Minimise a robust loss** ``sum rho(r / s)`` (``estim.fitting._loss``) in unconstrained
   coordinates (``e = sigmoid(a)``, ``mu_t = sigmoid(b)``: constraints by
   reparametrisation, never by clipping) with Levenberg-Marquardt on the iteratively
   reweighted residuals, written as an optax gradient transformation
   (``estim.fitting._levenberg_marquardt``). With a handful of parameters per ball, the Jacobian
   comes from forward-mode autodiff (``jax.jacfwd``) in the same pass as the residuals, one
   simulation per iteration; near the optimum the method converges quadratically.
4. **Check the noise floor**: the rms residual of the inliers must match the noise level
   read from the data (the spread about each flight's parabola); if it does not, restart
   with e from a grid over its range and keep the best. Then read the robust scale again from
   the best fit's residuals and, where it is clearly smaller than the one used, polish with
   it. The report says when the floor is not reached.
5. **Uncertainty** from the Gauss-Newton approximation at the optimum:
   ``cov = s^2 (J^T W J)^-1`` with J the Jacobian of the residuals with respect to the
   physical parameters, W the robust weights and ``s^2 = sum w r^2 / (n - p)`` the noise
   variance estimated from the residuals. A parameter the data cannot determine (mu_t with
   no bounce observed, say) shows up as a vanishing column of J and is reported as not
   identifiable instead of with a meaningless number.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._config import (
    FIT_COMPILE,
    FIT_ODE_COMPILE,
    FIT_ODE_OPTIMISED,
    FIT_ODE_TIER_UP,
    jit,
    require_x64,
    signature,
)
from ..forward import _ode
from ..forward._balls import check_outside, resting_on, solids_at_release
from ..forward._constants import ROLL
from ..forward._contact import has_edges
from ..forward._dispatch import ODE, closed_form_plan, path
from ..forward._ode import OdeSettings
from ..forward._ode import finish as ode_finish
from ..forward._ode import plan as ode_plan
from ..forward._solver import segments_of
from ..forward._trajectory import IMPACT, list_events, sample
from ..forward.laws import law_of
from ..model._params import Params
from ..model._scene import Scene
from ..tracks._camera import CameraArrays
from ..tracks._csv import MIN_SAMPLES, check_units
from ..tracks._image import MIN_ROWS
from . import _registry as registry
from ._initial import MU_DEFAULT, MU_RANGE, Initial, release_start, spin_start
from ._levenberg_marquardt import levenberg_marquardt
from ._loss import ROBUST_LOSSES, robust_loss, robust_weight
from ._missing_physics import (
    HELD,
    format_effects,
    format_note,
    held_coefficients,
    missing_physics,
    model_effects,
    one_restitution,
)
from ._sharding import gather, mesh_of, padded_size, per_unit, place

__all__ = ["BallFit", "FitResult", "fit", "PARAMETERS"]

# Every parameter a fit can estimate (estim.fitting._registry), in the order of the vector
# phi of physical values.
PARAMETERS = registry.NAMES
# The default under the seed's factor law (``registry.default_free`` gives every scene's).
DEFAULT_FREE = registry.FACTOR_FREE
# Restarts of a batch of more than 2 SUBSET_MIN keys run only the keys that restart (padded
# to a power of two, at least this many), when they are at most half of the batch.
SUBSET_MIN = 8
# A fitted parameter whose standard error exceeds this fraction of its prior's standard
# deviation is reported as held by the prior (the data add less than about 1.3 times the
# prior's information).
PRIOR_DECIDES = 0.8
# A ball's iterations stop once its best loss has not fallen by more than SETTLED_TOL of
# itself over SETTLED of them (``_settled``).
SETTLED = 10
SETTLED_TOL = 1e-9
# Contact events a fit's simulation lists (the report's impacts and their surfaces): a
# track's bounces are far fewer.
LISTED_EVENTS = 64


class _Problem(eqx.Module):
    """One ball's data and fixed values, padded to a common number of samples."""

    t: jax.Array  # (N,)
    obs: jax.Array  # (N, 3)
    mask: jax.Array  # (N, 3) bool
    radius: jax.Array  # ()
    mass: jax.Array  # () (kg), for the air's forces
    inertia: jax.Array  # () I / (m r^2), for a contact law that couples spin
    fixed: jax.Array  # (len(PARAMETERS),) phi: the values of the parameters not fitted
    scale: jax.Array  # () noise level s of the robust loss (m)
    anchor: jax.Array  # (3,) the point the observations scale about (pixel_scale)
    size: jax.Array  # () the track's own samples: the first ``size`` of the N
    view: jax.Array | None = None  # image tracks: (N,) int, the camera that saw each row
    cameras: CameraArrays | None = None  # image tracks: the cameras, obs holding (u, v, 0)
    prior: jax.Array | None = None  # (2, len(PARAMETERS)): priors' means and 1/sd (registry.prior_arrays)
    held: jax.Array | None = None  # (len(free),) bool: fitted parameters this ball holds at its start (_on_surface)


class ImageRows(NamedTuple):
    """Image tracks of one key of a fit (``estim.fitting._image``): the rows' times on
    their cameras' clocks, their pixels ``(n, 2)`` (NaN where lost), the camera of each
    row, the cameras, the pixels' noise level (px), and the starting values read off the
    start path (``Initial``: the flights of a track in metres cannot be read there)."""

    t: np.ndarray
    uv: np.ndarray
    view: np.ndarray
    cameras: CameraArrays
    noise: float
    initial: Initial


# The ODE path's settings in a fit (scenes with air): the defaults of estim.simulate, with a
# step budget for tracks of a few seconds.
FIT_ODE = dict(rtol=_ode.RTOL, atol=_ode.ATOL, contact_slack=_ode.SLACK, max_steps=1024)


def _clock(phi, problem: _Problem):
    """The rows' times on the model's clock, before the release at t0 is taken off: each
    row's time plus its camera's offset (image tracks of several cameras; camera 1's is 0)."""
    if problem.cameras is None:
        return problem.t
    offsets = jnp.concatenate([jnp.zeros(1), phi[registry.index(registry.component("dt_camera2").components)]])
    return problem.t + offsets[problem.view]


def _model(scene: Scene, phi, problem: _Problem):
    """The model's parameters, sample times and end time for physical values phi."""
    values = registry.unpack(phi)
    params = registry.to_params(values, radius=problem.radius, mass=problem.mass, inertia=problem.inertia, scene=scene)
    ts = jnp.clip(_clock(phi, problem) - values["t0"], 0.0, None)
    return params, ts, jnp.maximum(jnp.max(ts), 1e-3)


def fit_program(fun):
    """``fun`` (a fit's program, whose first argument is the scene) compiled with the
    options of the scene's path: ``FIT_COMPILE`` for the closed form; on the ODE path
    ``FIT_ODE_COMPILE`` (quick to compile, slow to run) for the first ``FIT_ODE_TIER_UP``
    calls with one signature (shapes, dtypes and static values of the arguments), then
    ``FIT_ODE_OPTIMISED`` (``estim._config`` gives the figures; ``estim._config.jit``
    counts the calls), or that from the first call inside ``estim.optimised_programs``.
    The two programs give the same fits to rounding.

    ``fun`` takes a static keyword ``rolls`` and returns, after its results, whether any
    of its plans had a ``ROLL`` segment (``_rolled``). In the closed form on exact
    geometry a call first runs the program without the rolls' closed forms
    (``estim.forward._solver.replay``: three quarters of a drop fit's program on a box
    table, and of its compile time), and runs again with them, from the same arguments,
    where a plan had a roll, and from then on for that signature: the results are always
    those of the program with rolls."""
    closed_form = jit(fun, options=FIT_COMPILE)
    ode = jit(fun, options=FIT_ODE_COMPILE, optimised=FIT_ODE_OPTIMISED, tier_up=FIT_ODE_TIER_UP)
    rolling = set()  # signatures whose plans have had a roll

    @functools.wraps(fun)
    def call(scene, *args, **kwargs):
        if path(scene) == ODE:
            return ode(scene, *args, rolls=True, **kwargs)[:-1]
        if not has_edges(scene):
            return closed_form(scene, *args, rolls=True, **kwargs)[:-1]
        key = signature((scene, args, kwargs))
        if key not in rolling:
            *out, rolled = closed_form(scene, *args, rolls=False, **kwargs)
            if not np.any(gather(rolled)):
                return tuple(out)
            rolling.add(key)
        return closed_form(scene, *args, rolls=True, **kwargs)[:-1]

    return call


def _rolled(scene: Scene, pl, rolls: bool):
    """Whether plan ``pl`` has a ``ROLL`` segment that a program without rolls (``rolls``
    False, static) left out (``fit_program``)."""
    if rolls or path(scene) == ODE:
        return jnp.bool_(False)
    return jnp.any(pl.decisions.kind == ROLL)


def _ode_settings():
    return OdeSettings(diffrax.Tsit5(), *(jnp.asarray(FIT_ODE[k]) for k in ("rtol", "atol", "contact_slack")),
                       FIT_ODE["max_steps"])


def _plan_at(scene: Scene, phi, problem: _Problem, max_segments: int):
    """The discrete structure of the model at phi (values only: no derivatives flow through
    a plan), and how many slots it uses."""
    params, _, t_end = _model(scene, phi, problem)
    if path(scene) == ODE:
        pl = ode_plan(scene, params, t_end, _ode_settings())
        return pl, pl.n_steps
    pl = closed_form_plan(scene, params, t_end, max_segments)
    return pl, pl.n_segments


def _simulate_at(scene: Scene, phi, problem: _Problem, pl, n_used, rolls: bool):
    """Model positions at the sample times, the events and the sample times, for physical
    values phi and their plan ``pl``: the closed form in a vacuum, the ODE path in a scene
    with air. Derivatives replay the first ``n_used`` slots (the batch's largest count).
    ``rolls`` (static): whether the closed form follows ``ROLL`` segments (``fit_program``)."""
    params, ts, t_end = _model(scene, phi, problem)
    if path(scene) == ODE:
        parts = ode_finish(scene, params, t_end, ts, _ode_settings(), LISTED_EVENTS, pl, n_used,
                           frozenset({"samples", "events"}))
        return parts["position"], parts["events"], ts
    segs = segments_of(scene, params, t_end, pl.decisions, pl.segments, n_used, rolls)
    law = law_of(scene)
    pos, _ = sample(segs, pl.decisions, law, law.coefficients(params), scene.gravity, ts, rolls and has_edges(scene))
    # The events only report the impacts (not differentiated): listed from the plan's
    # values, they stay out of the Jacobian's forward-mode trace.
    c = jax.lax.stop_gradient(law.coefficients(params))
    return pos, list_events(pl.segments, pl.decisions, law, c, scene.gravity, LISTED_EVENTS), ts


def _residuals(scene, phi, problem, pl, n_used, rolls):
    """Masked residuals (flattened), which entries are valid, model positions, and the
    faces of the impacts within the data (``LISTED_EVENTS`` slots in time order, -1 past them)."""
    pos, events, ts = _simulate_at(scene, phi, problem, pl, n_used, rolls)
    valid = problem.mask & (_clock(phi, problem) >= registry.value(phi, "t0"))[:, None]
    if problem.cameras is None:
        # A pixel track's metres are its pixels times a scale read off the data; the fitted
        # factor pixel_scale corrects that scale about the track's anchor (its surface). The
        # model is brought to the data's metres, not the data to the model's: residuals stay
        # in the units of the data's noise, and no scale can shrink them all to nothing.
        seen = problem.anchor + (pos - problem.anchor) / registry.value(phi, "pixel_scale")
    else:
        # Image tracks: the model seen by the camera of each row, in pixels (u, v, 0).
        uv = problem.cameras.project(pos, problem.view)
        seen = jnp.concatenate([uv, jnp.zeros_like(uv[:, :1])], axis=1)
    r = jnp.where(valid, seen - problem.obs, 0.0).reshape(-1)
    impacts = jnp.where((events.kind == IMPACT) & (events.t <= jnp.max(ts)), events.face, -1).astype(jnp.int32)
    return r, (valid.reshape(-1), pos, impacts)


def _prior_rows(phi, problem: _Problem):
    """The priors as rows of residuals: ``(phi - mean) / sd`` in noise units, times the
    robust scale (zero where a component has no prior); none without priors."""
    if problem.prior is None:
        return jnp.zeros(0)
    return (phi - problem.prior[0]) * problem.prior[1] * problem.scale


def _linearise(scene, free, loss, theta, problem, pl, n_used, rolls):
    """Residuals ``r`` and their Jacobian ``J`` with respect to theta (forward mode, one
    simulation with the plan ``pl``), the diagnostics ``aux`` of ``_residuals``, the
    residuals in noise units ``u`` and the robust loss (inf where J is not finite). With
    priors (``_Problem.prior``) their rows follow the data's (``_prior_rows``)."""

    def evaluate(theta):
        phi = registry.to_physical(theta, free, problem.fixed)
        r, aux = _residuals(scene, phi, problem, pl, n_used, rolls)
        r = jnp.concatenate([r, _prior_rows(phi, problem)])
        return r, (r, aux)

    J, (r, aux) = jax.jacfwd(evaluate, has_aux=True)(theta)
    if problem.held is not None:  # (no gradient, no step: held where it starts)
        J = jnp.where(problem.held, 0.0, J)
    u = r / problem.scale
    value = jnp.sum(robust_loss(u, loss))
    return J, r, aux, u, jnp.where(jnp.all(jnp.isfinite(J)), value, jnp.inf)


def _lm_step(scene, free, loss, carry, problem, pl, n_used, rolls):
    """One Levenberg-Marquardt iteration for one ball, whose model at theta has the plan
    ``pl``: residuals and Jacobian at theta (forward mode, one simulation), keep the best
    point seen, step."""
    theta, state, best = carry
    J, r, aux, u, value = _linearise(scene, free, loss, theta, problem, pl, n_used, rolls)
    improved = value < state.best_value
    m = problem.obs.size  # the data's rows; the priors' follow
    best = jax.tree.map(lambda new, old: jnp.where(improved, new, old), (r[:m], J[:m], aux), best)
    updates, state = _LM.update(
        None, state, theta, jacobian=J, residuals=r, weights=robust_weight(u, loss), value=value
    )
    return (theta + updates, state, best), jnp.minimum(value, state.best_value)


_LM = levenberg_marquardt()


@dataclass
class BallFit:
    """The fit of one ball.

    ``values`` and ``stderr`` map parameter names to numbers (stderr NaN where the data
    cannot determine the parameter, with the reason in ``notes``); ``correlation`` is the
    correlation matrix of the fitted parameters in the order of ``names``.
    """

    ball: str
    values: dict[str, float]
    stderr: dict[str, float]
    names: tuple[str, ...]
    correlation: np.ndarray
    rms_m: float  # rms residual of the inliers (m; pixels where ``unit`` is "px")
    noise_m: float  # noise level read from the data (m; pixels where ``unit`` is "px")
    n_obs: int  # samples compared with the model (rows with at least one coordinate)
    n_outliers: int  # samples the robust loss set aside (|r| > 5 noise)
    n_bounces: int  # impacts of the fitted model within the data
    converged: bool
    at_noise_floor: bool
    notes: list[str] = field(default_factory=list)
    loss_history: np.ndarray = field(default_factory=lambda: np.zeros(0))
    initial: Initial | None = None
    model_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    model_position: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    missing_physics: list[dict] = field(default_factory=list)  # effects the scene lacks, or coefficients held
    unit: str = "m"  # of the residuals: "m" (tracks in metres) or "px" (image tracks, estim.fit_image)
    depth: dict | None = None  # image tracks: how well the pixels fix the path's depth (estim.fitting._image)
    prior: dict[str, tuple[float, float]] = field(default_factory=dict)  # the priors applied: (mean, sd)
    effects: list[dict] | None = None  # what each effect of the model does over the track (fit(effects=True))
    contacts: tuple[tuple[str, str], ...] = ()  # each impact's (solid, face) within the data, in time order

    def to_json(self) -> dict:
        """The values by their registry names (those that act in the fit's scene), the
        release state as vectors (``"release"``: t, position, velocity, spin in rad/s, zeros
        where the scene has no spin), the model's positions at the track's times
        (``"fitted"``), and the fit's statistics."""
        out = {k: self.values[k] for k in self.values}
        vector = lambda name: [self.values.get(c, 0.0) for c in registry.component(name).components]  # noqa: E731
        out.update(
            release={"t": self.values["t0"], "position": vector("x0"), "velocity": vector("vx0"),
                     "spin": vector("spin_x")},
            fitted={"t": self.model_t.tolist(), "position": self.model_position.tolist()},
            stderr={k: (None if not math.isfinite(v) else v) for k, v in self.stderr.items()},
            correlation={"names": list(self.names), "matrix": np.round(self.correlation, 6).tolist()},
            **{f"rms_{self.unit}": self.rms_m, f"noise_{self.unit}": self.noise_m},
            n_obs=self.n_obs,
            n_outliers=self.n_outliers,
            n_bounces=self.n_bounces,
            contacts=[list(c) for c in self.contacts],
            converged=self.converged,
            at_noise_floor=self.at_noise_floor,
            notes=self.notes,
        )
        if self.missing_physics:
            out["missing_physics"] = self.missing_physics
        if self.depth is not None:
            out["depth"] = self.depth
        if self.prior:
            out["prior"] = {n: {"mean": m, "sd": sd} for n, (m, sd) in self.prior.items()}
        if self.effects is not None:
            out["effects"] = self.effects
        return out


@dataclass
class FitResult:
    balls: dict[str, BallFit]
    source: str = ""

    @property
    def converged(self) -> bool:
        return all(b.converged for b in self.balls.values())

    def to_json(self) -> dict:
        return {"source": self.source, "balls": {k: v.to_json() for k, v in self.balls.items()}}

    def format_table(self) -> str:
        """One row per ball: the parameters the registry shows (e, mu_t, vx0, and those
        shown where fitted, such as vy0 or the drag coefficient, when a ball fitted them)
        with standard errors, rms, samples, bounces, status."""

        def pm(bf, name):
            if name not in bf.values:  # a parameter that does not act in this ball's scene
                return "-"
            v, s = bf.values[name], bf.stderr.get(name, math.nan)
            return f"{v:.4f} +- {s:.4f}" if math.isfinite(s) else f"{v:.4f} (n/a)"

        fitted = {n for bf in self.balls.values() for n in bf.names}
        columns = registry.shown({n for bf in self.balls.values() for n in bf.values}, fitted)
        labels = "".join(f" {registry.component(n).label(n):>17}" for n in columns)
        pixels = any(bf.unit == "px" for bf in self.balls.values())
        head = f"{'ball':<10}{labels} {'rms (px)' if pixels else 'rms (mm)':>9} {'n':>5} {'bounces':>7}  status"
        rows = [head, "-" * len(head)]
        for ball, bf in self.balls.items():
            status = "converged" if bf.converged else "NOT converged"
            if not bf.at_noise_floor:
                status += ", above noise floor"
            cells = "".join(f" {pm(bf, n):>17}" for n in columns)
            rows.append(
                f"{ball:<10}{cells} "
                f"{bf.rms_m * (1.0 if bf.unit == 'px' else 1e3):9.2f} {bf.n_obs:5d} {bf.n_bounces:7d}  {status}"
            )
            rows.extend(f"{'':<10} note: {n}" for n in bf.notes)
            if bf.effects:
                rows.append(f"{'':<10} {format_effects(bf.effects)}")
        return "\n".join(rows)


def fit(
    scene: Scene,
    data: dict[str, tuple[np.ndarray, np.ndarray]],
    *,
    free: tuple[str, ...] | None = None,
    fixed: dict[str, dict[str, float]] | None = None,
    loss: str = "cauchy",
    steps: int = 30,
    restarts: int = 5,
    max_segments: int = 48,
    progress: Callable[[str], None] | None = None,
    balls: dict[str, str] | None = None,
    anchors: dict[str, tuple[float, float, float]] | None = None,
    prior: dict[str, tuple[float, float] | None] | None = None,
    effects: bool = False,
) -> FitResult:
    """Fit every ball of a data set.

    Args:
        scene: the scene the balls move in (radii from its balls).
        data: ``ball -> (t (n,), position (n, 3))`` in seconds and metres, NaN marking a lost
            coordinate (``Tracks.arrays()`` gives this).
        free: the parameters to fit (the names of ``PARAMETERS``, from the registry
            ``estim.fitting._registry``; a vector's name stands for its components:
            ``"spin"`` for spin_x, spin_y, spin_z). By default (``None``) what
            ``registry.default_free`` gives for the scene: under the seed's factor law e,
            mu_t, vx0, x0, z0, plus y0 and vy0 when the tracks have a y coordinate (as for
            any ``free`` that holds those five); under a law that couples spin (the friction
            law) e, mu, the release position, velocity and spin; and every parameter with
            a prior (``prior``). The rest are held at the data's
            start or at their default (``Parameter.hold_start``): x0, y0, z0, vx0, vy0 as
            read from the data (in the ball's plane of travel:
            ``estim.fitting._initial.release_start``; y0 the ball's y in the scene and
            ``vy0 = 0`` for a track without y), ``vz0 = 0``, ``t0 = 0`` (release at the
            data's t = 0), the drag coefficient 0.47 and no spin, unless ``fixed`` says
            otherwise.
        fixed: per ball, values to hold fixed (or to start from, for free parameters).
        loss: ``"cauchy"`` (default), ``"huber"`` or ``"l2"``.
        restarts: how many more starts (e on a grid over [0.3, 0.9]; mu_t and vx0 from the
            data, slightly perturbed, mu_t from 0.95 where the data's value was clipped to
            its range or lies above 0.95) to try for balls whose fit misses the noise floor.
            After them, a ball whose residuals' spread is clearly below the robust scale it
            was fitted with is polished with that spread (module docstring, step 4).
        progress: called with a short message at each stage.
        balls: the scene's ball of each key of ``data`` (default: the key is the ball's
            name). Several tracks of one ball (clips, ``estim.fitting._pooled``) are fitted
            side by side under their own keys this way.
        anchors: per key, the point (m) its observed positions scale about when
            ``pixel_scale`` is fitted or fixed (a pixel track's surface: the first sample's
            x and the top of the surface; default the origin).
        prior: what is known of the fitted parameters before the data: ``name -> (mean,
            standard deviation)`` (a vector's name for each of its components), or ``name
            -> None`` to drop a prior the scene declares (``Scene.priors``; the scene's
            apply unless dropped). Each prior on a fitted parameter enters the loss as one
            more residual, ``(value - mean) / sd`` in noise units, under the same robust
            loss as the data (Gaussian under ``"l2"``, heavy-tailed under ``"cauchy"``);
            the standard errors are then the posterior's. With the default ``free``, every
            parameter that acts and has a prior is fitted (``registry.default_free``: the
            table-tennis scene's drag coefficient). With a given ``free``, a scene's prior
            on a parameter the fit holds is not used; a given one is an error.
        effects: also size every effect of the model over each track (``BallFit.effects``,
            ``estim.fitting._missing_physics.model_effects``): how far drag, Magnus, wind,
            the spin at the bounce and the bounce's friction move the fitted ball, in noise
            levels, which says what the track can and cannot tell apart. A few more runs of
            the forward model per ball (one more compilation on the ODE path).

    Raises:
        ValueError: data or fixed values that a fit cannot use, naming the ball and the
            problem: times not finite or not strictly increasing, infinite positions (NaN
            marks a lost detection), fewer than 8 samples, a track that does not fall with
            the scene's gravity between bounces (not metres and seconds:
            ``estim.tracks._csv.check_units``), fixed values that are not finite, e or mu_t
            outside [0, 1], a fixed release point inside a solid, a ball of radius <= 0.
        KeyError: a ball the scene does not have.
    """
    return _fit_all(scene, data, free=free, fixed=fixed, loss=loss, steps=steps, restarts=restarts,
                    max_segments=max_segments, progress=progress, balls=balls, anchors=anchors, prior=prior,
                    effects=effects)[0]


@dataclass
class _Units:
    """What a fit worked on, for a fit that goes on from it (``estim.fitting._pooled``):
    the keys, the fitted names, each key's problem (with the robust scale it ended with),
    start from the data and theta, the best theta, the noise read from the data and
    whether each key reached it."""

    names: list[str]
    free: tuple[str, ...]
    problems: list[_Problem]
    inits: list[Initial]
    starts: list[np.ndarray]
    theta: np.ndarray
    noises: list[float]
    floors: list[bool]


def _fit_all(scene, data, *, free, fixed, loss, steps, restarts, max_segments, progress, balls, anchors=None,
             devices=None, images=None, explore=False, prior=None, effects=False, graduated=()):
    """:func:`fit`, and what it worked on (``_Units``); the keys split over ``devices``
    (``estim.fitting._sharding``; default: one device). A key of ``images``
    (:class:`ImageRows`) is fitted to its pixels; its ``data`` is then a 3-D start (the
    path the starts are read from, ``estim.tracks._reconstruct``). With ``explore`` every
    key runs every restart, at its noise floor or not (where the floor itself is uncertain:
    a few frames of pixels). ``graduated`` (scales in the data's unit, decreasing): after the
    restarts, the starts run once more through a robust scale of no less than each of
    these in turn, then the noise's, and are kept where they end lower."""
    require_x64()
    if loss not in ROBUST_LOSSES:
        raise ValueError(f"unknown loss {loss!r}; choose one of {ROBUST_LOSSES}")
    bad = [n for n in free or () if n not in PARAMETERS and n not in (p.name for p in registry.REGISTRY)]
    if bad:
        raise ValueError(f"unknown parameter(s) {bad}; a fit can estimate {PARAMETERS}")
    ball_of = {b: (balls or {}).get(b, b) for b in data} if isinstance(data, dict) else {}
    _check_inputs(scene, data, fixed or {}, ball_of, MIN_ROWS if images else MIN_SAMPLES, units=images is None)
    say = progress or (lambda msg: None)
    names = list(data)
    lateral = any(np.isfinite(np.asarray(data[b][1])[:, 1]).any() for b in names)
    # A track in metres fits by default what its priors speak of (registry.default_free).
    known = tuple(registry.priors(scene, prior)) if images is None else ()
    free = registry.default_free(scene, lateral, known) if free is None else registry.expand(free)
    offsets = registry.component("dt_camera2").components
    registry.check_acting(scene, [n for n in free if n not in offsets])
    if set(registry.FACTOR_FREE) <= set(free) and "y0" not in free and lateral:
        free = tuple(free) + tuple(n for n in registry.LATERAL if n not in free)  # 3-D tracks: the lateral release state too
    images = images or {}
    n_cameras = min((len(images[b].cameras.matrix) if b in images else 1) for b in names) if names else 1
    unseen = [n for n in offsets[n_cameras - 1:] if n in free]
    if unseen:
        raise ValueError(f"fitting {unseen}: the clock offsets of cameras this data does not have "
                         f"({n_cameras} camera(s); image tracks, estim.fit_image)")
    if not names:
        raise ValueError("no balls to fit")
    gravity = _gravity_vector(scene)
    priors = _priors_of(scene, prior, free)
    fixed = fixed or {}
    if "t0" not in free:
        _check_release_time(data, fixed)
    starts, problems, inits = [], [], []
    noises = []  # read from the data, before any rescaling
    helds = []  # per ball, the fitted parameters it holds at its start (_on_surface)
    n_max = max(len(images[b].t) if b in images else len(np.asarray(data[b][0])) for b in names)
    for b in names:
        spec = scene.ball(ball_of[b])
        t, pos = (np.asarray(a, dtype=np.float64) for a in data[b])
        release = fixed.get(b, {}).get("t0", 0.0)
        if b in images:
            init = images[b].initial
        else:
            init = release_start(t, pos, gravity, release_time=release, curved=scene.air is not None)
        if scene.air is not None and b not in images:
            init = dataclasses.replace(init, spin=spin_start(init, t, pos, gravity, scene.air, spec.radius, spec.mass,
                                                             fixed.get(b, {}).get("lift_factor", 1.0)))
        support = None if b in images else _on_surface(scene, spec, init, free, fixed.get(b, {}))
        if support is not None:
            init = init.released_from_rest(support[1])
        helds.append(np.array([support is not None and n in RESTING for n in free]))
        inits.append(init)
        values = registry.starting_values(spec, init, free)
        values.update(fixed.get(b, {}))
        phi = registry.pack(values)
        if b in images:
            rows = images[b]
            t = rows.t
            obs = np.concatenate([rows.uv, np.zeros((len(t), 1))], axis=1)
            mask = np.concatenate([np.isfinite(obs[:, :2]).all(axis=1, keepdims=True).repeat(2, axis=1),
                                   np.zeros((len(t), 1), bool)], axis=1)
            view, cameras, noise = np.asarray(rows.view, dtype=np.int64), rows.cameras, rows.noise
        else:
            obs, mask, view, cameras, noise = pos, np.isfinite(pos), None, None, init.noise
        pad = n_max - len(t)
        noises.append(float(noise) if np.isfinite(noise) and noise > 0 else (1.0 if b in images else 2e-3))
        problems.append(_Problem(
            t=np.concatenate([t, np.full(pad, t[-1])]),
            obs=np.concatenate([np.nan_to_num(obs), np.zeros((pad, 3))]),
            mask=np.concatenate([mask, np.zeros((pad, 3), bool)]),
            radius=np.float64(spec.radius),
            mass=np.float64(spec.mass),
            inertia=np.float64(spec.inertia),
            fixed=phi,
            scale=np.float64(noises[-1]),
            anchor=np.asarray((anchors or {}).get(b, (0.0, 0.0, 0.0)), dtype=np.float64),
            size=np.int64(len(t)),
            view=None if view is None else np.concatenate([view, np.zeros(pad, np.int64)]),
            cameras=cameras,
            prior=registry.prior_arrays(priors) if priors else None,
        ))
        starts.append(registry.to_theta(phi, free))
        say(f"{b}: {len(init.flights)} flights, {len(init.bounces)} bounces resolved; "
            f"start e={init.e:.3f} mu_t={init.mu_t:.3f} vx0={init.vx0:.3f}"
            + ("" if support is None else f"; released on {support[0]}'s top (z0={support[1]:.4f} held)"))
    if any(h.any() for h in helds):
        problems = [dataclasses.replace(pr, held=h) for pr, h in zip(problems, helds, strict=True)]
    batch = jax.tree.map(lambda *xs: np.stack(xs), *problems)
    mesh = None if devices is None else mesh_of(devices)

    def run(theta, problems):
        """``_run`` on the keys of ``theta`` at once, split over the devices (padded with
        copies of the first, every sample masked)."""
        n = theta.shape[0]
        padded = padded_size(n, mesh)
        theta = np.concatenate([theta, np.repeat(theta[:1], padded - n, axis=0)])
        problems = jax.tree.map(lambda x: np.concatenate([x, np.repeat(x[:1], padded - n, axis=0)]), problems)
        problems = eqx.tree_at(lambda p: p.mask, problems, problems.mask & (np.arange(padded) < n)[:, None, None])
        out = gather(_run(scene, tuple(free), loss, steps, max_segments, place(theta, mesh),
                          jax.tree.map(lambda x: place(x, mesh), problems), mesh))
        return jax.tree.map(lambda x: x[:n], out)

    def run_rows(theta, problems, rows):
        """``run`` on the keys ``rows`` only where that is worth a program of its own (a
        large batch of which at most half restart: the keys ``rows`` padded to a power of
        two, at least ``SUBSET_MIN``, so that few sizes compile), else on every key.
        Returns the results and the key of each of their rows."""
        if len(names) <= 2 * SUBSET_MIN or 2 * len(rows) > len(names):
            return run(theta, problems), list(range(len(names)))
        size = max(SUBSET_MIN, 1 << (len(rows) - 1).bit_length())
        pick = np.array(rows + [rows[0]] * (size - len(rows)))
        sub = jax.tree.map(lambda x: x[pick], problems)
        sub = eqx.tree_at(lambda p: p.mask, sub, sub.mask & (np.arange(size) < len(rows))[:, None, None])
        return run(theta[pick], sub), rows

    # Growing window: first up to the third resolved bounce, then everything.
    windows = []
    for init in inits:
        windows.append(init.bounces[2] + 0.05 if len(init.bounces) >= 3 else np.inf)
    theta = np.stack(starts)
    if np.any(np.isfinite(windows)):
        say("fitting the first bounces")
        early = eqx.tree_at(lambda p: p.mask, batch, batch.mask & (batch.t <= np.asarray(windows)[:, None])[..., None])
        theta, _, diag = run(theta, early)
        # The robust scale: the noise read from the data, or the spread of the residuals of
        # the early fit if larger (a model that misses some physics must not turn every
        # sample into an 'outlier'). A ball with fewer than three resolved bounces has no
        # early window: its run here started from a guess and may have stopped far from
        # the optimum, so its spread says nothing about the model and the noise stays.
        scales = [_spread(diag, i, float(pr.scale)) if np.isfinite(windows[i]) else float(pr.scale)
                  for i, pr in enumerate(problems)]
        problems, batch = _with_scales(problems, batch, scales)
    say("fitting all data")
    theta, history, diag = run(theta, batch)
    floors = [_at_floor(diag, i, noises[i]) for i in range(len(names))]
    best_theta, best_diag, best_hist = jax.tree.map(np.array, (theta, diag, history))  # writable copies
    # Multi-start for balls above the noise floor: e from a grid across its range (the
    # basin of the right e can be narrow where bounces land near tread edges or a series
    # goes Zeno), mu_t and vx0 from the data-driven start, slightly perturbed.
    rng = np.random.default_rng(0)
    grid = np.linspace(0.3, 0.9, restarts) if restarts > 1 else np.array([0.6])
    for attempt in range(restarts):
        todo = [explore or not ok for ok in floors]
        if not any(todo):
            break
        say(f"restart {attempt + 1}: {[n for n, go in zip(names, todo, strict=True) if go]}"
            + ("" if explore else " above the noise floor"))
        trial = np.asarray(best_theta).copy()
        for i, go in enumerate(todo):
            if go:
                trial[i] = _restart(starts[i], free, problems[i].fixed, inits[i],
                                    fixed.get(names[i], {}), grid[attempt], rng)
        rows = [i for i, go in enumerate(todo) if go]
        tried, at = run_rows(trial, batch, rows)
        for k, i in enumerate(at):
            if (_objective(tried[2], k, loss, problems[i], tried[0][k], free)
                    < _objective(best_diag, i, loss, problems[i], best_theta[i], free)):
                _adopt_row((best_theta, best_hist, best_diag), tried, i, k)
        floors = [_at_floor(best_diag, i, noises[i]) for i in range(len(names))]
    # A graduated scale (Blake and Zisserman 1987's graduated non-convexity), from the
    # starts once more: at a wide scale the robust loss is nearly quadratic over a start's
    # misses and leads towards the path that explains every sample; at a scale far below
    # those misses, a path that explains a subset of the samples and calls the rest
    # outliers is a local minimum of its own. Kept where it ends lower at the noise. (Every
    # key runs it: a fit at its floor without outliers may still be the higher of two
    # minima, as one camera's paths along its rays can be.)
    rows = [i for i in range(len(names)) if graduated and noises[i] < graduated[0]]
    if rows:
        say(f"graduated scale from {graduated[0]:g}: {[names[i] for i in rows]}")
        trial = np.stack(starts)
        for wide in [w for w in graduated if any(noises[i] < w for i in rows)] + [0.0]:
            _, scaled = _with_scales(problems, batch, [max(float(pr.scale), wide) for pr in problems])
            tried, at = run_rows(trial, scaled, rows)
            trial = trial.copy()
            for k, i in enumerate(at):
                trial[i] = tried[0][k]
        for k, i in enumerate(at):
            if i in rows and (_objective(tried[2], k, loss, problems[i], tried[0][k], free)
                              < _objective(best_diag, i, loss, problems[i], best_theta[i], free)):
                _adopt_row((best_theta, best_hist, best_diag), tried, i, k)
        floors = [_at_floor(best_diag, i, noises[i]) for i in range(len(names))]
    # The robust scale once more, from the best fit's residuals. The early fit may have
    # stopped far from its optimum (started from a poor guess) and read a spread the data
    # do not have; with too wide a scale the outliers pull on the estimates. Where the
    # spread is now clearly smaller, polish from the best point with it.
    scales = [_spread(best_diag, i, noises[i]) for i in range(len(names))]
    wider = [float(pr.scale) > 1.1 * s for pr, s in zip(problems, scales, strict=True)]
    if any(wider):
        say(f"polishing {[n for n, w in zip(names, wider, strict=True) if w]} at the noise read from the residuals")
        problems, batch = _with_scales(problems, batch, [s if w else float(pr.scale) for pr, s, w in zip(problems, scales, wider, strict=True)])
        polished, at = run_rows(np.asarray(best_theta), batch, [int(i) for i in np.flatnonzero(wider)])
        for k, i in enumerate(at):
            if wider[i]:
                _adopt_row((best_theta, best_hist, best_diag), polished, i, k)
        floors = [_at_floor(best_diag, i, noises[i]) for i in range(len(names))]
    results = {}
    for i, b in enumerate(names):
        results[b] = _report(scene, b, free, loss, best_theta[i], best_diag, i, problems[i], inits[i], np.asarray(best_hist[i]), floors[i], noises[i])
        explain_misfit(scene, results[b], problems[i], free)
        if effects:
            attach_effects(scene, results[b], problems[i])
    units = _Units(names=names, free=tuple(free), problems=problems, inits=inits, starts=starts,
                   theta=np.asarray(best_theta), noises=noises, floors=floors)
    return FitResult(results), units


def explain_misfit(scene: Scene, report: BallFit, problem: _Problem, free: Sequence[str]) -> None:
    """For a fit above its noise floor (``estim.fitting._missing_physics``): whether its path
    bounces on two surfaces the scene declares different (``one_restitution``); in a scene
    without air, how far the air the scene leaves out would move this ball over this track; in
    a scene with air, how far the air coefficients the fit held (not in ``free``) would, a
    quarter off. In ``report.missing_physics`` and, where it could explain the misfit, as a
    note.
    A fit released inside a solid gets a note saying so instead."""
    params, span, noise = _fitted_ball(scene, report, problem)
    solids = solids_at_release(scene, params)[0]
    if solids:
        # (Nothing in the fit's program keeps the release out of a solid; a simulation
        # refuses it, and so the diagnostics below cannot run.)
        report.notes.append(f"the fitted release point {[round(report.values[n], 4) for n in ('x0', 'y0', 'z0')]} "
                            f"lies inside {solids[0]!r}: this path is no physical one; the data do not fix the "
                            "release (too few rows before the first bounce?)")
        return
    if report.at_noise_floor or not math.isfinite(report.rms_m):
        return
    surfaces = one_restitution(scene, report.contacts, report.ball, report.values["e"], report.n_outliers)
    report.notes.extend(m["advice"] for m in surfaces)
    if not span > 0:
        report.missing_physics = surfaces
        return
    if scene.air is None:
        probe = functools.partial(missing_physics, scene, params, span, noise, report.ball)
    else:
        held = tuple(n for n in HELD if n not in free)
        probe = functools.partial(held_coefficients, scene, params, span, noise, report.ball, held)
    report.missing_physics = surfaces + _diagnostic(report, "the missing-physics probes", probe)
    for m in report.missing_physics[len(surfaces):]:
        if m["explains"]:
            m["advice_note"] = format_note(m, float(problem.mass))
            report.notes.append(m["advice_note"])


def attach_effects(scene: Scene, report: BallFit, problem: _Problem) -> None:
    """``report.effects``: how far each effect of the model moves the fitted ball over its
    track, in noise levels (``estim.fitting._missing_physics.model_effects``; ``[]`` where
    the track gives no span or noise to measure them by)."""
    params, span, noise = _fitted_ball(scene, report, problem)
    ok = span > 0 and math.isfinite(noise) and noise > 0 and not solids_at_release(scene, params)[0]
    sizes = functools.partial(model_effects, scene, params, span, noise)
    report.effects = _diagnostic(report, "the effects' sizes", sizes) if ok else []


def _diagnostic(report: BallFit, what: str, probe: Callable[[], list[dict]]) -> list[dict]:
    """``probe()``, a diagnostic of a finished fit; where one of its simulations cannot
    complete (``simulate``'s ``RuntimeError``: a probe's ball, its coefficient moved, may
    meet what the fitted one does not), ``[]`` and a note saying so. The fit is the answer;
    a diagnostic that fails must not take it away."""
    try:
        return probe()
    except RuntimeError as err:
        report.notes.append(f"{what} did not run ({err}): the fit stands, without them")
        return []


def _fitted_ball(scene: Scene, report: BallFit, problem: _Problem):
    """The fitted ball (``Params``, with its mass), the time its track covers after the
    release (s) and the track's noise in metres."""
    valid = np.asarray(problem.mask).any(axis=1)
    span = float(np.max(np.asarray(problem.t)[valid])) - report.values["t0"]
    params = registry.to_params(report.values, radius=problem.radius, mass=problem.mass,
                                inertia=problem.inertia, scene=scene)
    return params, span, report.noise_m * metres_per_unit(problem, report.model_position)


def metres_per_unit(problem: _Problem, position) -> float:
    """Metres per unit of a problem's residuals: 1 for tracks in metres; for image tracks
    the median, over the rows, of a pixel's size at the fitted ball (depth over focal
    length), which turns the pixels' noise into the metres that effect sizes compare."""
    if problem.cameras is None:
        return 1.0
    n = int(problem.size)
    view = np.asarray(problem.view)[:n]
    cams = jax.tree.map(np.asarray, problem.cameras)
    depth = np.einsum("ni,ni->n", cams.rotation[view, 2], np.asarray(position)[:n]) + cams.translation[view, 2]
    return float(np.median(depth / cams.matrix[view, 0, 0]))


def amount(value: float, unit: str) -> str:
    """A residual or a noise level as the tables print it: ``"1.23 mm"`` or ``"0.87 px"``."""
    return f"{value:.2f} px" if unit == "px" else f"{value * 1e3:.2f} mm"


# A track that starts this long after the release (s) is worth a word when its fit fails:
# a video's clock rarely starts at the release, and the model's does.
LATE_START = 1.0


def _check_release_time(data, fixed) -> None:
    """With the release time held fixed (default 0: the data's time origin), a sample before
    it would have no model to compare with: refuse it rather than leave it out."""
    for b, (t, pos) in data.items():
        t, pos = np.asarray(t, dtype=np.float64), np.asarray(pos, dtype=np.float64)
        release = float(fixed.get(b, {}).get("t0", 0.0))
        early = np.flatnonzero((t < release) & np.any(np.isfinite(pos), axis=1))
        if early.size:
            raise ValueError(
                f"ball {b!r}: {early.size} sample(s) lie before the release at t0 = {release:g} s "
                f"(the first at t = {float(t[early[0]]):g} s); the model releases each ball at t0, "
                "by default the data's t = 0: shift the times so that the release is at t = 0, "
                "give the release time (fixed t0), or fit it (free t0; CLI: --also t0)"
            )


def _check_inputs(scene, data, fixed, ball_of=None, min_samples: int = MIN_SAMPLES, units: bool = True) -> None:
    """Reject data and fixed values that fit cannot use, naming the ball and the problem:
    nothing is dropped, clipped, reordered or rescaled silently. NaN in a position is a lost
    detection (masked); anything else must be finite. ``units``: check that each track falls
    with the scene's gravity (``check_units``); not for a start read from pixels, which is
    in metres by the cameras' calibration and whose parabolas may span a contact the start
    did not find (a ball clipping the net), which no unit explains."""
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be an estim.Scene (estim.load_scene), got {type(scene).__name__}")
    if not isinstance(data, dict):
        raise TypeError(f"data must be a dict ball -> (t, position), got {type(data).__name__}")
    if not data:
        raise ValueError("no balls to fit")
    ball_of = ball_of or {b: b for b in data}
    g = float(scene.gravity)
    for b, value in data.items():
        spec = scene.ball(ball_of[b])  # KeyError naming the scene's balls
        if not (math.isfinite(spec.radius) and spec.radius > 0):
            raise ValueError(f"ball {b!r}: the scene gives it radius {spec.radius!r}; a radius "
                             "must be > 0 (metres)")
        try:
            t, pos = value
        except (TypeError, ValueError):
            raise ValueError(f"ball {b!r}: data must be a pair (t, position)") from None
        t, pos = np.asarray(t, dtype=np.float64), np.asarray(pos, dtype=np.float64)
        if t.ndim != 1 or pos.shape != (t.shape[0], 3):
            raise ValueError(f"ball {b!r}: t must have shape (n,) and position (n, 3), got "
                             f"{t.shape} and {pos.shape}")
        bad = np.flatnonzero(~np.isfinite(t))
        if bad.size:
            raise ValueError(f"ball {b!r}: t[{bad[0]}] = {float(t[bad[0]])!r} is not a finite "
                             "time (s)")
        # Times of the rows with data must increase strictly (rows without any coordinate,
        # such as the padding of estim.fitting._job.fit_pixels, carry no data and are masked).
        rows = np.flatnonzero(np.any(np.isfinite(pos), axis=1))
        bad = np.flatnonzero(np.diff(t[rows]) <= 0)
        if bad.size:
            i, j = int(rows[bad[0] + 1]), int(rows[bad[0]])
            what = "repeats" if t[i] == t[j] else "goes back from"
            raise ValueError(f"ball {b!r}: time t[{i}] = {float(t[i])!r} {what} t[{j}] = "
                             f"{float(t[j])!r}; times must increase strictly (sort the "
                             "samples, remove duplicates)")
        bad = np.argwhere(np.isinf(pos))
        if bad.size:
            i, k = (int(v) for v in bad[0])
            raise ValueError(f"ball {b!r}: position[{i}] {'xyz'[k]} = {float(pos[i, k])!r} is infinite "
                             "(a lost detection is NaN)")
        n = int(np.sum(np.all(np.isfinite(pos[:, [0, 2]]), axis=1)))
        if n < min_samples:
            raise ValueError(f"ball {b!r}: only {n} samples with x and z; a fit needs at least "
                             f"{min_samples}")
        if units:
            check_units(t, pos[:, 2], g, where=f"ball {b!r}")
    if not isinstance(fixed, dict):
        raise TypeError(f"fixed must be a dict ball -> {{parameter: value}}, got {type(fixed).__name__}")
    for b, values in fixed.items():
        if b not in data:
            raise ValueError(f"fixed names ball {b!r}, which is not in the data {list(data)}")
        for name, v in values.items():
            if name not in PARAMETERS:
                raise ValueError(f"fixed[{b!r}]: unknown parameter {name!r}; the parameters "
                                 f"are {PARAMETERS}")
            entry = registry.component(name)
            v = float(v)
            if not math.isfinite(v):
                raise ValueError(f"fixed[{b!r}][{name!r}] = {v!r} must be finite")
            why = entry.transform.refuse(v)
            if why:
                raise ValueError(f"fixed[{b!r}][{name!r}] = {v!r} {why}")
            if entry.zero_where_idle and v != 0 and not entry.acts(scene):
                raise ValueError(f"fixed[{b!r}][{name!r}] = {v!r}: {entry.name} acts only "
                                 f"{entry.acts_where}, and this scene does not have it")
        if "x0" in values and "z0" in values:
            spec = scene.ball(ball_of[b])
            y0 = float(values.get("y0", spec.position[1]))
            release = (float(values["x0"]), y0, float(values["z0"]))
            try:
                check_outside(scene, Params(0.5, 0.5, spec.radius, release, (0.0, 0.0, 0.0)))
            except ValueError as err:
                raise ValueError(f"fixed release point of ball {b!r}: {err}") from None


def _objective(diag, i, loss, problem, theta=None, free=()):
    """The robust loss of key i's residuals, and of its priors at ``theta``."""
    r, _, (valid, _, _) = diag
    out = float(np.sum(np.where(valid[i], robust_loss(r[i] / problem.scale, loss), 0.0)))
    if theta is not None and problem.prior is not None:
        phi = registry.to_physical(np.asarray(theta), free, problem.fixed)
        out += float(np.sum(robust_loss(np.asarray(_prior_rows(phi, problem)) / problem.scale, loss)))
    return out


def _priors_of(scene: Scene, prior, free) -> dict[str, tuple[float, float]]:
    """The priors a fit applies: those of ``registry.priors`` on the fitted parameters.

    Raises:
        ValueError: a prior given (not the scene's) on a parameter the fit holds.
    """
    given = [n for name, spec in (prior or {}).items() if spec is not None for n in registry.expand((name,))]
    held = [n for n in given if n not in free]
    if held:
        raise ValueError(f"a prior on {held}, which this fit holds (not in free): fit it, or drop the prior")
    return {n: v for n, v in registry.priors(scene, prior).items() if n in free}


def _adopt_row(best, result, i, k) -> None:
    """Key i of ``best`` takes its values from row k of the run ``result``."""
    for x, y in zip(jax.tree.leaves(best), jax.tree.leaves(result), strict=True):
        x[i] = y[k]


def _adopt(best, result, i) -> None:
    """Ball i of ``best`` (writable NumPy copies of a run's point, history and diagnostics)
    takes its values from the run ``result``."""
    for x, y in zip(jax.tree.leaves(best), jax.tree.leaves(result), strict=True):
        x[i] = y[i]


def _gravity_vector(scene: Scene) -> np.ndarray:
    """The scene's gravity as a vector (m/s^2). ``Scene.gravity`` is the magnitude of a
    gravity along -z (``load_scene`` refuses any other direction: the forward model's
    contacts assume it); the starts (``release_start``) take the vector, so a scene that
    carries another direction only has to hand it here."""
    return np.array([0.0, 0.0, -float(scene.gravity)])


# What a ball released resting on a surface holds (``_on_surface``), and how far (in noise
# levels of the heights, at least RESTING_TOL_M) the run's mean height may lie from the
# centre's height on a surface.
RESTING = ("z0", "vz0")
RESTING_TOL, RESTING_TOL_M = 4.0, 3e-3


def _on_surface(scene: Scene, spec, init: Initial, free, fixed: dict) -> tuple[str, float] | None:
    """``(solid, height)`` where the track starts with the ball on a surface: its first
    samples keep one height (``Initial.rest``) at which the ball's centre lies on an upward
    face of ``solid`` under it (``estim.forward._balls.resting_on``). The fit then releases
    the ball from that run (``Initial.released_from_rest``), ``z0`` the height on that face
    and ``vz0 = 0``, and holds both (``_Problem.held``): under the seed's factor law a ball
    released any height above the face bounces a Zeno series there whose every impact
    scales its horizontal speed by mu_t, and stops, where the one on the face slides on and
    leaves its edge; below the face it starts inside the solid. The loss is discontinuous
    at the data's own z0, and one-sided: no derivative there moves the fit anywhere useful.
    None where the track starts in flight, the caller fixes z0 or vz0, or no face lies
    under the run."""
    if init.rest is None or "z0" not in free or {"z0", "vz0"} & set(fixed):
        return None
    x, y, z = init.rest.position
    point = (x, spec.position[1] if y is None else y, z)
    noise = init.noise if math.isfinite(init.noise) else 0.0
    return resting_on(scene, point, spec.radius - fixed.get("compression", 0.0), max(RESTING_TOL * noise, RESTING_TOL_M))


def _restart(theta, free, fixed_phi, init: Initial, fixed: dict, e: float, rng) -> np.ndarray:
    """theta of a restart from the start ``theta``: e at ``e`` (a point of the grid over its
    range), mu_t at ``MU_DEFAULT`` where ``_restart_mu_at_default`` says so, mu_t perturbed
    by up to 0.02 and the release speed along the direction of travel by up to 0.03 m/s
    (one draw each, in this order, for the fitted ones), e and mu_t kept in [0.02, 0.995]."""
    phi = registry.to_physical(theta, free, fixed_phi)
    k = dict(zip(PARAMETERS, range(len(PARAMETERS)), strict=True))
    if "e" in free:
        phi[k["e"]] = e
    if _restart_mu_at_default(init, free, fixed):
        phi[k["mu_t"]] = MU_DEFAULT
    if "mu_t" in free:
        phi[k["mu_t"]] = phi[k["mu_t"]] + 0.02 * rng.uniform(-1, 1)
    if "vx0" in free or "vy0" in free:
        # Along the direction of travel u (``(1, 0, 0)`` for a track without y): the
        # component along x of a draw r is 0.03 * 1.0 * r, exactly the draw along x.
        dv = 0.03 * rng.uniform(-1, 1)
        for n, u in (("vx0", init.direction[0]), ("vy0", init.direction[1])):
            if n in free:
                phi[k[n]] = phi[k[n]] + u * dv
    for n in ("e", "mu_t"):
        phi[k[n]] = np.clip(phi[k[n]], 0.02, 0.995)
    return registry.to_theta(phi, free)


def _restart_mu_at_default(init: Initial, free, fixed) -> bool:
    """Whether restarts start mu_t at ``MU_DEFAULT`` instead of its start from the data:
    that start was clipped to its range (no information), or lies above the default, where
    the sigmoid's slope mu (1 - mu) falls towards 0 and holds the parameter nearly still."""
    return "mu_t" in free and "mu_t" not in fixed and not MU_RANGE[0] < init.mu_t <= MU_DEFAULT


def _spread(diag, i, floor) -> float:
    """Robust standard deviation of ball i's valid residuals (1.4826 times their median
    absolute deviation), floored at ``floor``."""
    r, _, (valid, _, _) = diag
    rv = np.asarray(r[i])[np.asarray(valid[i])]
    mad = 1.4826 * np.median(np.abs(rv - np.median(rv))) if rv.size else 0.0
    return max(float(mad), float(floor))


def _with_scales(problems, batch, scales):
    """The problems and their batch with new robust scales."""
    problems = [eqx.tree_at(lambda p: p.scale, pr, np.float64(s)) for pr, s in zip(problems, scales, strict=True)]
    return problems, eqx.tree_at(lambda p: p.scale, batch, np.asarray(scales, dtype=np.float64))


def _inliers(diag, i, noise):
    """Residuals, validity, and the inliers: within 4 robust standard deviations of the
    residuals (``_spread``, floored at the noise level read from the data)."""
    r, _, (valid, _, _) = diag
    r, valid = np.asarray(r[i]), np.asarray(valid[i])
    keep = valid & (np.abs(r) <= 4 * _spread(diag, i, noise))
    return r, valid, keep


def _at_floor(diag, i, noise) -> bool:
    """The rms of the inliers is within 30% of the noise level read from the data."""
    r, valid, keep = _inliers(diag, i, noise)
    rms = math.sqrt(np.mean(r[keep] ** 2)) if keep.any() else math.inf
    return rms <= 1.3 * noise


@fit_program
def _run(scene, free, loss, steps, max_segments, theta, batch, mesh=None, rolls=True):
    """Levenberg-Marquardt on the robust loss, ball by ball: at most ``steps`` iterations,
    fewer where the loss has settled (``_settled``).

    Returns the best point per ball, the loss histories ``(balls, steps)`` (a ball that
    stopped early repeats its last value), the residuals, Jacobian (with respect to
    theta), validity mask, model positions and impact count at the best point, and
    whether a plan of the ball had a roll left out (``fit_program``). Each ball
    runs its own loop of iterations, one ball after the other
    (``estim.fitting._sharding.per_unit``, over the devices of ``mesh``); a ball's replay
    runs only the slots its own plan uses (``estim.forward._scan``).
    """
    m = batch.obs[0].size  # residuals per ball
    n_theta = theta.shape[1]

    def one(theta, pr):
        best = (jnp.zeros(m), jnp.zeros((m, n_theta)),
                (jnp.zeros(m, bool), jnp.zeros(pr.obs.shape), jnp.full(LISTED_EVENTS, -1, jnp.int32)))

        def going(loop):
            k, _, history, _ = loop
            return (k < steps) & ~_settled(history, k)

        def iteration(loop):
            k, c, history, rolled = loop
            pl, used = _plan_at(scene, registry.to_physical(c[0], free, pr.fixed), pr, max_segments)
            c, value = _lm_step(scene, free, loss, c, pr, pl, used, rolls)
            return k + 1, c, history.at[k].set(value), rolled | _rolled(scene, pl, rolls)

        k, (_, state, best), history, rolled = jax.lax.while_loop(
            going, iteration, (jnp.int32(0), (theta, _LM.init(theta), best), jnp.full(steps, jnp.inf), jnp.bool_(False)))
        return state.best_params, jnp.where(jnp.arange(steps) < k, history, history[k - 1]), best, rolled

    return per_unit(one, mesh, theta, batch)


def _settled(history, k):
    """Whether a ball's best loss (``history``, non-increasing, its first ``k`` entries
    filled) fell by at most ``SETTLED_TOL`` of itself (or of 1) over its last ``SETTLED``
    iterations: more iterations would not move it (the report then calls it converged,
    ``_report``). Ten, not fewer: a camera fit of 15 frames went on improving (1.49 to
    1.37 px rms) after five iterations without progress."""
    last = history[jnp.maximum(k - 1, 0)]
    first = history[jnp.maximum(k - SETTLED, 0)]
    return (k >= SETTLED) & (first - last <= SETTLED_TOL * jnp.maximum(jnp.abs(last), 1.0))


def _report(scene, ball, free, loss, theta, diag, i, problem, init, history, at_floor, noise) -> BallFit:
    r, J, (_, pos, impacts) = jax.tree.map(lambda a: np.asarray(a[i]), diag)
    phi = registry.to_physical(np.asarray(theta), free, problem.fixed)
    # The values of the parameters that act in the scene (under the friction law: mu, not mu_t).
    acting = registry.acting(scene)
    n_cameras = 1 if problem.cameras is None else len(problem.cameras.matrix)
    seen = registry.component("dt_camera2").components[:n_cameras - 1]  # the clocks of the data's other cameras
    values = {n: float(v) for n, v in registry.unpack(phi).items() if n in acting or n in seen}
    # Jacobian with respect to the physical parameters: d phi / d theta per column.
    dphi = registry.slopes(phi, free)
    at_bound = dphi < 1e-10  # sigmoid saturated: the parameter sits on the edge of its range
    J = np.where(at_bound[None, :], 0.0, J / np.where(at_bound, 1.0, dphi)[None, :])
    w = robust_weight(r / problem.scale, loss)
    r_all, valid_np, keep = _inliers(diag, i, noise)
    n_obs = int(np.asarray(problem.mask).any(axis=1).sum())
    rms = math.sqrt(np.mean(r_all[keep] ** 2)) if keep.any() else math.nan
    # Gauss-Newton covariance with robust weights and the residual noise estimate.
    w = w * valid_np
    Jw = J * np.sqrt(w)[:, None]
    # Noise variance from the inlier residuals (unweighted: robust weights below 1 would
    # shrink it), with the degrees of freedom they carry.
    dof = max(int(keep.sum()) - len(free), 1)
    s2 = float(np.sum(r_all[keep] ** 2) / dof)
    notes = []
    # The priors as rows in the data's units (sqrt(s2) / sd on their parameter): with them
    # J^T W J + Jp^T Jp is the posterior's information times s2.
    weight = np.zeros(len(free)) if problem.prior is None else np.asarray(problem.prior[1])[registry.index(free)]
    with_prior = weight > 0
    sd_prior = np.divide(1.0, weight, out=np.full(len(free), np.inf), where=with_prior)
    Jp = (np.eye(len(free)) * math.sqrt(s2) / np.where(with_prior, sd_prior, 1.0))[with_prior]
    # The robust loss weighs the prior's rows as it weighs the data's.
    u_prior = (np.zeros(0) if problem.prior is None else
               np.asarray(_prior_rows(phi, problem))[registry.index(free)][with_prior] / float(problem.scale))
    w_prior = np.asarray(robust_weight(u_prior, loss))
    Jw = np.concatenate([Jw, Jp])
    col = np.linalg.norm(Jw, axis=0)
    scale_cols = np.where(col > 0, col, 1.0)
    Jn = Jw / scale_cols
    u, sv, vt = np.linalg.svd(Jn, full_matrices=False)
    identifiable = np.ones(len(free), bool)
    weak = sv < 1e-6 * sv.max() if sv.size else np.array([], bool)
    for k in np.flatnonzero(weak):
        involved = np.abs(vt[k]) > 0.3
        identifiable &= ~involved
    identifiable &= col > 1e-9 * max(col.max(), 1e-300)
    identifiable &= ~at_bound
    held = np.zeros(len(free), bool) if problem.held is None else np.asarray(problem.held)
    for k, n in enumerate(free):
        if held[k]:
            notes.append(f"{n} = {values[n]:.6g} held: the track starts with the ball on a surface "
                         f"({init.rest.stop - init.rest.start:.2f} s without vertical motion)")
        elif at_bound[k]:
            notes.append(f"{n} = {values[n]:.6f} sits on the edge of its range: no standard error")
        elif not identifiable[k]:
            notes.append(f"{n} is not identifiable from this data" + (
                " (no bounce observed)" if registry.component(n).needs_bounce and not init.bounces else ""))
    stderr = {n: math.nan for n in free}
    corr = np.full((len(free), len(free)), np.nan)
    # Every parameter that moves the model enters the covariance, those in a direction the
    # data leave open too: the pseudo-inverse leaves that direction out, so that the
    # identifiable parameters' errors count their correlation with what the data do fix of
    # the others (dropping the others would hold them fixed and understate those errors).
    ids = np.flatnonzero((col > 1e-9 * max(col.max(), 1e-300)) & ~at_bound) if identifiable.any() else np.zeros(0, int)
    if ids.size:
        try:
            # Sandwich form of the weighted least-squares covariance: A^-1 B A^-1 with
            # A = J^T W J, B = J^T W^2 J (Huber 1967); for inliers (W ~ 1) it is s^2 (J^T J)^-1.
            Jr = J[:, ids] * valid_np[:, None] / scale_cols[ids]
            Jq = Jp[:, ids] / scale_cols[ids]
            A = Jr.T @ (w[:, None] * Jr) + Jq.T @ (w_prior[:, None] * Jq)
            B = Jr.T @ ((w**2)[:, None] * Jr) + Jq.T @ ((w_prior**2)[:, None] * Jq)
            Ainv = np.linalg.pinv(A, rcond=1e-12, hermitian=True)
            cov = s2 * (Ainv @ B @ Ainv) / np.outer(scale_cols[ids], scale_cols[ids])
            sd = np.sqrt(np.clip(np.diag(cov), 0, None))
            sd_safe = np.where(sd > 0, sd, 1.0)
            for a, k in enumerate(ids):
                if identifiable[k]:
                    stderr[free[k]] = float(sd[a])
            sub = cov / np.outer(sd_safe, sd_safe)
            known = identifiable[ids]
            corr[np.ix_(ids[known], ids[known])] = sub[np.ix_(known, known)]
        except np.linalg.LinAlgError:
            notes.append("the Gauss-Newton matrix is singular: no standard errors")
    prior = {n: (float(np.asarray(problem.prior)[0, registry.index((n,))[0]]), float(sd_prior[k]))
             for k, n in enumerate(free) if with_prior[k]}
    for n, (mean, sd) in prior.items():
        if math.isfinite(stderr[n]) and stderr[n] > PRIOR_DECIDES * sd:
            notes.append(f"{n} is held by its prior {mean:g} +- {sd:g} more than by the data (standard error "
                         f"{stderr[n]:.3g}): the data say little about it")
    contacts = tuple(scene.face_label(int(f)) for f in impacts[impacts >= 0])
    unit = "m" if problem.cameras is None else "px"
    improvement = np.abs(np.diff(history[-4:])) if len(history) >= 4 else np.array([np.inf])
    converged = bool(np.all(np.isfinite(history[-1:])) and np.all(improvement <= 1e-6 * max(abs(history[-1]), 1.0))
                     and math.isfinite(rms))
    if not keep.any():
        notes.append("no sample lies after the fitted release time t0: nothing was fitted")
    elif not at_floor:
        notes.append(f"rms residual {amount(rms, unit)} is above the noise level {amount(noise, unit)} read from the data: a local minimum, or physics the model lacks"
                     + (" (air drag)" if scene.air is None else " (or air coefficients it holds)"))
        delay = float(np.min(problem.t[np.asarray(problem.mask).any(axis=1)])) - values["t0"]
        if delay > LATE_START:
            notes.append(f"the first sample is {delay:.2f} s after the release at t0 = {values['t0']:g} s: "
                         "if the data's clock does not start at the release, shift the times so that it does")
    n = int(problem.size)
    return BallFit(
        ball=ball,
        values=values,
        stderr=stderr,
        names=tuple(free),
        correlation=corr,
        rms_m=rms,
        noise_m=noise,
        n_obs=n_obs,
        n_outliers=int((valid_np & ~keep).reshape(-1, 3).any(axis=1).sum()),
        n_bounces=len(contacts),
        contacts=contacts,
        converged=converged,
        at_noise_floor=at_floor,
        notes=notes,
        loss_history=history,
        initial=init,
        model_t=np.asarray(problem.t)[:n],
        model_position=np.asarray(pos)[:n],
        residuals=r_all.reshape(-1, 3)[:n],
        unit=unit,
        prior=prior,
    )
