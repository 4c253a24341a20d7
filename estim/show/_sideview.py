"""The replay as a matplotlib side view (the XZ plane), for machines without OpenGL.

The same content as the MuJoCo replay (``estim.show._replay``): the scene's boxes as seen from
-y, the fitted balls as solid discs, the measured sample of each ball at the frame as a
translucent halo of the same colour (1.3 times the radius), the samples of the last
``trail`` seconds as dots, and the time and fitted parameters in the title and legend.
Balls nearer the viewer (smaller y) are drawn on top, as the camera would see them.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

from ..model._scene import Scene, load_scene
from ._plots import _colour
from ._replay import (
    GHOST_ALPHA,
    GHOST_SCALE,
    TRAIL_ALPHA,
    ReplayInfo,
    ReplayMotion,
    _rgb,
    check_output,
    replay_motion,
    write_video,
)

__all__ = ["SideView", "render_sideview"]

TREAD_RGB = (0.75, 0.66, 0.53)  # the scene file's tread material
GROUND_RGB = (0.78, 0.80, 0.82)


class SideView:
    """One matplotlib figure of a replay, redrawn per frame.

    ``SideView(scene, motion, width, height).frame(k)`` is frame ``k`` as a
    ``(height, width, 3)`` uint8 RGB array; ``to_pixels(points)`` maps world points to
    (column, row) pixels of those frames (for checks and annotations).
    """

    def __init__(self, scene: Scene, motion: ReplayMotion, width: int = 640, height: int = 360,
                 *, trail: float = 0.3):
        self.motion, self.trail = motion, trail
        self.width, self.height = int(width), int(height)
        dpi = 100
        self.fig = Figure(figsize=(self.width / dpi, self.height / dpi), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.fig)
        # The picture on the left, legend and clock on the right, so that neither ever
        # covers a ball.
        ax = self.ax = self.fig.add_axes((0.08, 0.12, 0.62, 0.78))
        lo, hi = self._extent(scene, motion)
        pad = 0.05 * max(hi[0] - lo[0], hi[1] - lo[1])
        xlim, zlim = (lo[0] - pad, hi[0] + pad), (lo[1] - pad, hi[1] + pad)
        for c, h in zip(np.asarray(scene.box_centre), np.asarray(scene.box_half), strict=True):
            ax.add_patch(Rectangle((c[0] - h[0], c[2] - h[2]), 2 * h[0], 2 * h[2], facecolor=TREAD_RGB,
                                   edgecolor="0.35", lw=0.8, zorder=1))
        for n, s in zip(np.asarray(scene.plane_normal), np.asarray(scene.plane_offset), strict=True):
            if n[2] > 0.5:  # a ground: solid below z = s
                ax.axhspan(zlim[0] - 1.0, s, color=GROUND_RGB, zorder=0)
        self.balls, self.halos, self.trails = {}, {}, {}
        # Nearer the viewer (smaller y) on top.
        depth = {b: float(np.nanmean(motion.fitted[b][:, 1])) for b in motion.balls}
        order = sorted(motion.balls, key=lambda b: -depth[b])
        for i, b in enumerate(order):
            c = _colour(b, motion.balls.index(b))
            r = motion.radius[b]
            z = 3 + 3 * i
            # Moving artists are 'animated': left out of the static background, which is
            # drawn once; each frame restores it and draws only these (blitting).
            self.trails[b] = ax.scatter([], [], s=6, color=c, alpha=TRAIL_ALPHA, lw=0, zorder=z,
                                        animated=True)
            self.halos[b] = ax.add_patch(Circle((0, 0), GHOST_SCALE * r, color=c, alpha=GHOST_ALPHA,
                                                lw=0, zorder=z + 1, animated=True))
            self.balls[b] = ax.add_patch(Circle((0, 0), r, facecolor=c, edgecolor="none", zorder=z + 2,
                                                animated=True, label=f"{b}\n{_legend_caption(motion, b)}"))
            self._order = [*getattr(self, "_order", []), b]
        ax.set_xlim(*xlim)
        ax.set_ylim(*zlim)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x [m]", fontsize=8)
        ax.set_ylabel("z [m]", fontsize=8)
        ax.tick_params(labelsize=7)
        handles = [self.balls[b] for b in motion.balls]
        self.fig.legend(handles=handles, loc="upper left", bbox_to_anchor=(0.72, 0.82),
                        fontsize=7, frameon=False, labelspacing=1.0,
                        title="fitted (solid disc)\nmeasured (halo, dots)", title_fontsize=7)
        ax.set_title("Side view (x-z): the fitted model and the measured samples", fontsize=8.5,
                     loc="left")
        self.clock = self.fig.text(0.73, 0.86, "", ha="left", va="bottom", fontsize=9,
                                   animated=True)
        self._background = None

    def _static(self):
        """Draw everything that does not move, once, and keep the pixels."""
        if self._background is None:
            self.canvas.draw()
            self._background = self.canvas.copy_from_bbox(self.fig.bbox)
        return self._background

    @staticmethod
    def _extent(scene: Scene, motion: ReplayMotion):
        c, h = np.asarray(scene.box_centre), np.asarray(scene.box_half)
        pts = [np.stack([c[:, 0] - h[:, 0], c[:, 2] - h[:, 2]], 1), np.stack([c[:, 0] + h[:, 0], c[:, 2] + h[:, 2]], 1)]
        for b in motion.balls:
            r = GHOST_SCALE * motion.radius[b]
            for p in (motion.fitted[b], motion.samples[b][1]):
                p = p[np.all(np.isfinite(p), axis=1)][:, [0, 2]]
                pts += [p - r, p + r]
        pts = np.concatenate(pts)
        return pts.min(axis=0), pts.max(axis=0)

    def frame(self, k: int) -> np.ndarray:
        m = self.motion
        t = m.t[k]
        for b in m.balls:
            self.balls[b].center = (m.fitted[b][k, 0], m.fitted[b][k, 2])
            g = m.measured[b][k]
            self.halos[b].set_visible(bool(np.all(np.isfinite(g))))
            if np.all(np.isfinite(g)):
                self.halos[b].center = (g[0], g[2])
            st, sp = m.samples[b]
            recent = sp[(st > t - self.trail) & (st <= t)] if self.trail > 0 else sp[:0]
            self.trails[b].set_offsets(recent[:, [0, 2]] if len(recent) else np.zeros((0, 2)))
        self.clock.set_text(f"t = {t:6.3f} s")
        self.canvas.restore_region(self._static())
        for b in self._order:  # far to near
            for artist in (self.trails[b], self.halos[b], self.balls[b]):
                if artist.get_visible():
                    self.ax.draw_artist(artist)
        self.fig.draw_artist(self.clock)
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def frames(self) -> Iterator[np.ndarray]:
        for k in range(self.motion.n_frames):
            yield self.frame(k)

    def to_pixels(self, points) -> np.ndarray:
        """(column, row from the top) pixels of world points ``(..., 3)`` (x and z used)."""
        p = np.asarray(points, np.float64)
        self._static()  # the equal aspect fixes the axes' box at draw time
        disp = self.ax.transData.transform(p[..., [0, 2]].reshape(-1, 2))
        col, row = disp[:, 0], self.height - disp[:, 1]
        return np.stack([col, row], axis=-1).reshape(p.shape[:-1] + (2,))


def _legend_caption(motion, ball: str) -> str:
    """The parameters of the replay's caption, two to a line (``e = 0.580, mu_t = 0.950`` /
    ``vx0 = 0.500 m/s`` / ...)."""
    parts = motion.caption(ball, sep="\n").split("\n")
    return "\n".join(", ".join(parts[i:i + 2]) for i in range(0, len(parts), 2))


def render_sideview(scene, fit, tracks, out, *, fps: float = 25.0, width: int = 640,
                    height: int = 360, trail: float = 0.3) -> ReplayInfo:
    """The replay of :func:`estim.render_replay` drawn with matplotlib in the x-z plane
    (no OpenGL needed), written to ``out`` (``.gif``, or ``.mp4`` with ffmpeg on PATH).
    Arguments as for :func:`estim.render_replay`; ``scene`` may also be an
    :class:`estim.Scene`."""
    check_output(out, fps)
    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    motion = replay_motion(scene, fit, tracks, fps=fps)
    view = SideView(scene, motion, width, height, trail=trail)

    colours = [_rgb(_colour(b, i)) for i, b in enumerate(motion.balls)]
    n = write_video(view.frames(), out, fps, colours=colours)
    return ReplayInfo(os.fspath(out), n, float(fps), float(motion.t[0]), float(motion.t[-1]),
                      motion.balls, "matplotlib")
