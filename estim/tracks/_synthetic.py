"""Synthetic tracked data with known truth: exact simulation plus realistic tracker faults.

:func:`synthesize_tracks` simulates balls with :func:`estim.simulate` at the frame times of
a camera and degrades the exact positions the way a tracker does: Gaussian noise, dropped
frames (absent rows), a few gross outliers and some lost coordinates (NaN). Everything
comes from one ``numpy.random.Generator(seed)``, so a seed reproduces the data exactly.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..forward._simulate import simulate
from ..model._params import Params
from ..model._scene import Scene
from ._csv import Tracks

__all__ = ["SyntheticDetails", "synthesize_tracks", "frame_times"]


class SyntheticDetails(NamedTuple):
    """What was done to make the tracks (``synthesize_tracks(..., return_details=True)``).

    Per ball: ``exact`` (n, 3) noise-free positions at the kept frames, ``outlier`` (n,)
    bool rows replaced by gross outliers, ``lost`` (n, 3) bool coordinates set to NaN,
    ``dropped`` frame times that were removed; ``release`` (position, velocity) and ``params``
    (e, mu_t) used.
    """

    exact: dict
    outlier: dict
    lost: dict
    dropped: dict
    release: dict
    params: dict


def frame_times(t_end: float, frame_rate: float) -> np.ndarray:
    """Frame times ``k / frame_rate`` for k = 0, 1, ... up to ``t_end`` inclusive."""
    n = int(math.floor(t_end * frame_rate + 1e-9))
    return np.arange(n + 1) / frame_rate


def synthesize_tracks(
    scene: Scene,
    truth: dict[str, dict],
    *,
    t_end: float = 2.3,
    frame_rate: float = 60.0,
    noise: float = 0.002,
    drop_fraction: float = 0.05,
    n_outliers: int = 3,
    outlier_size: float = 0.05,
    lost_fraction: float = 0.01,
    with_y: bool = False,
    seed: int = 0,
    return_details: bool = False,
) -> Tracks | tuple[Tracks, SyntheticDetails]:
    """Simulated, degraded tracks of the scene's balls with known parameters.

    Args:
        scene: the scene (:func:`estim.load_scene`).
        truth: ``ball -> {"e", "mu_t", "vx0"}`` plus optionally ``"x0"``, ``"z0"``,
            ``"vz0"``; the release point defaults to the ball's position in the scene (for
            the stairs scene that is the seed release x0 = -0.20, z0 = 1.40 + r + 0.25),
            ``vz0`` to 0; y0 is always the scene's y of the ball, vy0 = 0. In a scene with
            air every ball has its mass from the scene, the default drag coefficient and
            no spin.
        t_end: duration (s); frames at ``k / frame_rate`` in ``[0, t_end]``.
        frame_rate: frames per second.
        noise: standard deviation (m) of the Gaussian noise on every coordinate.
        drop_fraction: fraction of frames removed per ball (absent rows).
        n_outliers: samples per ball replaced by gross outliers: the exact position moved
            by ``outlier_size`` metres (times a factor in [0.8, 1.2]) in a random direction
            of the observed coordinates.
        lost_fraction: fraction of the remaining observed coordinates set to NaN (lost
            detections).
        with_y: include the y coordinate (else y is all NaN, ``has_y`` False).
        seed: seed of ``numpy.random.Generator``.
        return_details: also return a :class:`SyntheticDetails`.

    Returns:
        :class:`Tracks` (or ``(Tracks, SyntheticDetails)``).
    """
    balls = tuple(truth)
    if not balls:
        raise ValueError("truth names no balls")
    for name in balls:
        for key in ("e", "mu_t", "vx0"):
            if key not in truth[name]:
                raise ValueError(f"truth[{name!r}] lacks {key!r}")
        extra = set(truth[name]) - {"e", "mu_t", "vx0", "x0", "z0", "vz0"}
        if extra:
            raise ValueError(f"truth[{name!r}] has unknown keys {sorted(extra)}")
    if not 0 <= drop_fraction < 1 or not 0 <= lost_fraction < 1:
        raise ValueError("drop_fraction and lost_fraction must lie in [0, 1)")
    specs = [scene.ball(b) for b in balls]
    pos0 = np.array([[truth[b].get("x0", s.position[0]), s.position[1],
                      truth[b].get("z0", s.position[2])] for b, s in zip(balls, specs, strict=True)])
    vel0 = np.array([[truth[b]["vx0"], 0.0, truth[b].get("vz0", 0.0)] for b in balls])
    e = np.array([truth[b]["e"] for b in balls], dtype=np.float64)
    mu = np.array([truth[b]["mu_t"] for b in balls], dtype=np.float64)
    r = np.array([s.radius for s in specs])
    ts = frame_times(t_end, frame_rate)
    # In air the drag and Magnus accelerations scale with 1 / mass: every ball's mass from
    # the scene (a vacuum needs none, and gets none, so that its program stays the same).
    mass = None if scene.air is None else np.array([s.mass for s in specs])
    params = Params(e, mu, r, pos0, vel0, mass=mass)
    traj = simulate(scene, params, float(t_end), ts=jnp.asarray(ts))
    exact_all = np.asarray(traj.position)  # (B, n, 3)

    rng = np.random.Generator(np.random.PCG64(seed))
    axes = [0, 1, 2] if with_y else [0, 2]
    t_out, p_out = {}, {}
    det = SyntheticDetails({}, {}, {}, {}, {}, {})
    for i, b in enumerate(balls):
        n = ts.size
        n_drop = int(round(drop_fraction * n))
        drop = np.zeros(n, dtype=bool)
        drop[rng.choice(n, size=n_drop, replace=False)] = True
        keep = ~drop
        t = ts[keep]
        exact = exact_all[i, keep].copy()
        obs = exact.copy()
        obs[:, axes] += rng.normal(0.0, noise, size=(t.size, len(axes)))
        outlier = np.zeros(t.size, dtype=bool)
        k_out = min(int(n_outliers), t.size)
        idx = rng.choice(t.size, size=k_out, replace=False)
        outlier[idx] = True
        for j in idx:
            d = rng.normal(size=len(axes))
            d /= np.linalg.norm(d)
            obs[j, axes] = exact[j, axes] + outlier_size * rng.uniform(0.8, 1.2) * d
        lost = np.zeros((t.size, 3), dtype=bool)
        candidates = [(j, a) for j in np.flatnonzero(~outlier) for a in axes]
        n_lost = int(round(lost_fraction * len(candidates)))
        for c in rng.choice(len(candidates), size=n_lost, replace=False):
            j, a = candidates[c]
            lost[j, a] = True
        obs[lost] = np.nan
        if not with_y:
            obs[:, 1] = np.nan
        t_out[b], p_out[b] = t, obs
        det.exact[b], det.outlier[b], det.lost[b] = exact, outlier, lost
        det.dropped[b] = ts[drop]
        det.release[b] = (pos0[i].copy(), vel0[i].copy())
        det.params[b] = {"e": float(e[i]), "mu_t": float(mu[i])}
    tracks = Tracks(
        source=f"synthetic(seed={seed}, noise={noise}, frame_rate={frame_rate})",
        balls=balls, t=t_out, position=p_out, has_y=with_y,
    )
    return (tracks, det) if return_details else tracks
