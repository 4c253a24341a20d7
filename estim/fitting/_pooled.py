"""Many clips, one answer: parameters shared across clips of one ball, fitted together.

A person who measures restitution films the same ball on the same surface many times. Each
track of a ball in a clip (a *unit*) keeps its own release state (and time offset, pixel
scale and surface row, which are the clip's), and the *shared* parameters (``e``, the
drag coefficient, ...: names of the registry ``estim.fitting._registry``) take one value per
ball across all clips. The pipeline:

1. **One by one**: every unit is fitted alone (:func:`estim.fit`, all units in one batched
   program, with its restarts for units above their noise floor). This gives each unit's
   start and its robust scale ``s_i`` (its noise level). No priors, the scene's included
   (``Scene.priors``): many clips fix what one cannot, and a prior on a shared value
   counted once per clip would weigh as many times too much.
2. **Together**: Levenberg-Marquardt on ``sum_i sum_k rho(r_ik / s_i)`` over the shared
   values ``a`` (per ball) and every unit's own values ``b_i``. The Jacobian of unit i is
   ``[A_i | B_i]`` (its residuals depend on a and b_i only), so the damped normal equations
   have an arrow shape and the Schur complement solves them at the cost of one small
   system per unit and one per ball (as in bundle adjustment; Triggs et al. 2000, sec. 6):

       (H_aa - sum_i H_ab,i H_bb,i^-1 H_ba,i) da = -g_a + sum_i H_ab,i H_bb,i^-1 g_b,i,
       db_i = -H_bb,i^-1 (g_b,i + H_ba,i da),

   with ``H = J^T W J`` and ``g = J^T W r`` per unit (r and J divided by ``s_i``, W the
   robust weights), each diagonal block damped by ``lambda diag``. It stops after
   ``joint_steps`` iterations, or once the loss has settled (ten iterations within 1e-6)
   below where it started: a loss that has not moved from the start is a run of refused
   steps while the damping grows, not an optimum. The units are one axis
   of one program, padded to a common length and masked, as in a single fit: each unit's
   simulation and Jacobian in a loop over the units (``estim.fitting._sharding.per_unit``),
   the sums over units reductions over that axis, so the same program runs sharded: the
   unit axis split over every device JAX sees (``jax.sharding``; each device loops over
   its own units), the sums becoming all-reduces. Units that reached their noise floor
   alone but not together restart their own values from their one-by-one fit, then from
   the data's start, and the joint fit is kept where its loss falls.
3. **Uncertainty** of the shared values, from the Schur complement at the optimum: unit i
   carries the information ``M_i = H_aa,i - H_ab,i H_bb,i^-1 H_ba,i`` about a (its own
   values profiled out) and the efficient score ``q_i = g_a,i - H_ab,i H_bb,i^-1 g_b,i``.
   The model-based covariance is the robust loss's sandwich, as a single fit's (Huber
   1967): ``s^2 (sum_i M_i)^-1 (sum_i B_i) (sum_i M_i)^-1`` with ``B_i`` as ``M_i`` but with
   the squared weights and ``s^2`` the mean square of the inliers' normalised residuals
   (unweighted: weights below 1 would shrink it); with the weighted mean square and
   ``sigma^2 (sum M_i)^-1`` it came out 13% small at Gaussian noise under the Cauchy loss.
   The covariance that accounts for scatter between clips is the sandwich clustered by
   clip (Liang and Zeger 1986),

       V = (sum_i M_i)^-1 [C / (C - 1) sum_i q_i q_i^T] (sum_i M_i)^-1 / kappa^2,

   with the small-sample factor C / (C - 1) (CR1; C the number of units of the ball). Its
   bread is the Hessian of the loss, whose weights are ``rho''(u)``, not the IRLS weights of
   ``M_i``; ``kappa`` is the ratio of the two (leverage-weighted; 1 for l2, about 0.8 at
   Gaussian noise under the Cauchy loss, where the IRLS bread made V 20% small). A
   clip is the unit of independence: its residuals share one release, one pixel scale and
   whatever the model misses in that clip, so they are not independent samples, and clips
   that disagree more than their noise allows widen V. A third figure is the scatter of
   the clips' own estimates (step 4) about the shared value, as the standard error of a
   mean, ``sqrt(sum (a_i - a)^2 / (C (C - 1)))``. The reported standard error is the
   largest of the three: with few clips the clustered estimate is itself noisy and may
   fall below what the noise alone allows, and the robust loss, which down-weights the
   residuals of a clip that disagrees, also shrinks that clip's share of V (real clips that
   disagree by tens of their own standard errors gave a clustered error half the scatter). (A random-effects model would also estimate the
   between-clip variance of e; it needs one estimate per clip, which the clips' trade-off
   of e against drag often does not give, and it answers a different question: the spread
   of e across balls, not the e of this ball.)
4. **Which clips disagree**: each unit's own estimate of a shared parameter, with the
   other shared values held at theirs (a fit of that parameter and the unit's own values
   from the joint optimum; with one shared parameter, the one-by-one fit), and its
   distance from the shared value in its own standard errors, ``z``, name the clips that
   disagree (``|z| > 3``); ``Q = sum z^2`` (Cochran's heterogeneity statistic, C - 1
   degrees of freedom) says whether the clips scatter more than their noise allows.

Clips of image tracks (shots filmed by calibrated cameras, :func:`fit_image_clips`) go
the same way in pixels; their step 1 is :func:`estim.fit_image` per clip, and they keep
the scene's priors (one camera needs them) or the caller's, a shared value's once per
ball, which the standard errors count as the fit does.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._config import require_x64
from ..model._scene import Scene
from ..tracks._camera import CameraArrays
from ..tracks._image import ImageTracks
from . import _registry as registry
from ._fit import (
    LISTED_EVENTS,
    PARAMETERS,
    SETTLED,
    FitResult,
    ImageRows,
    _at_floor,
    _fit_all,
    _inliers,
    _linearise,
    _objective,
    _plan_at,
    _report,
    _rolled,
    _run,
    explain_misfit,
    fit_program,
)
from ._image import RESTARTS as IMAGE_RESTARTS
from ._image import _depth_report, _fit_image_ends, _without, default_image_free
from ._loss import robust_curvature, robust_weight
from ._sharding import gather, mesh_of, padded_size, per_unit, place

__all__ = ["Clip", "PooledResult", "SharedFit", "fit_clips", "fit_image_clips"]

DISAGREE_Z = 3.0  # a clip whose own estimate lies further than this (in its stderr) disagrees
OWN_STEPS = 15  # iterations of a clip's own estimate, from the joint optimum
# The joint fit's iterations, at most: it stops where its loss settles, so more cost only
# the fits that need them. The 15 real table drops (`../shared/realdata`, drag and e
# shared) still fell at 40 (30287, every clip "not converged"); at 160 they reach 30223.
JOINT_STEPS = 160
# For image clips: one camera leaves a clip's spin and mu loosely fixed, and the joint
# steps crawl along them: three shots from the side settled after 50 iterations (16.70 ->
# 16.49), and at 40 the report had called them not converged (the loss still falling by
# 4e-5 an iteration).
IMAGE_JOINT_STEPS = 80


@dataclass(frozen=True)
class Clip:
    """One tracked clip of one ball: a label (unique), the scene's ball, times (s) and
    positions (m, NaN for a lost coordinate), values held fixed for this clip (its release
    time, say), where it came from, what else describes it (a pixel clip's scale), the
    group of clips it shares its parameters with (default: every clip of its ball; several
    groups are independent fits run as one program), and the point its positions scale
    about when ``pixel_scale`` is fitted (a pixel clip's surface)."""

    label: str
    ball: str
    t: np.ndarray
    position: np.ndarray
    fixed: dict = field(default_factory=dict)
    source: str = ""
    extra: dict = field(default_factory=dict)
    group: str | None = None
    anchor: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class SharedFit:
    """The shared values of one ball across its clips.

    Attributes:
        group: the clips' group (by default the name of their ball).
        names: the shared parameters.
        values: their values.
        stderr: standard errors (module docstring, step 3: the largest of the clustered,
            the model-based and the scatter one).
        stderr_clustered: the sandwich clustered by clip (CR1).
        stderr_model: the model-based one.
        stderr_scatter: the scatter of the clips' own estimates about the shared value, as
            the standard error of their mean (NaN without own estimates).
        clips: the labels of the ball's units.
        per_clip: ``name -> label -> (value, stderr, z)``, each clip's own estimate with the
            other shared values held (module docstring, step 4).
        heterogeneity: ``name -> (Q, degrees of freedom)``.
        disagree: ``(label, name, value, z)`` of every clip whose own estimate lies more
            than ``DISAGREE_Z`` standard errors from the shared value.
    """

    group: str
    names: tuple[str, ...]
    values: dict[str, float]
    stderr: dict[str, float]
    stderr_clustered: dict[str, float]
    stderr_model: dict[str, float]
    stderr_scatter: dict[str, float]
    clips: list[str]
    per_clip: dict[str, dict[str, tuple[float, float, float]]]
    heterogeneity: dict[str, tuple[float, int]]
    disagree: list[tuple[str, str, float, float]]

    def to_json(self) -> dict:
        def num(x):
            return None if not math.isfinite(x) else float(x)

        out = {n: self.values[n] for n in self.names}
        out.update(
            group=self.group,
            stderr={n: num(v) for n, v in self.stderr.items()},
            stderr_clustered={n: num(v) for n, v in self.stderr_clustered.items()},
            stderr_model={n: num(v) for n, v in self.stderr_model.items()},
            stderr_scatter={n: num(v) for n, v in self.stderr_scatter.items()},
            method="the largest of the sandwich clustered by clip (CR1), the model-based "
                   "Gauss-Newton error and the scatter of the clips' own estimates",
            n_clips=len(self.clips),
            per_clip={n: {c: {"value": num(v), "stderr": num(s), "z": num(z)} for c, (v, s, z) in d.items()}
                      for n, d in self.per_clip.items()},
            heterogeneity={n: {"Q": num(q), "dof": k} for n, (q, k) in self.heterogeneity.items()},
            disagree=[{"clip": c, "parameter": n, "value": v, "z": z} for c, n, v, z in self.disagree],
        )
        return out


@dataclass
class PooledResult:
    """A fit of several clips with shared parameters: the shared values per ball, every
    unit's fit (its ``values`` hold the shared values) and the one-by-one fits it started
    from."""

    shared: dict[str, SharedFit]
    clips: FitResult
    individual: FitResult
    units: list[Clip]
    left_out: dict[str, str] = field(default_factory=dict)  # clip label -> why it could not be fitted

    @property
    def converged(self) -> bool:
        return self.clips.converged

    def to_json(self) -> dict:
        """``shared`` (flat for one ball, else per ball), ``clips`` (per unit what a single
        fit gives, with its source and extra), ``individual`` (the one-by-one fits),
        ``left_out`` (clips given but not fitted: label -> why)."""
        shared = {b: s.to_json() for b, s in self.shared.items()}
        clips = {}
        for u in self.units:
            entry = self.clips.balls[u.label].to_json()
            entry.update(ball=u.ball, source=u.source, **u.extra)
            clips[u.label] = entry
        return {
            "shared": next(iter(shared.values())) if len(shared) == 1 else shared,
            "clips": clips,
            "individual": {k: v.to_json() for k, v in self.individual.balls.items()},
            "left_out": dict(self.left_out),
        }

    def format_table(self) -> str:
        """The shared values per group, then one row per clip: its own estimate of each
        shared parameter (z from the shared value), rms, noise, status."""
        rows = []
        for sf in self.shared.values():
            cells = "   ".join(f"{n} = {sf.values[n]:.4f} +- {sf.stderr[n]:.4f}" for n in sf.names)
            rows.append(f"{sf.group}: shared over {len(sf.clips)} clips: {cells}")
            for n in sf.names:
                q, k = sf.heterogeneity[n]
                wide = k and q > k + 3 * math.sqrt(2 * k)
                rows.append(f"  {n}: Q = {q:.1f} on {k} dof (the clips scatter "
                            f"{'more than' if wide else 'as'} their noise allows)")
            # (Residuals in metres, shown in mm; an image fit's in pixels.)
            unit, scale = ("px", 1.0) if self.clips.balls[sf.clips[0]].unit == "px" else ("mm", 1e3)
            head = f"  {'clip':<22}" + "".join(f" {n + ' (own)':>26}" for n in sf.names) + \
                f" {f'rms ({unit})':>9} {'noise':>7}  status"
            rows += [head, "  " + "-" * (len(head) - 2)]
            for label in sf.clips:
                bf = self.clips.balls[label]
                own = "".join(
                    f" {_pm(*sf.per_clip[n][label][:2]) + f' z={sf.per_clip[n][label][2]:+.1f}':>26}"
                    for n in sf.names)
                status = ("converged" if bf.converged else "NOT converged") + (
                    "" if bf.at_noise_floor else ", above noise floor")
                rows.append(f"  {label:<22}{own} {bf.rms_m * scale:9.2f} {bf.noise_m * scale:7.2f}  {status}")
            for c, n, v, z in sf.disagree:
                rows.append(f"  clip {c} disagrees on {n}: {v:.4f}, {z:+.1f} stderr from the shared value")
            for label in sf.clips:
                bf = self.clips.balls[label]
                rows.extend(f"  {label}: {m['advice_note']}" for m in bf.missing_physics if m.get("advice_note"))
        rows.extend(f"left out: {label}: {why}" for label, why in self.left_out.items())
        return "\n".join(rows)


def _pm(v, s) -> str:
    return f"{v:.4f} +- {s:.4f}" if math.isfinite(s) else f"{v:.4f} (n/a)"


# --------------------------------------------------------------------------- the joint fit


class _Arrow(eqx.Module):
    """The state of the joint Levenberg-Marquardt: per unit its theta (shared entries equal
    within a ball), per ball its loss, damping and best point's blocks."""

    theta: jax.Array  # (U, P) the point to evaluate next
    best_theta: jax.Array  # (U, P)
    best_value: jax.Array  # (G,)
    damping: jax.Array  # (G,)
    hessian: jax.Array  # (U, P, P) J^T W J at the best point (normalised residuals)
    gradient: jax.Array  # (U, P)


def _arrow_step(shared_idx, local_idx, group, real, state: _Arrow, J, u, w, value):
    """One joint Levenberg-Marquardt step (module docstring, step 2), from the residuals
    ``u`` (U, m), their Jacobian ``J`` (U, m, P) and robust weights ``w`` at ``state.theta``,
    and each unit's loss ``value`` (U,). ``group`` (U, G) is one-hot (zero for padding);
    ``real`` (U,) marks the units that are not padding."""
    value_g = jnp.einsum("ug,u->g", group, jnp.where(real, value, 0.0))
    better_g = jnp.isfinite(value_g) & (value_g < state.best_value)
    lam_g = jnp.where(better_g, state.damping / 3.0, state.damping * 4.0)
    better = (group @ better_g.astype(value.dtype)) > 0.5
    lam = group @ lam_g
    Jw = J * jnp.sqrt(w)[..., None]
    H = jnp.where(better[:, None, None], jnp.einsum("umi,umj->uij", Jw, Jw), state.hessian)
    g = jnp.where(better[:, None], jnp.einsum("umi,um->ui", Jw, u * jnp.sqrt(w)), state.gradient)
    base = jnp.where(better[:, None], state.theta, state.best_theta)

    s, loc = jnp.asarray(shared_idx), jnp.asarray(local_idx)
    Haa, Hab, Hbb = H[:, s][:, :, s], H[:, s][:, :, loc], H[:, loc][:, :, loc]
    ga, gb = g[:, s], g[:, loc]

    def damp(M, lam):
        return M + (lam[..., None] * (jnp.diagonal(M, axis1=-2, axis2=-1) + 1e-12))[..., None] * jnp.eye(M.shape[-1])

    Hbb = jnp.where(real[:, None, None], damp(Hbb, lam), jnp.eye(len(local_idx)))
    X = jnp.linalg.solve(Hbb, jnp.concatenate([jnp.swapaxes(Hab, 1, 2), gb[..., None]], axis=2))
    X = jnp.where(real[:, None, None], X, 0.0)
    S = damp(jnp.einsum("ug,uij->gij", group, Haa), lam_g) - jnp.einsum("ug,uij,ujk->gik", group, Hab, X[..., :-1])
    b = -jnp.einsum("ug,ui->gi", group, ga) + jnp.einsum("ug,uij,uj->gi", group, Hab, X[..., -1])
    da_g = jnp.linalg.solve(S, b[..., None])[..., 0]
    da = group @ da_g
    db = -X[..., -1] - jnp.einsum("uij,uj->ui", X[..., :-1], da)
    step = jnp.zeros_like(base).at[:, s].set(da).at[:, loc].set(db)
    step = jnp.where(jnp.all(jnp.isfinite(step), axis=1, keepdims=True), step, 0.0)
    return _Arrow(
        theta=base + step,
        best_theta=base,
        best_value=jnp.where(better_g, value_g, state.best_value),
        damping=lam_g,
        hessian=H,
        gradient=g,
    )


@fit_program
def _run_joint(scene, free, shared_idx, local_idx, loss, steps, max_segments, state: _Arrow, best,
               batch, group, real, mesh=None, rolls=True):
    """``steps`` joint iterations from ``state``; returns the state, the loss per ball per
    step (G, steps), the residuals, Jacobian, validity, positions and impacts at the best
    point per unit (as ``estim.fitting._fit._run``), ``best`` where none was better, and
    whether a plan had a roll left out (``estim.fitting._fit.fit_program``)."""

    def one(theta, pr):
        pl, used = _plan_at(scene, registry.to_physical(theta, free, pr.fixed), pr, max_segments)
        J, r, aux, u, value = _linearise(scene, free, loss, theta, pr, pl, used, rolls)
        m = pr.obs.size  # the data's rows (kept as a fit keeps them); the priors' follow
        return J / pr.scale, u, robust_weight(u, loss), value, (r[:m], J[:m], aux), _rolled(scene, pl, rolls)

    def step(carry, _):
        state, best, rolled = carry
        Ju, u, w, value, diag, rolls_left_out = per_unit(one, mesh, state.theta, batch)
        new = _arrow_step(shared_idx, local_idx, group, real, state, Ju, u, w, value)
        improved = (group @ (new.best_value < state.best_value).astype(value.dtype)) > 0.5
        best = jax.tree.map(
            lambda x, y: jnp.where(improved.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), diag, best)
        return (new, best, rolled | jnp.any(rolls_left_out)), new.best_value

    (state, best, rolled), history = jax.lax.scan(step, (state, best, jnp.bool_(False)), None, length=steps)
    return state, history.T, best, rolled


def fit_clips(
    scene: Scene,
    clips: Sequence[Clip],
    *,
    shared: Sequence[str] = ("e",),
    free: tuple[str, ...] | None = None,
    loss: str = "cauchy",
    steps: int = 30,
    joint_steps: int = JOINT_STEPS,
    restarts: int = 5,
    max_segments: int = 48,
    devices=None,
    per_clip: bool = True,
    progress: Callable[[str], None] | None = None,
) -> PooledResult:
    """Fit several clips together, with parameters shared across the clips of each ball.

    Args:
        scene: the scene (every clip was filmed in it).
        clips: the clips (:class:`Clip`), each one ball's track; labels must be unique.
        shared: the parameters shared by all clips of a ball (registry names, fitted), e.g.
            ``("e", "drag_coefficient")``; the rest of ``free`` is fitted per clip.
        free: every fitted parameter (shared ones are added if missing); by default what
            :func:`estim.fit` fits by default in the scene.
        loss: the robust loss, as :func:`estim.fit`.
        steps: iterations of the one-by-one fits, as :func:`estim.fit`.
        restarts: as :func:`estim.fit` for the one-by-one fits; clips that reached their
            noise floor alone but not together restart their own values at most
            ``min(restarts, 2)`` times (from their one-by-one fit, then from the data's
            start).
        max_segments: as :func:`estim.fit`.
        joint_steps: iterations of the joint fit, at most (``JOINT_STEPS``; it stops
            where its loss settles).
        devices: the devices to split the clips over (default: every device JAX sees; one
            device runs unsharded).
        per_clip: each clip's own estimate of each shared parameter (module docstring,
            step 4: one more fit per shared parameter when there are several); ``False``
            skips it (``SharedFit.per_clip`` then holds NaN and ``disagree`` nothing).
        progress: called with a short message at each stage.

    Returns:
        A :class:`PooledResult`.

    Raises:
        ValueError: fewer than two clips, repeated labels, an unknown or unfitted shared
            name, a shared name the scene cannot use (drag without air), or a clip that
            :func:`estim.fit` rejects (named by its label).
    """
    require_x64()
    say = progress or (lambda msg: None)
    clips = list(clips)
    shared = _shared_names([c.label for c in clips], shared)
    lateral = any(np.isfinite(np.asarray(c.position)[:, 1]).any() for c in clips)
    free = registry.default_free(scene, lateral) if free is None else registry.expand(free)
    free = tuple(free) + tuple(n for n in shared if n not in free)
    fixed_shared = [n for c in clips for n in shared if n in c.fixed]
    if fixed_shared:
        raise ValueError(f"shared parameter(s) {sorted(set(fixed_shared))} are held fixed in a clip; "
                         "a shared parameter is fitted")

    devices = list(jax.devices() if devices is None else devices)
    say(f"one by one: {len(clips)} clips")
    data = {c.label: (c.t, c.position) for c in clips}
    fixed = {c.label: dict(c.fixed) for c in clips if c.fixed}
    individual, units = _fit_all(scene, data, free=free, fixed=fixed, loss=loss, steps=steps,
                                 restarts=restarts, max_segments=max_segments, progress=say,
                                 balls={c.label: c.ball for c in clips}, anchors={c.label: c.anchor for c in clips},
                                 devices=devices, prior={name: None for name, *_ in scene.priors})
    return _together(scene, clips, units, individual, shared, loss=loss, joint_steps=joint_steps,
                     restarts=restarts, max_segments=max_segments, devices=devices, per_clip=per_clip, say=say)


def fit_image_clips(
    scene: Scene,
    clips: Mapping[str, ImageTracks],
    *,
    shared: Sequence[str] = ("e",),
    free: tuple[str, ...] | None = None,
    loss: str = "cauchy",
    steps: int = 30,
    joint_steps: int = IMAGE_JOINT_STEPS,
    restarts: int = IMAGE_RESTARTS,
    max_segments: int = 48,
    prior: Mapping[str, tuple[float, float] | None] | None = None,
    devices=None,
    per_clip: bool = True,
    progress: Callable[[str], None] | None = None,
) -> PooledResult:
    """Fit several clips of image tracks together (shots of one ball filmed by calibrated
    cameras), with parameters shared across the clips of each ball.

    Each ball of each clip is a unit (labelled by its clip, and ``clip/ball`` where a clip
    has several balls). Step 1 is :func:`estim.fit_image` on each unit alone (its starts
    read off the pixels through the physics, its rows past a hit left out), then the
    joint fit, the standard errors and each clip's own estimates as :func:`fit_clips`
    (module docstring, steps 2 to 4), in pixels. The scene's priors stay, unlike in
    :func:`fit_clips`: one camera needs them (a spin no ball has, read to bend a path
    along the lens; an e that trades with the depth of the whole path). Each clip's own
    values keep theirs, and a prior on a shared value counts once per ball (in its first
    unit: counted once per clip, it would weigh as many times too much). The standard
    errors count the priors as the fit does (a clip's spin left to its prior is not
    information its pixels lack), and the one-by-one fits, which each clip's own
    estimates come from, are those of :func:`estim.fit_image`, priors and all.

    Args:
        scene: the scene, in whose world frame the cameras are calibrated.
        clips: ``label -> ImageTracks`` (:func:`estim.read_image_tracks_csv`); every clip
            seen by the same number of cameras.
        shared, loss, steps, max_segments, devices, per_clip, progress: as
            :func:`fit_clips`.
        free: every fitted parameter; default what :func:`estim.fit_image` fits (shared
            ones are added if missing).
        joint_steps: as :func:`fit_clips`; more by default (``IMAGE_JOINT_STEPS``).
        restarts: as :func:`estim.fit_image` for the one-by-one fits.
        prior: as :func:`estim.fit_image`: priors of one's own, ``name -> (mean, sd)``, or
            ``name -> None`` to drop the scene's; they apply as the scene's do (each
            clip's own values, and a shared value's once per ball).

    Returns:
        A :class:`PooledResult` whose units' fits are in pixels (``BallFit.unit == "px"``)
        with their depth reports, and whose ``individual`` fits are the one-by-one fits.

    Raises:
        ValueError: fewer than two units, an unknown or unfitted shared name, clips seen
            by different numbers of cameras, or fewer than two units left that
            :func:`estim.fit_image` can fit (one it refuses, too few rows say, is left out
            and named with why in ``PooledResult.left_out``).
    """
    require_x64()
    say = progress or (lambda msg: None)
    units_of = [(label if len(tracks.balls) == 1 else f"{label}/{b}", b, tracks)
                for label, tracks in clips.items() for b in tracks.balls]
    shared = _shared_names([u[0] for u in units_of], shared)
    n_cameras = sorted({len(tracks.cameras) for tracks in clips.values()})
    if len(n_cameras) > 1:
        raise ValueError(f"the clips are seen by {n_cameras} cameras: fitted together, every clip is seen by "
                         "the same number of cameras (their clocks' offsets are each clip's own)")
    free = registry.expand(default_image_free(scene, n_cameras[0]) if free is None else free)
    free = tuple(free) + tuple(n for n in shared if n not in free)
    individual, data, images, starts, units, left_out = {}, {}, {}, {}, [], {}
    for label, b, tracks in units_of:
        say(f"one by one: {label}")
        try:
            result, ends = _fit_image_ends(scene, _without(tracks, b, []), free=free, fixed=None, loss=loss,
                                           steps=steps, restarts=restarts, max_segments=max_segments, prior=prior,
                                           effects=False, progress=say)
        except ValueError as err:
            # A clip that cannot be fitted alone (too few rows, ...) is left out, named, and
            # reported (``PooledResult.left_out``), not a reason to stop the others' fit.
            left_out[label] = str(err)
            say(f"left out {label}: {err}")
            continue
        bf = individual[label] = result.balls[b]
        alone = _without(tracks, b, ends[b])
        ok = alone.valid(b)
        t, at = np.unique(alone.t[b][ok], return_index=True)
        data[label] = (t, np.asarray(bf.model_position)[ok][at])  # the 3-D path the joint fit starts from
        images[label] = ImageRows(t=alone.t[b], uv=alone.uv[b], view=alone.view[b],
                                  cameras=CameraArrays.of(alone.cameras), noise=bf.noise_m, initial=bf.initial)
        starts[label] = {n: bf.values[n] for n in (*free, "t0")}
        units.append(Clip(label=label, ball=b, t=t, position=data[label][1], source=tracks.source))
    if len(units) < 2:
        raise ValueError(f"a fit of shared parameters needs at least two clips, got {len(units)} that could be "
                         "fitted" + "".join(f"; left out: {k}: {v}" for k, v in left_out.items()))
    devices = list(jax.devices() if devices is None else devices)
    # What the one-by-one fits ended on, as one batch of the same length (their values as
    # starts: restarts would only leave them).
    _, worked = _fit_all(scene, data, free=free, fixed=starts, loss=loss, steps=steps, restarts=0,
                         max_segments=max_segments, progress=say, balls={u.label: u.ball for u in units},
                         devices=devices, images=images, prior=prior)
    # The priors on the shared values (the scene's, or the caller's) count once per ball,
    # in its first unit.
    seen, problems = set(), []
    columns = [registry.NAMES.index(n) for n in shared]
    for u, pr in zip(units, worked.problems, strict=True):
        if pr.prior is not None and (u.group or u.ball) in seen:
            weights = np.array(pr.prior)
            weights[1, columns] = 0.0
            pr = eqx.tree_at(lambda p: p.prior, pr, weights)
        seen.add(u.group or u.ball)
        problems.append(pr)
    worked = dataclasses.replace(worked, problems=problems)
    out = _together(scene, units, worked, FitResult(individual), shared, loss=loss, joint_steps=joint_steps,
                    restarts=restarts, max_segments=max_segments, devices=devices, per_clip=per_clip, say=say)
    camera_of = {label: tracks.cameras[0] for label, _, tracks in units_of}
    for label, bf in out.clips.balls.items():
        bf.depth = _depth_report(bf, camera_of[label])
        if bf.depth["note"]:
            bf.notes.append(bf.depth["note"])
    out.left_out = left_out
    return out


def _shared_names(labels: list[str], shared: Sequence[str]) -> tuple[str, ...]:
    """The shared parameters' components, checked, for a fit of the units ``labels``."""
    if len(labels) < 2:
        raise ValueError(f"a fit of shared parameters needs at least two clips, got {len(labels)}")
    if len(set(labels)) != len(labels):
        raise ValueError(f"clip labels must be unique, got {labels}")
    shared = registry.expand(shared)
    unknown = [n for n in shared if n not in PARAMETERS]
    if unknown:
        raise ValueError(f"unknown shared parameter(s) {unknown}; the parameters are {PARAMETERS}")
    if "t0" in shared:
        raise ValueError("t0 is a clip's own time offset and cannot be shared")
    return shared


def _together(scene: Scene, clips: list[Clip], units, individual: FitResult, shared: tuple[str, ...], *, loss: str,
              joint_steps: int, restarts: int, max_segments: int, devices, per_clip: bool, say) -> PooledResult:
    """Steps 2 to 4 of the module docstring, from the one-by-one fits ``individual`` and
    what they worked on (``units``, one per clip, in the order of ``clips``)."""
    labels = [c.label for c in clips]
    free = units.free
    shared_idx = tuple(free.index(n) for n in shared)
    local_idx = tuple(k for k in range(len(free)) if k not in shared_idx)
    if not local_idx:
        raise ValueError("every fitted parameter is shared: a clip needs its own release state")
    keys = [c.group or c.ball for c in clips]
    balls = sorted(set(keys), key=keys.index)  # the groups, in order of appearance
    group_of = np.array([balls.index(k) for k in keys])

    # The joint start: per ball, the median over its clips of each shared value (in the
    # unconstrained coordinate: robust to a clip whose one-by-one fit went to a bound).
    theta = units.theta.copy()
    for g in range(len(balls)):
        members = group_of == g
        theta[np.ix_(members, shared_idx)] = np.median(theta[np.ix_(members, shared_idx)], axis=0)

    mesh = mesh_of(devices)
    n_units = len(clips)
    padded = padded_size(n_units, mesh)
    problems = list(units.problems) + [units.problems[0]] * (padded - n_units)
    batch = jax.tree.map(lambda *xs: np.stack(xs), *problems)
    batch = eqx.tree_at(lambda p: p.mask, batch, batch.mask & (np.arange(padded) < n_units)[:, None, None])
    group = np.zeros((padded, len(balls)))
    group[np.arange(n_units), group_of] = 1.0
    real = np.arange(padded) < n_units
    if mesh is not None:
        say(f"the {n_units} clips split over {mesh.size} devices")
    placed = jax.tree.map(lambda x: place(x, mesh), (batch, group, real))

    def joint(theta0):
        theta0 = np.concatenate([theta0, np.repeat(theta0[:1], padded - n_units, axis=0)])
        state = _Arrow(theta=place(theta0, mesh), best_theta=place(theta0, mesh),
                       best_value=jnp.full(len(balls), jnp.inf, jnp.float64),
                       damping=jnp.full(len(balls), 1e-3, jnp.float64),
                       hessian=place(np.zeros((padded, len(free), len(free))), mesh),
                       gradient=place(np.zeros((padded, len(free))), mesh))
        m = batch.obs[0].size
        best = jax.tree.map(lambda x: place(x, mesh), (
            np.zeros((padded, m)), np.zeros((padded, m, len(free))),
            (np.zeros((padded, m), bool), np.zeros(batch.obs.shape),
             np.full((padded, LISTED_EVENTS), -1, np.int32))))
        histories = []
        chunk = 5
        for done in range(0, joint_steps, chunk):
            state, history, best = _run_joint(scene, free, shared_idx, local_idx, loss, min(chunk, joint_steps - done),
                                              max_segments, state, best, *placed, mesh)
            histories.append(np.asarray(gather(history)))
            say(f"joint fit: step {min(done + chunk, joint_steps)}/{joint_steps}, loss "
                + ", ".join(f"{b} {v:.2f}" for b, v in zip(balls, histories[-1][:, -1], strict=True)))
            run = np.concatenate(histories, axis=1)
            settled = run.shape[1] >= SETTLED and np.all(
                run[:, -SETTLED] - run[:, -1] <= 1e-6 * np.maximum(np.abs(run[:, -1]), 1.0))
            # SETTLED iterations within 1e-6 (the report's test of convergence), after a
            # step that lowered the loss: converged. A loss that has not moved since the
            # start is a run of refused steps while the damping grows, not an optimum:
            # from the median start, the clips' weakly fixed values (a spin, a mu that one
            # camera leaves to its prior) took steps that raised the loss until the
            # damping reached about 300 (three shots from the side: the first ten steps
            # refused, then the loss fell from 16.70 to 16.49).
            if settled and np.all(run[:, -1] < run[:, 0]):
                break
        theta_best, diag = gather((state.best_theta, best))
        diag = jax.tree.map(lambda x: np.array(x[:n_units]), diag)  # writable copies
        return np.array(theta_best[:n_units]), np.concatenate(histories, axis=1), diag

    say("together: shared " + ", ".join(shared) + " across the clips of " + ", ".join(balls))
    theta_best, history, diag = joint(theta)
    floors = [_at_floor(diag, i, units.noises[i]) for i in range(n_units)]
    total = _group_objective(diag, loss, units.problems, group_of, len(balls))
    # Only a clip that reached its noise floor alone but not together restarts: one that
    # missed it alone too lacks something no start gives it.
    for attempt, source in enumerate(("one by one", "data")[: min(restarts, 2)]):
        retry = [not floors[i] and units.floors[i] for i in range(n_units)]
        if not any(retry):
            break
        missed = [labels[i] for i in range(n_units) if retry[i]]
        say(f"restart {attempt + 1}: {missed} above the noise floor, their own values from the {source} start")
        trial = theta_best.copy()
        for i in range(n_units):
            if retry[i]:
                start = units.theta[i] if source == "one by one" else units.starts[i]
                trial[i, list(local_idx)] = start[list(local_idx)]
        tried = joint(trial)
        tried_total = _group_objective(tried[2], loss, units.problems, group_of, len(balls))
        for g in range(len(balls)):
            if tried_total[g] < total[g]:
                members = np.flatnonzero(group_of == g)
                theta_best[members] = tried[0][members]
                for x, y in zip(jax.tree.leaves(diag), jax.tree.leaves(tried[2]), strict=True):
                    x[members] = y[members]
                total[g] = tried_total[g]
        floors = [_at_floor(diag, i, units.noises[i]) for i in range(n_units)]

    reports = {}
    for i, label in enumerate(labels):
        hist = history[group_of[i]]
        reports[label] = _report(scene, label, free, loss, theta_best[i], diag, i, units.problems[i], units.inits[i],
                                 hist, floors[i], units.noises[i])
        explain_misfit(scene, reports[label], units.problems[i], free)
    own = (_own_estimates(scene, units, individual, shared, theta_best, loss, max_segments, say) if per_clip
           else {n: [(math.nan, math.nan)] * n_units for n in shared})
    shared_fits = {b: _shared_fit(b, [i for i in range(n_units) if group_of[i] == g], labels, free, shared,
                                  theta_best, diag, units.problems, loss, own, units.noises)
                   for g, b in enumerate(balls)}
    for sf in shared_fits.values():
        for c, n, v, z in sf.disagree:
            reports[c].notes.append(f"its own {n} = {v:.4f} lies {z:+.1f} stderr from the shared value")
    result = FitResult(reports, source=", ".join(c.source for c in clips if c.source))
    return PooledResult(shared=shared_fits, clips=result, individual=individual, units=clips)


def _own_estimates(scene, units, individual, shared, theta, loss, max_segments, say):
    """Each unit's own estimate of each shared parameter, the other shared values held at
    theirs: ``name -> [(value, stderr)]`` per unit (module docstring, step 4). With one
    shared parameter that is the one-by-one fit; otherwise a fit of the unit's own values
    and that parameter, from the joint optimum (a fit, not a linearisation: a clip that
    disagrees has residuals the robust loss down-weights at the shared value, which would
    hide how far it lies)."""
    free = units.free
    out = {}
    for n in shared:
        if len(shared) == 1:
            fits = [individual.balls[label] for label in units.names]
            out[n] = [(bf.values[n], bf.stderr.get(n, math.nan)) for bf in fits]
            continue
        say(f"each clip's own {n}, the other shared values held")
        own_free = tuple(m for m in free if m not in shared or m == n)
        phis = [registry.to_physical(theta[i], free, pr.fixed) for i, pr in enumerate(units.problems)]
        problems = [eqx.tree_at(lambda p: p.fixed, pr, phi) for pr, phi in zip(units.problems, phis, strict=True)]
        batch = jax.tree.map(lambda *xs: np.stack(xs), *problems)
        start = np.stack([registry.to_theta(phi, own_free) for phi in phis])
        best, history, diag = jax.device_get(_run(scene, own_free, loss, OWN_STEPS, max_segments, start, batch))
        out[n] = []
        for i, label in enumerate(units.names):
            bf = _report(scene, label, own_free, loss, best[i], diag, i, problems[i], units.inits[i], np.asarray(history[i]),
                         True, units.noises[i])
            out[n].append((bf.values[n], bf.stderr.get(n, math.nan)))
    return out


def _group_objective(diag, loss, problems, group_of, n_groups) -> np.ndarray:
    out = np.zeros(n_groups)
    for i, pr in enumerate(problems):
        out[group_of[i]] += _objective(diag, i, loss, pr)
    return out


def _shared_fit(group, members, labels, free, shared, theta, diag, problems, loss, own_estimates,
                noises) -> SharedFit:
    """Standard errors of the shared values and each clip's own estimate (module
    docstring, steps 3 and 4), in physical coordinates."""
    s_idx = [free.index(n) for n in shared]
    l_idx = [k for k in range(len(free)) if k not in s_idx]
    M, B, q = [], [], []
    squares, n_inliers = 0.0, 0
    bread_w = bread_psi = 0.0
    for i in members:
        r, J, valid = (np.asarray(x[i]) for x in (diag[0], diag[1], diag[2][0]))
        phi = registry.to_physical(theta[i], free, problems[i].fixed)
        # Physical coordinates; a parameter whose sigmoid saturated (at the edge of its
        # range, as ``_report`` says) has no column.
        dphi = registry.slopes(phi, free)
        at_bound = dphi < 1e-10
        J = np.where(at_bound[None, :], 0.0, J / np.where(at_bound, 1.0, dphi)[None, :]) / float(problems[i].scale)
        u = np.where(valid, r / float(problems[i].scale), 0.0)
        w = np.asarray(robust_weight(u, loss)) * valid
        if problems[i].prior is not None:
            # The priors' rows as the fit counted them ((phi - mean) / sd, weight 1): one
            # camera's clip leaves its own spin to its prior, which must not be read as
            # information the data lack.
            mean, inv_sd = (np.asarray(a)[[PARAMETERS.index(n) for n in free]] for a in problems[i].prior)
            rows = np.flatnonzero(inv_sd > 0)
            J = np.concatenate([J, np.eye(len(free))[rows] * inv_sd[rows, None] * ~at_bound[None, :]])
            u = np.concatenate([u, (phi[[PARAMETERS.index(n) for n in free]] - mean)[rows] * inv_sd[rows]])
            w = np.concatenate([w, np.ones(rows.size)])
            valid = np.concatenate([valid, np.zeros(rows.size, bool)])  # (not samples: no noise to read)
        H = J.T @ (w[:, None] * J)
        # K: the shared columns with the clip's own values profiled out, so that
        # K^T W K = H_aa - H_ab H_bb^-1 H_ba and K^T W u = g_a - H_ab H_bb^-1 g_b.
        K = J[:, s_idx] - J[:, l_idx] @ (np.linalg.pinv(H[np.ix_(l_idx, l_idx)]) @ H[np.ix_(l_idx, s_idx)])
        M.append(K.T @ (w[:, None] * K))
        B.append(K.T @ ((w * w)[:, None] * K))
        q.append(K.T @ (w * u))
        lever = np.sum(K * K, axis=1) * valid
        bread_w += float(np.sum(w * lever))
        bread_psi += float(np.sum(np.asarray(robust_curvature(u, loss)) * lever))
        _, _, keep = _inliers(diag, i, noises[i])
        squares += float(np.sum(u[: keep.size][keep] ** 2))
        n_inliers += int(keep.sum())
    M, B, q = np.array(M), np.array(B), np.array(q)
    C = len(members)
    # The noise variance from the inliers' residuals (unweighted: weights below 1 would
    # shrink it), with the degrees of freedom they carry, as a single fit's.
    sigma2 = squares / max(n_inliers - C * len(l_idx) - len(s_idx), 1)
    info = M.sum(axis=0)
    try:
        inv = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        inv = np.full_like(info, np.nan)
    model = sigma2 * inv @ B.sum(axis=0) @ inv
    # The clustered sandwich's bread is the loss's Hessian, whose weights are rho''(u), not
    # the IRLS weights w(u) of ``info``: at Gaussian noise under the Cauchy loss their means
    # are 0.70 and 0.88, and the IRLS bread gave standard errors 20% small. Scaled by the
    # ratio of the two breads (leverage-weighted; 1 for l2), floored so that a clip full of
    # outliers (rho'' < 0) cannot blow it up.
    ratio = min(max(bread_psi / bread_w, 0.25), 1.0) if bread_w > 0 else 1.0
    clustered = inv @ (C / max(C - 1, 1) * np.einsum("ci,cj->ij", q, q)) @ inv / ratio**2
    values = {n: float(registry.to_physical(theta[members[0]], free, problems[members[0]].fixed)[PARAMETERS.index(n)])
              for n in shared}
    se_c = {n: float(np.sqrt(max(clustered[k, k], 0.0))) for k, n in enumerate(shared)}
    se_m = {n: float(np.sqrt(max(model[k, k], 0.0))) for k, n in enumerate(shared)}
    per_clip, heterogeneity, disagree, se_s = {}, {}, [], {}
    for n in shared:
        per_clip[n] = {}
        zs, owns = [], []
        for i in members:
            own, own_se = own_estimates[n][i]
            z = (own - values[n]) / own_se if own_se > 0 else math.nan
            per_clip[n][labels[i]] = (own, own_se, z)
            if math.isfinite(z):
                zs.append(z)
                owns.append(own)
                if abs(z) > DISAGREE_Z:
                    disagree.append((labels[i], n, own, z))
        heterogeneity[n] = (float(np.sum(np.square(zs))), max(len(zs) - 1, 0))
        # The scatter of the clips' own estimates about the shared value, as the standard
        # error of a mean of them (nan with fewer than two).
        k = len(owns)
        se_s[n] = math.sqrt(float(np.sum((np.array(owns) - values[n]) ** 2)) / (k * (k - 1))) if k > 1 else math.nan
    se = {n: max(se_c[n], se_m[n], se_s[n] if math.isfinite(se_s[n]) else 0.0) for n in shared}
    return SharedFit(group=group, names=tuple(shared), values=values, stderr=se, stderr_clustered=se_c,
                     stderr_model=se_m, stderr_scatter=se_s, clips=[labels[i] for i in members],
                     per_clip=per_clip, heterogeneity=heterogeneity, disagree=disagree)

