"""Fits in pixels: balls seen by one or more calibrated cameras.

:func:`fit_image` fits image tracks (``estim.tracks._image``): the model's 3-D path, seen by
the camera of each row (``estim.tracks._camera``: OpenCV's projection), against the
pixels, with the robust loss of every fit (residuals in pixels, noise read from the pixels'
third differences). What it estimates is 3-D, in the scene's world frame: the release
state, the law's coefficients, the spin where it acts, and with several cameras the offset
of each camera's clock from the first's (``dt_camera2``, ...: a row at time t of camera k
is the model at ``t + dt_camerak``).

1. **Start.** One camera gives rays, not points; the path comes through the physics
   (``estim.tracks._reconstruct``): flights under gravity of known size, meeting at the
   bounces, the centre one radius above the surface at each bounce. With several cameras
   the same least squares takes every camera's rays: a triangulation through the physics.
   The bounces go on the scene's surfaces, bounded ones (a table that holds the bounce
   point) before planes (``estim.tracks._reconstruct.reconstructions``); the ``STARTS``
   best such paths are fitted side by side in one batch (always ``STARTS``, so that one
   compiled program serves every shot of a length), and the fit that explains the pixels
   best (the least robust loss) is kept. Where the bounces fit one surface only, the
   second start is the first moved ``FARTHER`` along the rays (depth is the direction one
   camera fixes worst); another start's fit nearly as good along a path far away is
   reported as a second solution (``BallFit.depth["alternative"]``, ``AMBIGUOUS``). The
   starting values come from the path's flights (:func:`start_values`: the release state,
   e and mu from the velocities at the first bounce, in air the spin from the first
   flight's curvature).
2. **Fit.** Every fit's machinery (``estim.fitting._fit``) with the residuals in pixels
   and the scene's priors (``Scene.priors``: a few frames from one camera fix e and the
   friction coefficient loosely, and a wrong e trades with the depth of the whole path).
   Every key runs every restart (``_fit_all(explore=True)``: e from a grid over its
   range), at its noise floor or not: a few frames of pixels read that floor poorly. Then
   every start runs once more through a graduated robust scale (``GRADUATED``: at 20 px,
   then at the pixels' noise), kept where it ends lower: at the noise of a clean track a
   start's misses of a few pixels had led to paths that explain part of the samples.
   Where a start's fit rebounds off a solid on which no start bounces (the net, or the
   floor where the starts bounce on the table), the starts run again with those solids
   set aside (``Scene.set_aside``), each polished in the whole scene from where it ended.
   Where the chosen fit misses some rows by more than ``WILD`` noise levels or ``APART``
   times its misses of the others (wild detections, which inflate the noise read from
   third differences) and the noise read without them (no lower than the fit's misses of
   the other rows) is more than ``REREAD`` times lower, every start runs again at it,
   read without those rows; and so on from the new fit (``REREADS`` times at most).
   Where the fit misses the track's first or last row by more than ``WILD`` noise levels
   and ``HIT_APART`` times the noise its other misses show (the ball hit there by what
   the scene does not hold), the fit runs again without that row, and so on from the new
   ends (``HITS``).
3. **Depth.** Depth (along a camera's axis) is the direction the pixels fix worst. From the
   fit's covariance, each ball's report gives the standard error of the release point
   along the first camera's axis and across it (``BallFit.depth``), and a note where the
   depth is not fixed: a release point whose standard error along the axis exceeds
   ``DEPTH_LIMIT`` or that the data cannot determine at all.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ..forward._balls import inside
from ..model._air import spin_for_lift, spinless_acceleration
from ..model._params import DRAG_COEFFICIENT
from ..model._scene import Scene
from ..tracks._camera import CameraArrays
from ..tracks._image import MIN_ROWS, ImageTracks
from ..tracks._reconstruct import EDGE, NARROW, reconstructions
from . import _registry as registry
from ._fit import FitResult, ImageRows, _fit_all, attach_effects
from ._initial import E_DEFAULT, FRICTION_DEFAULT, MU_DEFAULT, Initial
from ._loss import robust_loss

__all__ = ["DEPTH_LIMIT", "RESTARTS", "default_image_free", "fit_image"]

# A release point known to worse than this along the camera's axis (m) is "not fixed".
DEPTH_LIMIT = 0.05
# The largest spin a start takes from a flight's curvature (rad/s): beyond, noise.
SPIN_START = 400.0
# Restarts of every start (e from 0.3 and 0.9): on the views study of docs/pages/cameras.md,
# with the table-tennis scene's prior on e, five changed no shot and none lost one (a
# start that missed a bounce: 42 cm off). More iterations than the 30 of a run did harm
# there: at 40 two shots of 16 ran off along the rays to a path 40-90 cm away that fits
# 15 frames as well (the depth one camera leaves open).
RESTARTS = 2
# The robust scales (px) of the graduated run from the starts (``_fit._fit_all``), before
# the pixels' noise: 20 px, about what a start read off one camera's rays misses by.
# Without it a track cleaner than a pixel settled on paths that explain part of the
# samples (docs/pages/cameras.md, "Clean tracks"); steps at 4, 0.8, ... px between left
# that study's tables (48 clean fits) the same to their last digit, and each costs a run.
GRADUATED = (20.0,)
# Starts per ball: the start paths with the bounces on different surfaces
# (estim.tracks._reconstruct.reconstructions), fitted side by side; the best is kept.
STARTS = 2
# Where the bounces fit one surface only, the second start is the first moved this factor
# farther along the first camera's rays (its pixels stay): depth is what one camera fixes
# worst, and from behind, fits from the one start ran towards the camera until the ball
# met the net and bounced back off it (two shots of 32 in the views study of
# docs/pages/cameras.md, 72-79 cm off, their loss above the truth's); from 5% farther both
# reached the truth's basin (2 and 10 cm off). 5% nearer missed one of them. A start so
# moved whose release lies in a solid is not taken (the first is repeated).
FARTHER = 1.05
# Another start's fit whose robust loss exceeds the chosen one's by less than this, with a
# path more than DEPTH_LIMIT away on average, is reported as a second solution: the pixels
# tell the two apart by less than a likelihood ratio of e^2.
AMBIGUOUS = 2.0
# A fit whose values lie more than DOUBT standard deviations from one of its priors is
# doubted: one camera's pixels fix e and mu only loosely, so a fit pulled that far from what
# is known of the ball is rather the fit of a wrong path, a depth that gravity's size
# allowed (MuJoCo's shots seen from in front, the ball coming at the camera: the start read
# a short drop near the bounce for a long flight, and the fit ended at e = 0.2, 96 cm off,
# 13 sd from the prior; or the start was right and its fit ran to e = 0.02 while the other
# start's ran 3 m off, beyond the table, at a loss above the truth's). The first start is
# then moved along the first camera's rays by each pair of DEEPER factors in turn (the
# second only while the best fit is doubted); the best fit of all is kept (1.25 and 0.8
# reached those two shots' truths, 3 and 10 cm off).
DOUBT = 3.0
# ... as is a fit whose robust loss (``_loss``) averages more than this per pixel coordinate:
# a typical miss of 2.5 noise levels (a fit at the noise averages about 0.3), a path that
# explains the frames no better than one that met the net on its way (the other shot
# above, whose two starts' fits ended at 3.3 per coordinate and 3 m off).
MISFIT = 1.0
# ... as is a fit whose path lies farther than this from the start read off the pixels, on
# average (m): the start's bounce on the scene's surface holds its depth, and a fit that
# leaves it by metres has run along the rays (a drive seen from in front: from a start 1.6
# m off at its release, 5 cm at its bounce, both fits ran to a path under the table
# bouncing on the floor, 2.6 m off, at a loss above the truth's).
DRIFT = 1.0
DEEPER = ((1.25, 0.8), (1.25**2, 0.8**2))
# Wild rows (a detection far off the ball) spoil the noise level read from the pixels'
# third differences: two rows 40 px off in 15 frames read 2 px as 3-11 px (each spoils
# four of the twelve windows), and the robust scale and the priors' weight follow that
# level (docs/pages/cameras.md, "Frames lost"). Rows the chosen fit misses by more than
# WILD noise levels, or by more than APART times the rms of its misses of the other rows
# (three wild rows read 2 px as 16-22 px), are left out of a second reading, floored at
# that rms (``_wild_rows``); where it is more than REREAD times lower, every start runs
# again at it, from starts read without those rows (the rows stay in the fit, under the
# robust loss), and the new fit is read so again, REREADS times at most (a third wild
# row may be missed by less than 3 of the first level and by more than 3 of the second). No clean track of the studies that set these (76) was read
# again; a 10-frame MuJoCo drive whose first reading was low (0.87 px for 2) was, before
# the floor (0.3 px: 5.6 -> 12.9 cm off); starts read with the rows took a fit 1.8 cm
# off to 2.7 m.
WILD = 3.0
APART = 6.0
REREAD = 1.5
REREADS = 3
# A start's first flight may touch its bounce's surface this long before the bounce (s),
# whose time is read off the pixels (``_flies_through``).
NEAR_BOUNCE = 0.01
# The suffix of the key of a start's run with solids set aside (``_fit_starts``).
ASIDE = "/aside"
# Rows at a track's ends where the fit misses the row or the one next to it by more than
# WILD noise levels and HIT_APART times the noise its other misses show (``_off``,
# ``_hit_rows``) are read as another shot's (the ball hit by a racket or a hand, which the
# scene does not hold, between two frames) and the fit runs again without them, one row an
# end at a time (the fit passes close to the row next to one so missed), HITS times at
# most. A drive of estim's own physics seen from the side, 9
# frames and 2 more after the opponent's return: 12.9 cm off at 9.1 px rms with them, the
# fit through the first 10 rows 6.5 cm off missing the tenth by 112 px, through the first 9
# at 2.5 cm, the track's own without them. Not APART's 6: where the model's flight departs
# from the ball's at the ends (MuJoCo's drives, whose spin halves in a quarter of a second
# where estim's holds: seed 0, the second drive seen from the side, its first row missed by
# 7 times the others' rms, 6 times their median's noise) a row of the shot's own had been
# taken out, its fit 7.0 -> 10.7 cm off.
HITS = 3
HIT_APART = 10.0


def default_image_free(scene: Scene, n_cameras: int) -> tuple[str, ...]:
    """What an image fit estimates by default: the law's coefficients that act in the
    scene, the release position and velocity (3-vectors: a camera sees the ball in 3-D),
    the spin where it acts, and the clock offsets of cameras 2, 3, ... ."""
    base = registry.default_free(scene, True)
    out = list(base)
    for n in registry.expand(("position", "velocity")):
        if n not in out:
            out.append(n)
    out += list(registry.component("dt_camera2").components[:n_cameras - 1])
    return tuple(out)


def fit_image(scene: Scene, tracks: ImageTracks, *, free=None, fixed=None, loss: str = "cauchy", steps: int = 30,
              restarts: int = RESTARTS, max_segments: int = 48, prior=None, effects: bool = False,
              progress: Callable[[str], None] | None = None) -> FitResult:
    """Fit every ball of image tracks (module docstring).

    Args:
        scene: the scene, in whose world frame the cameras are calibrated.
        tracks: the pixels and their cameras (``estim.read_image_tracks_csv``).
        free: the parameters to fit (registry names); default :func:`default_image_free`.
        fixed: per ball, values to hold (or start from); as :func:`estim.fit`. Without
            a ``t0`` a ball is released at its track's first row (a video's clock, or a
            shot cut from a rally, starts where it starts: released at t = 0, the model
            would fly unseen up to that row, through whatever lies on the way; a note
            says so where that row is not at t = 0).
        restarts: restarts of every start, e from a grid over its range (default
            ``RESTARTS``).
        loss, steps, max_segments, prior, effects, progress: as :func:`estim.fit` (the
            scene's priors apply unless ``prior`` drops them: a few frames from one camera
            leave e and the friction coefficient loosely fixed, and what is known of the
            ball keeps them, and with them the path's depth, where they belong).

    Returns:
        A :class:`estim.FitResult` whose balls' residuals are in pixels (``unit == "px"``:
        ``rms_m`` and ``noise_m`` hold pixels) with ``model_position`` the fitted 3-D path
        at the rows' times and ``depth`` the depth report.

    Raises:
        ValueError: a ball the scene lacks, too few rows per flight, more than
            ``registry.MAX_CAMERAS`` cameras, and every refusal of :func:`estim.fit`.
    """
    return _fit_image_ends(scene, tracks, free=free, fixed=fixed, loss=loss, steps=steps, restarts=restarts,
                           max_segments=max_segments, prior=prior, effects=effects, progress=progress)[0]


def _fit_image_ends(scene: Scene, tracks: ImageTracks, *, free, fixed, loss, steps, restarts, max_segments, prior,
                    effects, progress) -> tuple[FitResult, dict[str, np.ndarray]]:
    """:func:`fit_image`, and per ball the rows at the track's ends it read as another
    shot's (``HIT_APART``), which a fit that goes on from it leaves out too."""
    if not isinstance(tracks, ImageTracks):
        raise TypeError(f"tracks must be estim.ImageTracks (estim.read_image_tracks_csv), got {type(tracks).__name__}")
    if len(tracks.cameras) > registry.MAX_CAMERAS:
        raise ValueError(f"{len(tracks.cameras)} cameras: an image fit takes at most {registry.MAX_CAMERAS}")
    say = progress or (lambda msg: None)
    options = dict(free=free, fixed=fixed, loss=loss, steps=steps, restarts=restarts, max_segments=max_segments,
                   prior=prior, effects=effects, progress=progress)
    result = _fit_image(scene, tracks, **options)
    ends = {b: np.zeros(0, np.int64) for b in tracks.balls}  # the rows read as another shot's, per ball
    for _ in range(HITS):
        more = {b: rows for b, bf in result.balls.items() if (rows := _hit_rows(tracks, b, bf, ends[b])).size}
        if not more:
            break
        for b, rows in more.items():
            say(f"{b}: the fit misses the track's end row(s) at t = "
                f"{', '.join(f'{t:.3f}' for t in tracks.t[b][rows])} s by more than {WILD:g} noise levels and "
                f"{HIT_APART:g} times the noise its other misses show: fitting again without them (a hit?)")
            ends[b] = np.sort(np.concatenate([ends[b], rows]))
            result.balls[b] = _fit_image(scene, _without(tracks, b, ends[b]), **options).balls[b]
    for b, rows in ends.items():
        if rows.size:
            result.balls[b].notes.append(
                f"{rows.size} row(s) at the track's ends (t = {', '.join(f'{t:.3f}' for t in tracks.t[b][rows])} s) "
                f"lie off the path of the others (each, or the row next to it, missed by more than {WILD:g} noise levels "
                f"and {HIT_APART:g} times the noise the other misses show, row by row from the end): the ball was hit there by what the "
                "scene does not hold (a racket, a hand), or the detector lost it; fitted without them (read as "
                "missed detections); the fitted path at their times is that of the other rows")
    result.source = tracks.source
    return result, ends


