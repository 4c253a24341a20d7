"""Hits: where something the scene does not have strikes the tracked ball.

A tracked shot often runs past its own end (the opponent's racket returns the ball, a hand
catches it) or starts before it (a serve's toss). At such a hit the ball's velocity jumps
far from every solid of the scene, and no motion of the scene's ball explains the samples
on both sides of it: a fit of the whole track bends its flights, its bounce and its spin
towards samples it cannot reach. ``estim fit`` (``estim.fitting._job.fit_csv``) fits the
longest stretch of the track between hits and says where it cut.

**Detection** (NumPy, before any fit). With gravity known, ``w = z + g t^2 / 2`` and the
horizontal coordinates are straight lines in a flight in vacuum; in air they bend by the
drag and Magnus accelerations, which change the velocity by ``a dt`` per frame, smoothly.
At every sample i, straight lines fitted by least squares to the ``WINDOW`` samples before
i and to those from i on give the mean velocity on each side; their difference ``dv`` is
the jump at i (plus what the air changes over a window, a fraction of a metre per second
for a ping-pong ball at 180 Hz). A jump is a hit where it exceeds ``HIT_SPEED`` and
``HIT_FRACTION`` of the speed before it, and where the ball (both lines carried to the
middle of the two windows, averaged) is further than ``CLEARANCE`` beyond its radius from
every solid (``estim.forward._balls.inside``): at a bounce, the ball touches one. The
windows next out (samples ``WINDOW`` to ``2 WINDOW`` away on either side) must see the
jump too: a tracker's glitch, a few bad samples in a row, jumps away and back, a hit stays;
a jump within ``2 WINDOW`` samples of either end of the track is not called a hit. Tracks
sampled below ``MIN_RATE`` are not searched (a window then spans most of a flight).
"""

from __future__ import annotations

import numpy as np

from ..forward._balls import inside
from ..model._scene import Scene

__all__ = ["HIT_SPEED", "HIT_FRACTION", "CLEARANCE", "WINDOW", "MIN_RATE", "hits", "longest_stretch"]

WINDOW = 6  # samples on each side of a candidate
HIT_SPEED = 1.5  # m/s: a jump no air force makes over two windows of frames
HIT_FRACTION = 0.3  # of the speed before the jump (a fast ball's drag over the windows stays below)
CLEARANCE = 0.03  # m beyond the radius: further from every solid than a bounce's contact
MIN_RATE = 60.0  # samples per second


def _jump(tt, pp, k: int, out: int, g: float):
    """At sample k, from straight lines through the ``WINDOW`` samples ``out`` windows away
    before it and after it (``out = 0``: adjacent): the velocity jump (m/s), whether it is
    one (above ``HIT_SPEED`` and ``HIT_FRACTION`` of the speed before), and where the ball
    is between the two windows (the two lines carried to the middle time, averaged)."""
    ends = []
    for lo in (k - (out + 1) * WINDOW, k + out * WINDOW):
        t, y = tt[lo:lo + WINDOW], pp[lo:lo + WINDOW]
        dt = t - t.mean()
        ends.append((dt @ (y - y.mean(axis=0)) / (dt @ dt), y.mean(axis=0), t.mean()))
    (va, ma, ta), (vb, mb, tb) = ends
    tc = 0.5 * (tt[k - 1] + tt[k])
    jump = float(np.linalg.norm(vb - va))
    speed = float(np.linalg.norm(va - np.array([0.0, 0.0, g * tc])))
    at = 0.5 * ((ma + va * (tc - ta)) + (mb + vb * (tc - tb))) - np.array([0.0, 0.0, 0.5 * g * tc**2])
    return jump, jump > max(HIT_SPEED, HIT_FRACTION * speed), tc, at


def hits(t, position, scene: Scene, radius: float, y_default: float = 0.0) -> list[tuple[int, float, float]]:
    """The hits of one track: ``(index of the first sample after it, time, speed jump m/s)``.

    Args:
        t: ``(n,)`` sample times (s), increasing.
        position: ``(n, 3)`` positions (m); rows without x or z are left out, a y that is
            NaN everywhere (a side view) is ``y_default`` (the ball's y in the scene).
        scene: its solids and gravity.
        radius: the ball's radius (m).
    """
    t = np.asarray(t, dtype=np.float64)
    p = np.array(position, dtype=np.float64)
    if np.all(np.isnan(p[:, 1])):
        p[:, 1] = y_default
    rows = np.flatnonzero(np.isfinite(t) & np.all(np.isfinite(p), axis=1))
    if rows.size < 2 * WINDOW + 1 or np.median(np.diff(t[rows])) > 1.0 / MIN_RATE:
        return []
    g = float(scene.gravity)
    tt, pp = t[rows], p[rows]
    pp[:, 2] += 0.5 * g * tt**2  # w: straight in a flight in vacuum
    jumps = [k for k in range(WINDOW, rows.size - WINDOW + 1) if _jump(tt, pp, k, 0, g)[1]]
    # The windows that straddle one jump all see it, most where they meet at it: each run's
    # largest is the jump, and there a bounce's ball touches its solid.
    runs = []
    for k in jumps:
        if runs and k - runs[-1][-1] <= WINDOW:
            runs[-1].append(k)
        else:
            runs.append([k])
    found = []
    for run in runs:
        k = max(run, key=lambda k: _jump(tt, pp, k, 0, g)[0])
        # Too close to an end of the track to tell a hit from a few bad samples; and the
        # windows next out must see the jump too: a burst of bad samples (a tracker's
        # glitch) jumps away and back, a hit stays.
        if k < 2 * WINDOW or k + 2 * WINDOW > rows.size or not _jump(tt, pp, k, 1, g)[1]:
            continue
        jump, _, tc, at = _jump(tt, pp, k, 0, g)
        in_box, in_plane = inside(np, scene, at[None], np.array([radius + CLEARANCE]))
        if not (in_box.any() or in_plane.any()):
            found.append((int(rows[k]), float(tc), jump))
    return found


def longest_stretch(n: int, found) -> tuple[int, int]:
    """``(start, stop)``: the longest run of the ``n`` samples between the hits ``found``
    (the earliest of equal ones)."""
    edges = [0] + [h[0] for h in found] + [n]
    lengths = np.diff(edges)
    k = int(np.argmax(lengths))
    return edges[k], edges[k + 1]
