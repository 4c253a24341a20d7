"""Plots of a fit in pixels (matplotlib): what each camera saw with the fitted path drawn
over it, and the fitted 3-D path from the side and from above.

As in ``estim.show._plots``, each function draws on its own ``Figure``, saves it when given
a path and returns it.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from ..fitting._fit import FitResult
from ..tracks._image import ImageTracks
from ._plots import _colour, _save

__all__ = ["plot_image_fit", "plot_path", "points_on_rays", "replay_samples"]


def plot_image_fit(tracks: ImageTracks, result: FitResult, path=None) -> Figure:
    """One panel per camera, in image coordinates (u right, v down, the image's frame
    where its size is known): the tracked pixels (markers; outliers crossed) and the
    fitted path as the camera sees it (line)."""
    n = len(tracks.cameras)
    fig = Figure(figsize=(7 * min(n, 2), 4.2 * ((n + 1) // 2)), layout="tight")
    axes = np.atleast_1d(fig.subplots((n + 1) // 2, min(n, 2))).reshape(-1)
    for k, (ax, cam) in enumerate(zip(axes, tracks.cameras, strict=False)):
        for i, (ball, bf) in enumerate(result.balls.items()):
            c = _colour(ball, i)
            rows = tracks.view[ball] == k
            uv = tracks.uv[ball][rows]
            out = np.any(np.abs(bf.residuals[: rows.size][rows, :2]) > 5 * bf.noise_m, axis=1)
            ax.plot(uv[~out, 0], uv[~out, 1], "o", ms=2.5, color=c, alpha=0.55, label=f"{ball} tracked")
            if out.any():
                ax.plot(uv[out, 0], uv[out, 1], "x", ms=5, color="crimson", label="outliers")
            seen = np.asarray(cam.project(bf.model_position[: rows.size][rows]))
            ax.plot(seen[:, 0], seen[:, 1], "-", lw=1.3, color=c, label=f"{ball} fitted")
        if cam.size is not None:
            ax.set_xlim(0, cam.size[0])
            ax.set_ylim(cam.size[1], 0)
        else:
            ax.invert_yaxis()
        ax.set_aspect("equal")
        ax.set_title(f"camera {cam.name!r}")
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
        ax.legend(fontsize=7)
    for ax in axes[n:]:
        ax.set_visible(False)
    return _save(fig, path)


def points_on_rays(tracks: ImageTracks, ball: str, position) -> np.ndarray:
    """``(n, 3)``: for each row of ``ball``, the point of its pixel's ray nearest to
    ``position[i]`` (the fitted path): the pixels placed in 3-D at the fitted depth; NaN
    where the pixel was lost."""
    out = np.full((tracks.t[ball].size, 3), np.nan)
    for k, cam in enumerate(tracks.cameras):
        rows = (tracks.view[ball] == k) & tracks.valid(ball)
        d = cam.rays(tracks.uv[ball][rows])
        v = np.asarray(position)[rows] - cam.centre
        out[rows] = cam.centre + np.sum(v * d, axis=1)[:, None] * d
    return out


def plot_path(tracks: ImageTracks, result: FitResult, path=None) -> Figure:
    """The fitted 3-D path (line) from the side (the horizontal direction of travel
    against height) and from above (x, y), with each pixel placed on its ray at the fitted
    depth (markers, :func:`points_on_rays`) and the cameras' positions from above."""
    fig = Figure(figsize=(11, 4.2), layout="tight")
    side, above = fig.subplots(1, 2)
    for i, (ball, bf) in enumerate(result.balls.items()):
        c = _colour(ball, i)
        order = np.argsort(bf.model_t)
        p = bf.model_position[order]
        pts = points_on_rays(tracks, ball, bf.model_position)[order]
        along = 1 if np.ptp(p[:, 1]) >= np.ptp(p[:, 0]) else 0
        side.plot(pts[:, along], pts[:, 2], "o", ms=2.5, color=c, alpha=0.5, label=f"{ball}: pixels on their rays")
        side.plot(p[:, along], p[:, 2], "-", color=c, lw=1.3, label=f"{ball} fitted")
        side.set_xlabel(f"{'xy'[along]} (m)")
        above.plot(pts[:, 0], pts[:, 1], "o", ms=2.5, color=c, alpha=0.5)
        above.plot(p[:, 0], p[:, 1], "-", color=c, lw=1.3)
    for cam in tracks.cameras:
        above.plot(*cam.centre[:2], "k^", ms=7)
        above.annotate(cam.name, cam.centre[:2], fontsize=8, xytext=(4, 4), textcoords="offset points")
    side.set_ylabel("z (m)")
    side.set_title("from the side")
    side.set_aspect("equal", adjustable="datalim")
    side.legend(fontsize=7)
    above.set_xlabel("x (m)")
    above.set_ylabel("y (m)")
    above.set_title("from above (cameras: triangles)")
    above.set_aspect("equal", adjustable="datalim")
    return _save(fig, path)


def replay_samples(tracks: ImageTracks, fit: dict, camera: int = 0) -> dict:
    """``ball -> (t, position)`` for a replay from camera ``camera``'s viewpoint
    (``estim.show._replay``): its rows' pixels placed on their rays at the fitted depth
    (:func:`points_on_rays` of fit.json's ``"fitted"`` path), which that camera sees exactly
    where it saw the ball.

    Raises:
        ValueError: a ball without a fitted path, or a path that does not match the rows."""
    out = {}
    for ball in tracks.balls:
        fitted = fit.get("balls", {}).get(ball, {}).get("fitted")
        if fitted is None:
            raise ValueError(f"the fit has no fitted path of ball {ball!r} (fit.json of `estim fit --camera`)")
        position = np.asarray(fitted["position"], dtype=np.float64)
        if position.shape != (tracks.t[ball].size, 3):
            raise ValueError(f"ball {ball!r}: the fit's path has {position.shape[0]} rows, the tracks "
                             f"{tracks.t[ball].size}: not the fit of these tracks")
        rows = tracks.view[ball] == camera
        out[ball] = (tracks.t[ball][rows], points_on_rays(tracks, ball, position)[rows])
    return out