def _fit_image(scene: Scene, tracks: ImageTracks, *, free, fixed, loss, steps, restarts, max_segments, prior,
               effects, progress) -> FitResult:
    """:func:`fit_image` on every row of ``tracks`` (its steps 1 to 3)."""
    say = progress or (lambda msg: None)
    given = {b: dict(values) for b, values in (fixed or {}).items()}
    recs_of, t0_of, surfaces_of, clock = {}, {}, {}, {}
    for b in tracks.balls:
        scene.ball(b)  # KeyError naming the scene's balls
        n = int(np.sum(tracks.valid(b)))
        if n < MIN_ROWS:
            raise ValueError(f"ball {b!r}: only {n} rows with both pixels; a fit needs at least {MIN_ROWS}")
        first = float(np.min(tracks.t[b][tracks.valid(b)]))
        if "t0" not in given.get(b, {}) and first != 0.0:
            given.setdefault(b, {})["t0"] = first
            clock[b] = (f"the track's clock starts at t = {first:.3f} s: the release is taken at its first row "
                        "(to fit the release time: free t0, --also t0; to give it: fixed t0)")
            say(f"{b}: {clock[b]}")
        t0_of[b] = float(given.get(b, {}).get("t0", 0.0))  # the release the starts are read at
        recs, surfaces_of[b] = _starts(scene, tracks, b, t0_of[b])
        recs_of[b] = recs
        say(f"{b}: {len(recs)} start(s) in 3-D from {len(tracks.cameras)} camera(s): {len(recs[0].bounces)} "
            f"bounce(s), rays missed by {recs[0].ray_rms * 1e3:.2f} mrad rms")
    free = registry.expand(default_image_free(scene, len(tracks.cameras)) if free is None else free)
    options = dict(free=free, loss=loss, steps=steps, restarts=restarts, max_segments=max_segments,
                   progress=progress, prior=prior)
    first = {b: tracks.noise(b) for b in tracks.balls}
    noise_of = dict(first)
    fits, chosen = _solve(scene, tracks, recs_of, t0_of, surfaces_of, given, noise_of, say, options)
    wild_of = {}  # the rows of each ball read past, at its last reading
    reread = tracks.balls  # (a ball not read again keeps its fit and level: nothing new to read)
    for _ in range(REREADS):
        wild = {b: _wild_rows(tracks, b, chosen[b][0], noise_of[b]) for b in reread}
        reread = {b: level for b, (rows, level) in wild.items() if rows.size and level * REREAD < noise_of[b]}
        if not reread:
            break
        say(f"{', '.join(reread)}: rows missed by more than {WILD:g} noise levels or {APART:g} times the others' rms; "
            "the noise read without them "
            f"({', '.join(f'{v:.2f} px' for v in reread.values())}) is more than {REREAD:g} times lower: fitting again "
            "at it, from starts read without them")
        cleared = {b: _starts(scene, _without(tracks, b, wild[b][0]), b, t0_of[b]) for b in reread}
        noise_of.update(reread)
        wild_of.update({b: wild[b][0] for b in reread})
        again, chosen_again = _solve(scene, tracks, {b: recs for b, (recs, _) in cleared.items()}, t0_of,
                                     {**surfaces_of, **{b: s for b, (_, s) in cleared.items()}}, given,
                                     noise_of, say, options)
        fits = {**{k: f for k, f in fits.items() if f[3] not in reread}, **again}
        chosen.update(chosen_again)
    result = FitResult({b: fit[0] for b, fit in chosen.items()})
    for b, bf in result.balls.items():
        if b in clock:
            bf.notes.insert(0, clock[b])
        if b in wild_of:
            rows = wild_of[b]
            bf.notes.append(f"{rows.size} row(s) (t = {', '.join(f'{t:.3f}' for t in tracks.t[b][rows])} s) missed by "
                            f"more than {WILD:g} times the noise read from every row ({first[b]:.2f} px) or from "
                            f"the rows left, or by {APART:g} times the rms of the other misses: read without them "
                            f"(and no lower than that rms), {noise_of[b]:.2f} px, at which the fit ran again from "
                            "starts read without them (they stay in the fit, under the robust loss): wild detections?")
        if effects:
            attach_effects(scene, bf, chosen[b][2])
        bf.ball = b
        bf.depth = _depth_report(bf, tracks.cameras[0])
        bf.depth["alternative"] = _alternative(bf, chosen[b][1], [f[:2] for f in _of(fits, b) if f[0] is not bf])
        if not np.isfinite(chosen[b][1]):
            bf.notes.append("no start led to a path the cameras could have seen (every fit was released inside a "
                            "solid, passes behind a camera, hides behind a surface from it, rebounds off a solid where "
                            "the pixels show no bounce, or left its residuals not finite): "
                            "this path is the least bad; add a camera, or check the cameras' poses and the scene")
        for note in (bf.depth["note"], (bf.depth["alternative"] or {}).get("note", "")):
            if note:
                bf.notes.append(note)
    return result


def _starts(scene: Scene, tracks: ImageTracks, ball: str, t0: float) -> tuple[list, set]:
    """The start paths of ``ball`` read off its pixels through the physics
    (``reconstructions``), each moved out of the solids, with a second one ``FARTHER``
    along the rays where the bounces fit one surface only; and the solids the starts
    bounce on (``_bounced_on``)."""
    try:
        recs = reconstructions(tracks, ball, scene, alternatives=STARTS)
    except ValueError as err:
        raise ValueError(f"ball {ball!r}: {err}") from None
    surfaces = _bounced_on(scene, ball, recs)  # (before a start is moved off its surface)
    recs = [_released_outside(_inside_out(rec, scene, ball, tracks), scene, ball, tracks, t0) for rec in recs]
    if len(recs) < STARTS:
        farther = recs[0].scaled(FARTHER, tracks.cameras[0].centre)
        if not _released_inside(farther, scene, ball, t0):
            recs.append(farther)
    return recs, surfaces


def _solve(scene: Scene, tracks: ImageTracks, recs_of: dict, t0_of: dict, surfaces_of: dict, given: dict,
           noise_of: dict, say, options: dict) -> tuple[dict, dict]:
    """The fits of the balls of ``recs_of`` from their starts, and the starts moved along
    the rays where a fit is doubted (``DEEPER``), at the noise levels ``noise_of``: every
    start's ``(fit, loss, problem, ball)`` by key, and each ball's chosen one (``_choose``)."""
    fits = _kept(_fit_starts(scene, tracks, recs_of, t0_of, surfaces_of, given, 0, noise_of=noise_of, **options),
                 recs_of)
    for stage, factors in enumerate(DEEPER, 1):
        # First where any start's fit is doubted (the others may have run off as well, to
        # paths the priors cannot tell), then where the best one still is.
        doubted = [b for b in recs_of if any(_doubted(f, recs_of[b][0]) for f in _of(fits, b)) if stage == 1
                   or _doubted(min(_of(fits, b), key=lambda f: f[1]), recs_of[b][0])]
        moved = {b: [r for r in (recs_of[b][0].released_at(f, tracks.cameras[0].centre) for f in factors)
                     if not _released_inside(r, scene, b, t0_of[b])] for b in doubted}
        moved = {b: recs for b, recs in moved.items() if recs}
        if not moved:
            break
        say(f"{', '.join(moved)}: a fit doubted (a prior more than {DOUBT:g} sd off, a robust loss above "
            f"{MISFIT:g} per pixel coordinate, a path {DRIFT:g} m from the start, or no path the cameras could "
            f"have seen); starts moved by {' and '.join(f'{f:.2f}' for f in factors)} "
            "along the rays")
        fits.update(_kept(_fit_starts(scene, tracks, moved, t0_of, surfaces_of, given, stage * STARTS,
                                      noise_of=noise_of, **options), recs_of))
    chosen = {b: _choose(_of(fits, b), recs_of[b][0]) for b in recs_of}
    return fits, chosen


def _kept(fits: dict, recs_of: dict) -> dict:
    """``fits`` (``_fit_starts``) without the runs with solids set aside whose fit is
    doubted (``_doubted``, against the ball's first start): such a run answers a fit that
    met a solid on its way only where it ends where the starts and the priors say the ball
    is. (A MuJoCo serve whose second bounce, 8 cm before the net, sent it into the net's
    face: with the net set aside the fits ran to paths rolling along the table at e =
    0.25-0.67, 32-35 cm off, where the fits kept, which met the net, lay 8-26 cm off.)"""
    return {k: f for k, f in fits.items() if not (k.endswith(ASIDE) and _doubted(f, recs_of[f[3]][0]))}


def _wild_rows(tracks: ImageTracks, ball: str, bf, noise: float) -> tuple[np.ndarray, float]:
    """The rows of ``ball`` that the fit ``bf`` misses (the length of the pixel residual)
    by more than ``WILD`` noise levels, or by more than ``APART`` times the rms of its
    misses of the other rows (the largest set of the largest misses that all are: three
    rows 40 px off in 15 read 2 px as 16-22 px, and no row is missed by 3 of those); and
    the noise level read without them (NaN where there are none), no lower than the rms
    of the fit's misses of the other rows: a fit of p parameters to n pixel coordinates
    leaves misses of rms sigma sqrt((n - p) / n) where its model holds, more where it does
    not, so that rms is a floor for sigma; third differences read on a few rows after the
    largest misses are taken out can fall below it (a 10-frame MuJoCo drive read 0.87 px,
    then 0.3 px, its fit missing the other rows by 1.16 px rms: 2 px were added)."""
    r = np.asarray(bf.residuals, dtype=np.float64)[:, :2]  # (u, v; the third column is 0)
    miss = np.linalg.norm(r, axis=1)
    finite = np.isfinite(miss) & tracks.valid(ball)  # (a row without a detection has no miss)

    def rms_without(rows):
        others = finite & ~np.isin(np.arange(miss.size), rows)
        return math.sqrt(np.mean(r[others] ** 2)) if others.any() else math.nan

    wild = finite & (miss > WILD * noise)
    largest = np.argsort(np.where(finite, -miss, np.inf))
    for k in range(int(finite.sum()) // 3, 0, -1):
        if miss[largest[k - 1]] > APART * rms_without(largest[:k]):
            wild[largest[:k]] = True
            break
    rows = np.flatnonzero(wild)
    if not rows.size:
        return rows, float("nan")
    return rows, float(np.maximum(_without(tracks, ball, rows).noise(ball), rms_without(rows)))


def _hit_rows(tracks: ImageTracks, ball: str, bf, ends) -> np.ndarray:
    """The first and the last of ``ball``'s rows with pixels, not in ``ends`` (rows already
    left out), where the fit ``bf`` misses that row or the one next to it as :func:`_off`
    says; none where fewer than ``MIN_ROWS`` rows would be left. The row next to it:
    with rows past hits at both ends the fit passes through an end row and misses its
    neighbour (the first row is the release, and a path bent to one end's row can bend to
    the other's: a drive with a row before its release and two after the return, fitted
    with the last left out, missed the first three rows by 1.7, 86 and 19 px)."""
    left = np.flatnonzero(tracks.valid(ball) & ~np.isin(np.arange(len(tracks.t[ball])), ends))
    if left.size - 2 < MIN_ROWS:
        return np.zeros(0, np.int64)
    by_time = left[np.argsort(tracks.t[ball][left], kind="stable")]
    pairs = {int(by_time[0]): int(by_time[1]), int(by_time[-1]): int(by_time[-2])}
    return np.array(sorted(end for end, next_ in pairs.items()
                           if _off(tracks, ball, bf, end, ends) or _off(tracks, ball, bf, next_, ends)), np.int64)


def _off(tracks: ImageTracks, ball: str, bf, row: int, ends) -> bool:
    """Whether the fit ``bf`` misses ``ball``'s ``row`` (the distance in pixels between its
    detection and the fitted path's projection) by more than ``WILD`` times its noise
    level and ``HIT_APART`` times the noise its misses of the other rows with pixels, not
    in ``ends``, show (their median over sqrt(2 ln 2), a Rayleigh distribution's: the
    rows beside a hit at the other end, which the fit bends towards, do not raise it)."""
    uv = tracks.uv[ball]
    camera = tracks.cameras[int(tracks.view[ball][row])]
    miss = float(np.linalg.norm(np.asarray(camera.project(np.asarray(bf.model_position)[row])) - uv[row]))
    misses = np.linalg.norm(np.asarray(bf.residuals, dtype=np.float64)[:, :2], axis=1)
    others = tracks.valid(ball) & ~np.isin(np.arange(len(uv)), np.append(ends, row))
    return bool(others.any() and miss > WILD * bf.noise_m
                and miss > HIT_APART * np.median(misses[others]) / math.sqrt(2 * math.log(2)))


def _without(tracks: ImageTracks, ball: str, rows) -> ImageTracks:
    """``ball``'s track alone, its ``rows`` read as missed detections (NaN)."""
    uv = tracks.uv[ball].copy()
    uv[rows] = np.nan
    return ImageTracks(tracks.source, (ball,), tracks.cameras, {ball: tracks.t[ball]}, {ball: uv},
                       {ball: tracks.view[ball]})


def _fit_starts(scene: Scene, tracks: ImageTracks, recs_of: dict, t0_of: dict, surfaces_of: dict, given: dict,
                first: int, free, noise_of: dict, **options) -> dict[str, tuple]:
    """Fit each ball from its start paths ``recs_of[ball]`` side by side (``_fit_all``),
    always ``STARTS`` of them per ball (the last repeated where there are fewer: every shot
    of a given length then runs the same compiled program), under the keys ``_key(ball,
    first + j)``, at the pixels' noise level ``noise_of[ball]``. Returns each key's
    ``(fit, _loss, problem, ball)``."""
    data, images, ball_of, starts = {}, {}, {}, {}
    arrays = CameraArrays.of(tracks.cameras)
    for b, recs in recs_of.items():
        ok = tracks.valid(b)
        t, at = np.unique(tracks.t[b][ok], return_index=True)
        for j in range(STARTS):
            key = _key(b, first + j)
            rec = recs[min(j, len(recs) - 1)]
            data[key] = (t, rec.position[ok][at])
            starts[key] = start_values(rec, scene, b, t0_of[b])
            images[key] = ImageRows(t=tracks.t[b], uv=tracks.uv[b], view=tracks.view[b], cameras=arrays,
                                    noise=noise_of[b], initial=_initial(rec, starts[key]))
            ball_of[key] = b
    # The path's own starts for the fitted parameters (fixed values double as starts);
    # what the caller holds or gives wins.
    fixed = {k: {**{n: v for n, v in starts[k].items() if n in free}, **given.get(ball_of[k], {})} for k in data}
    every, units = _fit_all(scene, data, free=free, fixed=fixed, balls=ball_of, images=images, explore=True,
                            graduated=GRADUATED, **options)
    out = {k: (bf, units.problems[units.names.index(k)], ball_of[k]) for k, bf in every.balls.items()}
    struck = [k for k, bf in every.balls.items() if _struck(bf, surfaces_of[ball_of[k]])]
    if struck:
        # Run again with what no start bounces on set aside, then polished in the whole
        # scene from where that run ended: a fit that met the net on its way can settle
        # there (a serve seen from in front whose start lay 2.8 cm from its path ran into
        # the net's face and ended 1.5 m off; with the net set aside, 0.8 cm). The polish
        # meets the net again where the path does go through it.
        kept = frozenset().union(*surfaces_of.values())
        aside = scene.set_aside([n for n in scene.names if n not in kept])
        around, _ = _fit_all(aside, data, free=free, fixed=fixed, balls=ball_of, images=images, explore=True,
                             graduated=GRADUATED, **options)
        # (Every key runs, so that the program compiled for this batch serves: a key that
        # struck nothing, or whose run ended released inside a solid set aside, from its
        # start, and is not kept.)
        struck = [k for k in struck if not _in_solid(scene, ball_of[k], around.balls[k].values)]
        ended = {k: {**{n: v for n, v in around.balls[k].values.items() if n in free}, **given.get(ball_of[k], {})}
                 if k in struck else fixed[k] for k in data}
        polished, units = _fit_all(scene, data, free=free, fixed=ended, balls=ball_of, images=images,
                                   explore=True, **{**options, "restarts": 0})
        out.update({k + ASIDE: (polished.balls[k], units.problems[units.names.index(k)], ball_of[k])
                    for k in struck})
    # A fit released inside a solid, whose path the cameras could not have seen, or that
    # rebounds off a solid on which no start bounces (``_struck``) is no path (its loss
    # infinite: doubted, and kept only where every start's fit is one).
    return {k: (bf, np.inf if _in_solid(scene, b, bf.values) or _hidden(scene, b, tracks, bf)
                or _struck(bf, surfaces_of[b]) else _loss(bf), problem, b)
            for k, (bf, problem, b) in out.items()}


def _struck(bf, surfaces) -> bool:
    """Whether the fit ``bf`` rebounds off a solid on which no start bounces (``surfaces``,
    ``_bounced_on``: the starts put the bounces where the pixels' cusps meet the scene's
    surfaces; a ball that comes back off the net, seen from far behind, looks much like one
    that flies on after its bounce, and a real net stops a ball)."""
    return any(solid not in surfaces for solid, _ in bf.contacts)


def _choose(fits: list[tuple], start) -> tuple:
    """The fit to keep of a ball's ``(fit, loss, ...)``: of those not doubted (``_doubted``;
    all of them where every one is), of those within ``AMBIGUOUS`` of the least loss (paths
    the pixels cannot tell apart), the one nearest the start read from the pixels through
    the physics (``start``, a ``Reconstruction``: its bounces on the scene's surfaces fix a
    depth that a moved start's fit may leave for a path under the table or beyond it,
    bouncing on the floor, at a loss as low or lower: a drive seen from in front, whose
    first start's fit lay 5 cm from the truth, ended 2.5 m off, under the table, from a
    moved start at a loss 3 below it)."""
    fits = [f for f in fits if not _doubted(f, start)] or fits
    least = min(f[1] for f in fits)
    near = [f for f in fits if not f[1] - least >= AMBIGUOUS]  # (every fit where all losses are infinite)
    return min(near, key=lambda f: float(np.nanmean(np.linalg.norm(f[0].model_position - start.position, axis=1))))


def _of(fits: dict, ball: str) -> list[tuple]:
    """The ``(fit, loss, problem, ball)`` of every start of ``ball``."""
    return [f for f in fits.values() if f[3] == ball]


def _doubted(fit: tuple, start) -> bool:
    """Whether a start's ``(fit, loss, ...)`` sits more than ``DOUBT`` standard deviations
    from one of its priors, misses its pixels by more than ``MISFIT`` of robust loss per
    coordinate on average, or lies farther than ``DRIFT`` from the ball's first start
    (``start``, a ``Reconstruction``) on average."""
    bf, loss = fit[:2]
    return (any(abs(bf.values[n] - mean) > DOUBT * sd for n, (mean, sd) in bf.prior.items())
            or not loss <= MISFIT * max(2 * bf.n_obs, 1)  # (u and v of each observed row)
            or not np.nanmean(np.linalg.norm(bf.model_position - start.position, axis=1)) <= DRIFT)


def _bounced_on(scene: Scene, ball: str, recs) -> frozenset[str]:
    """The names of the solids that the bounces of the start paths ``recs`` touch (their
    bounce points within ``EDGE`` radii of the surface, as :func:`_flies_through` reads them)."""
    points = np.concatenate([rec.bounce_points.reshape(-1, 3) for rec in recs])
    box, plane = inside(np, scene, points, np.full(len(points), EDGE * scene.ball(ball).radius))
    touched = np.concatenate([box, plane], axis=1).any(axis=0)
    return frozenset(name for name, hit in zip(scene.names, touched, strict=True) if hit)


def start_values(rec, scene: Scene, ball: str, t0: float = 0.0) -> dict[str, float]:
    """Starting values read off a start path (``estim.tracks._reconstruct``): the release
    state at ``t0`` from its first flight; at its first bounce, e from the normal velocities
    (``-v_z after / v_z before``), the friction law's mu from the tangential change
    (``|dv_t| / ((1 + e) |v_z before|)``: a sliding bounce's, a lower bound where the ball
    grips); in air the spin from the first flight's own acceleration less the drag, the
    Magnus part inverted (``estim.model._air.spin_for_lift``). Clipped inside the ranges."""
    out = dict(zip(("x0", "y0", "z0"), map(float, rec.flights[0, 0] + _back(rec, t0)), strict=True))
    out.update(zip(("vx0", "vy0", "vz0"), map(float, rec.velocity(t0, 0)), strict=True))
    if rec.bounces:
        b = rec.bounces[0]
        before, after = rec.velocity(b, 0), rec.velocity(b, 1)
        if before[2] < 0:
            e = float(np.clip(-after[2] / before[2], 0.05, 0.98))
            out["e"] = e
            mu = float(np.linalg.norm((after - before)[:2]) / ((1.0 + e) * -before[2]))
            out["mu"] = float(np.clip(mu, 0.05, 0.9))
    if scene.air is not None and rec.flights.shape[1] == 3:
        spec = scene.ball(ball)
        end = rec.bounces[0] if rec.bounces else float(rec.t.max())
        middle = 0.5 * (rec.refs[0] + end)
        v = rec.velocity(middle, 0)
        drag = spinless_acceleration(scene.air, spec.radius, spec.mass, DRAG_COEFFICIENT)(v)
        spin = spin_for_lift(scene.air, spec.radius, spec.mass, v, rec.flights[0, 2] - drag)
        out.update(zip(("spin_x", "spin_y", "spin_z"), map(float, np.clip(spin, -SPIN_START, SPIN_START)),
                       strict=True))
    return out


def _inside_out(rec, scene: Scene, ball: str, tracks: ImageTracks):
    """A start path without a bounce that runs through a solid is no start (it has only
    gravity's size to fix its depth, which drag and spin falsify): it is scaled
    about the first camera's centre (its pixels stay) to the depth that puts its first point
    nearest the scene's release point of the ball. Other paths are returned as they are."""
    if rec.bounces:  # a bounce on a surface holds the scale; only a path without one can stray
        return rec
    spec = scene.ball(ball)
    ok = tracks.valid(ball)
    # Half the radius: a start that touches a surface at a bounce (the centre one radius
    # above it, to rounding) is a start; one that runs through a solid is not.
    in_box, in_plane = inside(np, scene, rec.position[ok], np.full(int(ok.sum()), 0.5 * spec.radius))
    if not (in_box.any() or in_plane.any()):
        return rec
    rows = np.flatnonzero(ok & (tracks.view[ball] == 0))
    if not rows.size:
        return rec
    centre = tracks.cameras[0].centre
    first = rec.position[rows[np.argmin(tracks.t[ball][rows])]] - centre
    factor = float(np.dot(np.asarray(spec.position) - centre, first) / np.dot(first, first))
    return rec.scaled(min(max(factor, 0.05), 20.0), centre)


def _released_outside(rec, scene: Scene, ball: str, tracks: ImageTracks, t0: float = 0.0):
    """A start path released inside a solid (:func:`_released_inside`) or whose first flight
    rises through the solid it bounces on (:func:`_flies_through`), scaled about the first
    camera's centre (its pixels stay) by the factor nearest 1 after which neither holds (a
    first flight seen end-on, its depth held only by the bounce's ray, can be read below
    the table; just under it is not out of it). Any other path, or one that no factor
    between 1/20 and 20 frees, is returned as it is."""
    if not (_released_inside(rec, scene, ball, t0) or _flies_through(rec, scene, ball, t0)):
        return rec
    surface = inside(np, scene, rec.bounce_points[:1], np.array([EDGE * scene.ball(ball).radius]))
    centre = tracks.cameras[0].centre
    for step in range(1, 100):  # 1 -+ 1%, 2%, ...: the nearest depth first
        for factor in (1.0 - 0.01 * step, 1.0 + 0.01 * step, 20.0 ** (step / 99) if step > 50 else None):
            if not factor or factor < 0.05:
                continue
            scaled = rec.scaled(factor, centre)
            if not (_released_inside(scaled, scene, ball, t0) or _flies_through(scaled, scene, ball, t0, surface)):
                return scaled
    return rec


def _initial(rec, values: dict[str, float]) -> Initial:
    """The fit's ``Initial`` of a start path: its starting values and bounces."""
    v = np.array([values["vx0"], values["vy0"], 0.0])
    direction = tuple(v / np.linalg.norm(v)) if np.linalg.norm(v) > 0 else (1.0, 0.0, 0.0)
    return Initial(e=values.get("e", E_DEFAULT), mu_t=MU_DEFAULT, vx0=values["vx0"], vz0=values["vz0"],
                   x0=values["x0"], z0=values["z0"], bounces=tuple(rec.bounces), y0=values["y0"],
                   vy0=values["vy0"], direction=direction, mu=values.get("mu", FRICTION_DEFAULT),
                   spin=tuple(values.get(f"spin_{c}") for c in "xyz"))


def _back(rec, t: float) -> np.ndarray:
    """The first flight's position at time ``t`` (m), extrapolated back from its reference."""
    dt = t - rec.refs[0]
    return rec.velocity(rec.refs[0], 0) * dt + 0.5 * rec.acceleration(0) * dt**2


def _key(ball: str, j: int) -> str:
    return ball if j == 0 else f"{ball}#start{j + 1}"


def _released_inside(rec, scene: Scene, ball: str, t0: float = 0.0) -> bool:
    """Whether a start path's release point (:func:`start_values`) lies within the ball's
    radius of a solid, where a fit cannot start. (Near its bounces a start moved along the
    rays may run through the surface: the fit's physics takes it off.)"""
    return _in_solid(scene, ball, start_values(rec, scene, ball, t0))


def _hidden(scene: Scene, ball: str, tracks: ImageTracks, bf) -> bool:
    """Whether the fitted path lies where its cameras could not have seen it: behind a
    row's camera (its centre less than a radius in front of the lens) at any row, or at
    more than half of its rows hidden behind a box whose top a ball bounces on (the line
    of sight from the row's camera to the ball's centre passes through it; at least
    ``NARROW`` radii wide, as the start's bounce surfaces: a table, a step; not a net, which
    a camera sees through; its outline shrunk by the ball's radius). A camera tracked the
    ball there, so no such path is the ball's: a drive seen from in front had its fit run
    to a path under the table, 2.6 m off, at a robust loss 2 below the truth's basin, and
    another, from a start without its bounce, to a path that ends in the lens."""
    radius = scene.ball(ball).radius
    rows = np.flatnonzero(tracks.valid(ball))
    position = np.asarray(bf.model_position)[:len(tracks.t[ball])][rows]
    views = tracks.view[ball][rows]
    if any(np.any(cam.depth(position[views == k]) < radius) for k, cam in enumerate(tracks.cameras)):
        return True
    centre, half = np.asarray(scene.box_centre), np.asarray(scene.box_half)
    solid = 2 * np.minimum(half[:, 0], half[:, 1]) >= NARROW * radius
    if not solid.any():
        return False
    eye = np.stack([c.centre for c in tracks.cameras])[views]
    ray = position - eye
    inset = np.array([radius, radius, 0.0])  # (a ball beside the outline, seen past its edge, shows)
    lo = (centre[solid] - half[solid] + inset)[None] - eye[:, None]
    hi = (centre[solid] + half[solid] - inset)[None] - eye[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):  # (slabs parallel to the ray)
        a, b = lo / ray[:, None], hi / ray[:, None]
    parallel = ray[:, None] == 0.0
    enter = np.where(parallel, np.where((lo <= 0) & (hi >= 0), -np.inf, np.inf), np.minimum(a, b)).max(axis=2)
    leave = np.where(parallel, np.where((lo <= 0) & (hi >= 0), np.inf, -np.inf), np.maximum(a, b)).min(axis=2)
    hidden = ((enter < leave) & (leave > 0.0) & (enter < 1.0)).any(axis=1)
    return bool(hidden.sum() > 0.5 * rows.size)


def _in_solid(scene: Scene, ball: str, values: dict) -> bool:
    """Whether the release point of ``values`` (``x0``, ``y0``, ``z0``) lies within the
    ball's radius of a solid."""
    point = np.array([[values["x0"], values["y0"], values["z0"]]])
    in_box, in_plane = inside(np, scene, point, np.array([scene.ball(ball).radius]))
    return bool(in_box.any() or in_plane.any())


def _flies_through(rec, scene: Scene, ball: str, t0: float = 0.0, surface=None) -> bool:
    """Whether a start path's first flight, from the release at ``t0`` until ``NEAR_BOUNCE``
    before its first bounce, runs half the ball's radius into the solid it bounces on: a
    path released below the table that rises through it to bounce on its top is no start.
    (Other solids it may graze, as a start moved along the rays grazes the net: the fit's
    physics takes it off them.) ``surface``: that solid as ``inside``'s masks (the boxes'
    and the planes'), by default the one the path's bounce point touches (a path moved along
    the rays moves its bounce off the surface). A path without a bounce: ``_inside_out``."""
    if not rec.bounces:
        return False
    radius = scene.ball(ball).radius
    box, plane = surface or inside(np, scene, rec.bounce_points[:1], np.array([EDGE * radius]))
    # The flight's own curve every 5 ms: between two frames a path can cross a thin solid.
    times = np.arange(t0, max(rec.bounces[0] - NEAR_BOUNCE, t0) + 1e-9, 0.005)
    flight = np.stack([rec.flights[0, 0] + _back(rec, t) for t in times])
    in_box, in_plane = inside(np, scene, flight, np.full(len(flight), 0.5 * radius))
    return bool((in_box & box).any() or (in_plane & plane).any())


def _loss(bf) -> float:
    """How well a start's fit explains its pixels, to choose between starts: the robust
    loss of its residuals at the pixels' noise level (the same scale for every start), and
    of its priors."""
    u = np.concatenate([bf.residuals.ravel() / bf.noise_m, [(bf.values[n] - m) / sd for n, (m, sd) in bf.prior.items()]])
    return float(np.sum(robust_loss(u, "cauchy"))) if np.all(np.isfinite(u)) else np.inf


def _alternative(bf, loss: float, others) -> dict | None:
    """The nearest rival of the chosen fit among the other starts' ``(fit, loss)``: one
    whose loss is within ``AMBIGUOUS`` of ``loss`` (above it, or below: ``_choose``) and
    whose path lies more than
    ``DEPTH_LIMIT`` from the chosen one on average (a second solution that the pixels
    cannot rule out); ``None`` without one."""
    rivals = []
    for other, other_loss in others:
        distance = float(np.mean(np.linalg.norm(other.model_position - bf.model_position, axis=1)))
        if other_loss - loss < AMBIGUOUS and distance > DEPTH_LIMIT:
            rivals.append((other_loss - loss, distance, other))
    if not rivals:
        return None
    gap, distance, other = min(rivals, key=lambda r: r[0])
    # (A rival more than AMBIGUOUS below was doubted, ``_choose``: the pixels favour it and
    # the priors or the start read off them do not.)
    how = (f"explains the pixels about as well (robust loss {gap:+.2f})" if gap > -AMBIGUOUS else
           f"explains the pixels better (robust loss {gap:+.2f}) but was set aside, far from a prior or from "
           "the start read off the pixels")
    return {"distance_m": distance, "loss_difference": gap, "values": dict(other.values),
            "note": f"a second path, {distance * 100:.0f} cm from this one on average (e = {other.values['e']:.3f}), "
                    f"{how}: one camera cannot tell them apart; add a camera, or more frames"}


def _depth_report(bf, camera) -> dict:
    """The release point's standard errors along the camera's axis and across it (m)."""
    names = ("x0", "y0", "z0")
    axis = np.asarray(camera.rotation)[2]
    out = {"camera": camera.name, "axis": axis.tolist()}
    if not all(n in bf.names for n in names):
        out.update(along_axis_m=None, across_axis_m=None, fixed=True, note="")
        return out
    k = [bf.names.index(n) for n in names]
    sd = np.array([bf.stderr[n] for n in names])
    if not np.all(np.isfinite(sd)):
        out.update(along_axis_m=None, across_axis_m=None, fixed=False,
                   note=f"the depth of the path along camera {camera.name!r}'s axis is not fixed by this data: "
                        "the release point cannot be determined (see the notes above); add a camera, or hold "
                        "the release point fixed")
        return out
    cov = bf.correlation[np.ix_(k, k)] * np.outer(sd, sd)
    along = float(math.sqrt(max(axis @ cov @ axis, 0.0)))
    across = float(math.sqrt(max(np.trace(cov) - along**2, 0.0) / 2.0))
    fixed = along <= DEPTH_LIMIT
    note = "" if fixed else (f"the depth of the release point along camera {camera.name!r}'s axis is known only to "
                             f"{along * 100:.1f} cm (across it to {across * 100:.1f} cm): the pixels leave the "
                             "depth open; add a camera, or more bounces in view")
    out.update(along_axis_m=along, across_axis_m=across, fixed=fixed, note=note)
    return out
