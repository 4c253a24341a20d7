"""Replay of fitted versus measured motion: MuJoCo offscreen frames, GIF and MP4.

The fitted model and the tracked data are shown together, frame by frame:

- the **fitted** balls are the scene's own ball bodies, placed at the model's positions by
  setting the ``qpos`` of their free joints and calling ``mujoco.mj_forward`` (kinematics
  only: MuJoCo's physics never runs, the motion is estim's exact solution);
- the **measured** sample of each ball at that frame is a translucent halo of the same
  colour (1.3 times the ball's radius, so it surrounds the solid ball where model and data
  agree and stands apart where they do not, at an outlier), and the samples of the last
  ``trail`` seconds are small translucent dots;
- a side camera looks along +y at the staircase, placed so that the solids and every
  position of the replay fit in the frame; a caption band under the picture gives the time
  and the fitted parameters.

MuJoCo renders offscreen through OpenGL. Without a display, ``import estim`` chooses EGL
(``MUJOCO_GL=egl``) unless ``MUJOCO_GL`` is set; where no OpenGL context can be made,
:class:`RenderError` says so, and ``estim.render_sideview`` draws the same content with
matplotlib instead.

Frames are written as a GIF with Pillow or as an MP4 through an ``ffmpeg`` found on PATH.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field

# MuJoCo picks its OpenGL backend when it is first imported; estim/__init__.py sets the
# same default before any estim module imports mujoco. Repeated here for code that imports
# this module on its own.
if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from ..fitting import _registry as registry  # noqa: E402
from ..forward._simulate import simulate  # noqa: E402
from ..model._scene import Scene, load_scene, scene_from_model  # noqa: E402
from ..tracks._camera import Camera, project  # noqa: E402
from ..tracks._csv import Tracks, read_tracks_csv  # noqa: E402
from ._plots import COLOURS  # noqa: E402

__all__ = [
    "EncoderNotFoundError",
    "RenderError",
    "ReplayInfo",
    "ReplayMotion",
    "CalibratedView",
    "SideCamera",
    "calibrated_model",
    "calibrated_view",
    "frame_times",
    "render_frames",
    "render_replay",
    "replay_motion",
    "side_camera",
    "write_gif",
    "write_mp4",
    "write_video",
]

# The halo of a measured sample, relative to the ball's radius, and its opacity; the trail
# dots. The halo is larger than the ball so that it stays visible where the fit is good.
GHOST_SCALE, GHOST_ALPHA = 1.3, 0.35
TRAIL_SCALE, TRAIL_ALPHA = 0.3, 0.6
# GIF stores frame durations in hundredths of a second, and viewers slow frames shorter
# than 20 ms down to 100 ms: 50 frames per second is the most a GIF can show.
GIF_MAX_FPS = 50.0
# What every fit.json gives a ball, whatever its scene's law: e and the release state.
REQUIRED = ("e", "vx0", "x0", "z0")


class RenderError(RuntimeError):
    """MuJoCo could not render offscreen (no OpenGL context); the message says why and
    what to do (``MUJOCO_GL``, or the matplotlib side view)."""


class EncoderNotFoundError(RuntimeError):
    """An MP4 was asked for, but no ``ffmpeg`` is on PATH."""


# --------------------------------------------------------------------------- the motion


@dataclass(frozen=True, eq=False)
class ReplayMotion:
    """What a replay shows, sampled at its frame times.

    Attributes:
        balls: the balls, in the order of the tracks.
        t: ``(frames,)`` frame times (s), on the data's clock.
        fps: frames per second.
        fitted: ``ball -> (frames, 3)`` the fitted model's centre positions (m).
        measured: ``ball -> (frames, 3)`` the measured sample nearest each frame time (within
            half a sampling interval of the data), NaN where there is none (a dropped
            frame); where the data has no y, the model's y.
        samples: ``ball -> (t (n,), position (n, 3))`` every measured sample (y filled as in
            ``measured``), for trails.
        params: ``ball -> {name: value}`` the values the model was replayed with: every
            parameter of the registry that acts in the scene (``estim.fitting._registry``;
            the fit's, else the default). Captions show e, mu_t, vx0 and the parameters the fit estimated besides
            (``free``) that the registry shows where fitted (vy0, the drag coefficient, the
            spin, ...); a ``params`` holding only some of them shows those.
        radius: ``ball -> radius`` (m) from the scene.
        free: ``ball -> names`` of the parameters the fit estimated (empty: not known).
    """

    balls: tuple[str, ...]
    t: np.ndarray
    fps: float
    fitted: dict[str, np.ndarray]
    measured: dict[str, np.ndarray]
    samples: dict[str, tuple[np.ndarray, np.ndarray]]
    params: dict[str, dict[str, float]]
    radius: dict[str, float]
    free: dict[str, tuple[str, ...]] = field(default_factory=dict)

    def caption(self, ball: str, *, sep: str = "   ") -> str:
        """``"e = 0.580   mu_t = 0.950   vx0 = 0.500 m/s"``: the parameters a caption shows
        for ``ball`` (``estim.fitting._registry.describe``)."""
        return registry.describe(self.params[ball], self.free.get(ball, ()), sep=sep)

    @property
    def n_frames(self) -> int:
        return int(self.t.shape[0])


def frame_times(t_start: float, t_end: float, fps: float) -> np.ndarray:
    """Frame times ``t_start + k / fps`` for ``k = 0 .. floor((t_end - t_start) fps)``: a
    frame every ``1 / fps`` seconds over the span, none after its end."""
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    span = float(t_end) - float(t_start)
    if not (math.isfinite(span) and span >= 0):
        raise ValueError(f"the time span [{t_start}, {t_end}] is empty or not finite")
    # The small tolerance keeps a span that is a whole number of frames (2.2 s at 25 fps)
    # from losing its last frame to rounding.
    n = math.floor(span * fps + 1e-9) + 1
    return float(t_start) + np.arange(n) / float(fps)


def _read_fit(fit) -> dict[str, tuple[dict, tuple[str, ...]]]:
    """``ball -> (values, fitted names)`` from a fit.json path, its parsed object, or a
    FitResult. The values are the registry's parameters that the fit gives (fit.json
    holds them under their names, beside its statistics); every fit gives at least
    ``REQUIRED`` (e, vx0, x0, z0), the replay takes the others' defaults."""
    if hasattr(fit, "balls") and not isinstance(fit, Mapping):  # a FitResult
        return {b: ({k: v for k, v in bf.values.items() if k in registry.NAMES}, tuple(bf.names))
                for b, bf in fit.balls.items()}
    if isinstance(fit, (str, os.PathLike)):
        path = os.fspath(fit)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"fit file not found: {path}")
        try:
            with open(path) as f:
                fit = json.load(f)
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}: not a JSON file ({err})") from None
        where = path
    else:
        where = "fit"
    if not isinstance(fit, Mapping) or not isinstance(fit.get("balls"), Mapping):
        raise ValueError(f"{where}: expected an object with 'balls' (as `estim fit` writes)")
    out = {}
    for ball, values in fit["balls"].items():
        if not isinstance(values, Mapping):
            raise ValueError(f"{where}: ball {ball!r} is not an object of parameter values")
        missing = [k for k in REQUIRED if not _is_number(values.get(k))]
        if missing:
            raise ValueError(f"{where}: ball {ball!r} has no numeric {missing}")
        bad = [k for k in registry.NAMES if k in values and not _is_number(values[k])]
        if bad:
            raise ValueError(f"{where}: ball {ball!r}: {bad} must be numbers, got "
                             f"{[values[k] for k in bad]}")
        corr = values.get("correlation")
        names = corr.get("names", ()) if isinstance(corr, Mapping) else ()
        out[ball] = ({k: float(values[k]) for k in registry.NAMES if k in values},
                     tuple(n for n in names if n in registry.NAMES))
    return out


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _read_tracks(tracks, scene: Scene) -> dict[str, tuple[np.ndarray, np.ndarray]]:

    if isinstance(tracks, (str, os.PathLike)):
        tracks = read_tracks_csv(tracks, scene=scene)
    if isinstance(tracks, Tracks):
        return {b: (tracks.t[b], tracks.position[b]) for b in tracks.balls}
    return {b: (np.asarray(t, np.float64), np.asarray(p, np.float64)) for b, (t, p) in tracks.items()}


def replay_motion(scene: Scene | str | os.PathLike, fit, tracks, *, fps: float = 25.0) -> ReplayMotion:
    """The fitted and measured motion of every tracked ball at the replay's frame times.

    Args:
        scene: the scene (or its MJCF path) the fit was made in.
        fit: a fit.json path, its parsed object (``{"balls": {name: {"e", "mu_t", "vx0",
            "x0", "z0", ...}}}``), or an :class:`estim.FitResult`. Every parameter of the
            registry (``estim.fitting._registry``) that it gives is used: the release state
            in 3D, the release time ``t0`` on the data's clock, and in a scene with air the
            drag coefficient and the spin; the others take their defaults (``y0`` the
            ball's y in the scene, ``vy0 = vz0 = t0 = 0``, C_D = 0.47, no spin).
        tracks: a tracks CSV path, an :class:`estim.Tracks`, or ``ball -> (t, position)``.
        fps: frames per second; frames run over the data's time span (:func:`frame_times`).

    Raises:
        ValueError: a tracked ball has no fit, or is not in the scene; bad fit values
            (not numbers, out of range, a spin in a scene without air).
    """
    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    values = _read_fit(fit)
    data = _read_tracks(tracks, scene)
    if not data:
        raise ValueError("the tracks hold no balls")
    unfitted = [b for b in data if b not in values]
    if unfitted:
        raise ValueError(f"the fit has no result for tracked ball(s) {unfitted}; it has {sorted(values)}")
    for b in data:
        scene.ball(b)  # KeyError naming the scene's balls
    t_all = np.concatenate([data[b][0] for b in data])
    ts = frame_times(float(np.min(t_all)), float(np.max(t_all)), fps)

    fitted, measured, samples, params, radius, free = {}, {}, {}, {}, {}, {}
    acting = registry.acting(scene)
    for b, (t, pos) in data.items():
        spec = scene.ball(b)
        v = registry.values_for(spec, values[b][0])
        t0 = v["t0"]
        # Before its release time the ball waits at the release point, as in the fit.
        t_end = max(float(ts[-1]) - t0, 1e-3)
        fitted[b] = _fitted_positions(scene, spec, v, t_end, np.clip(ts - t0, 0.0, t_end))

        t, pos = np.asarray(t, np.float64), np.asarray(pos, np.float64).copy()
        # 2-D tracks: put the samples at the model's depth, so halo and ball line up.
        y_model = np.interp(t, ts, fitted[b][:, 1])
        pos[:, 1] = np.where(np.isfinite(pos[:, 1]), pos[:, 1], y_model)
        ok = np.all(np.isfinite(pos), axis=1)
        samples[b] = (t[ok], pos[ok])
        measured[b] = _nearest_samples(t, pos, ts)
        params[b] = {k: x for k, x in v.items() if k in acting}
        free[b] = values[b][1]
        radius[b] = float(spec.radius)
    return ReplayMotion(tuple(data), ts, float(fps), fitted, measured, samples, params, radius, free)


def _fitted_positions(scene: Scene, spec, values, t_end, ts) -> np.ndarray:
    """The model's positions of one ball at times ``ts``, for the registry's ``values``.

    One unbatched ``simulate`` with the default sample times, then the dense solution at
    ``ts``: a new batch or sample shape would compile the whole solver again (tens of
    seconds on a loaded machine), while this call shares its compiled program with
    ``estim simulate`` and JAX's persistent cache; only the small sampling program is
    compiled per bucket of 64 frames.
    """
    # The mass only matters in air; leaving it out otherwise keeps the pytree (and so the
    # compiled program) that of a plain single-ball simulation.
    air = getattr(scene, "air", None) is not None
    idle = [n for n in registry.NAMES if registry.component(n).zero_where_idle and values[n] != 0
            and not registry.component(n).acts(scene)]
    if idle:
        raise ValueError(f"ball {spec.name!r}: the fit gives {', '.join(f'{n} = {values[n]:g}' for n in idle)}, "
                         f"which acts only {registry.component(idle[0]).acts_where}: replay it in the scene "
                         "it was fitted in")
    p = registry.to_params(values, radius=spec.radius, mass=spec.mass if air else None, inertia=spec.inertia,
                           scene=scene)
    traj = simulate(scene, p, t_end)
    n = ts.shape[0]
    padded = np.concatenate([ts, np.full(-n % 64, ts[-1])])
    pos, _ = _evaluate(traj, padded)
    return np.asarray(pos, dtype=np.float64)[:n]


def _evaluate(traj, t):
    global _EVALUATE
    if _EVALUATE is None:
        import equinox as eqx

        _EVALUATE = eqx.filter_jit(lambda traj, t: traj.evaluate(t))
    return _EVALUATE(traj, t)


_EVALUATE = None


def _nearest_samples(t: np.ndarray, pos: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """The sample nearest each frame time if within half the data's sampling interval
    (a dropped frame gives NaN, not a stale sample), else NaN."""
    out = np.full((ts.shape[0], 3), np.nan)
    if t.size == 0:
        return out
    dt = float(np.median(np.diff(t))) if t.size > 1 else math.inf
    k = np.clip(np.searchsorted(t, ts), 1, max(t.size - 1, 1))
    k = np.where((k > 0) & (np.abs(ts - t[k - 1]) <= np.abs(t[np.minimum(k, t.size - 1)] - ts)), k - 1, k)
    k = np.clip(k, 0, t.size - 1)
    near = np.abs(t[k] - ts) <= 0.5 * dt + 1e-9
    out[near] = pos[k[near]]
    out[~np.all(np.isfinite(out), axis=1)] = np.nan
    return out


# --------------------------------------------------------------------------- the camera


@dataclass(frozen=True)
class SideCamera:
    """A MuJoCo free camera: ``lookat`` point (m), ``distance`` (m), ``azimuth`` and
    ``elevation`` (degrees; azimuth 90 looks along +y), vertical field of view ``fovy``
    (degrees; a free camera takes it from the model's ``visual/global/fovy``, which
    :func:`render_frames` sets to this value in its copy of the model)."""

    lookat: tuple[float, float, float]
    distance: float
    azimuth: float = 90.0
    elevation: float = -15.0
    fovy: float = 45.0

    def to_mjv(self) -> mujoco.MjvCamera:
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = self.lookat
        cam.distance = self.distance
        cam.azimuth = self.azimuth
        cam.elevation = self.elevation
        return cam

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Eye position, forward, up and right unit vectors (MuJoCo's free camera)."""
        az, el = math.radians(self.azimuth), math.radians(self.elevation)
        forward = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        up = np.array([-math.sin(el) * math.cos(az), -math.sin(el) * math.sin(az), math.cos(el)])
        eye = np.asarray(self.lookat, np.float64) - self.distance * forward
        return eye, forward, up, np.cross(forward, up)

    def project(self, points, width: int, height: int) -> np.ndarray:
        """Pixel coordinates ``(..., 2)`` = (column, row from the top) of world points
        ``(..., 3)`` in a ``width`` x ``height`` image; pixel (i, j) covers [i, i+1) x
        [j, j+1). Points behind the camera give NaN."""
        eye, forward, up, right = self.frame()
        rel = np.asarray(points, np.float64) - eye
        depth = rel @ forward
        depth = np.where(depth > 0, depth, np.nan)
        tan = math.tan(math.radians(self.fovy) / 2)
        col = 0.5 * width * (1 + (rel @ right) / (depth * tan * width / height))
        row = 0.5 * height * (1 - (rel @ up) / (depth * tan))
        return np.stack([col, row], axis=-1)


def _solid_corners(model) -> np.ndarray:
    """Corners of the model's static boxes (planes are unbounded and left out)."""
    corners = []
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    for g in range(model.ngeom):
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX and model.body_dofnum[model.geom_bodyid[g]] == 0:
            rot = data.geom_xmat[g].reshape(3, 3)
            corners.append(data.geom_xpos[g] + (signs * model.geom_size[g]) @ rot.T)
    return np.concatenate(corners) if corners else np.zeros((0, 3))


def side_camera(model, motion: ReplayMotion | None, width: int, height: int, *,
                elevation: float = -15.0, fovy: float = 30.0, margin: float = 0.04) -> SideCamera:
    """A camera looking along +y (from -y) that frames the scene's boxes and every position
    of ``motion`` (balls and halos with their radii), with ``margin`` (a fraction of the
    image) to spare: the nearest distance at which everything fits, by bisection.

    ``fovy`` (degrees) is narrower than MuJoCo's default 45, so the camera stands further
    back and the fronts of the treads do not crowd out their tops; :func:`render_frames`
    renders with the camera's ``fovy``."""
    model = _as_model(model)
    pts = [_solid_corners(model)]
    if motion is not None:
        for b in motion.balls:
            r = GHOST_SCALE * motion.radius[b]
            for p in (motion.fitted[b], motion.samples[b][1]):
                p = p[np.all(np.isfinite(p), axis=1)]
                pts += [p + d for d in ((r, 0, 0), (-r, 0, 0), (0, 0, r), (0, 0, -r))]
    pts = np.concatenate(pts)
    if pts.size == 0:
        raise ValueError("nothing to frame: the model has no boxes and there is no motion")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    lookat = tuple(float(v) for v in 0.5 * (lo + hi))

    def fits(d):
        px = SideCamera(lookat, d, 90.0, elevation, fovy).project(pts, width, height)
        if not np.all(np.isfinite(px)):
            return False
        return bool(np.all((px[:, 0] >= margin * width) & (px[:, 0] <= (1 - margin) * width)
                           & (px[:, 1] >= margin * height) & (px[:, 1] <= (1 - margin) * height)))

    near, far = 1e-3, 10.0 * (float(np.max(hi - lo)) + 1.0)
    while not fits(far):
        far *= 2.0
    for _ in range(60):
        mid = 0.5 * (near + far)
        near, far = (near, mid) if fits(mid) else (mid, far)
    return SideCamera(lookat, far, 90.0, elevation, fovy)


@dataclass(frozen=True)
class CalibratedView:
    """The viewpoint of a calibrated camera (``estim.tracks._camera.Camera``).

    MuJoCo renders a pinhole camera only: square pixels, the principal point at the image
    centre, no lens distortion. A calibrated camera may have none of these, so the view
    renders a wider pinhole picture from the camera's pose and resamples it into the
    camera's own picture. The pinhole is the camera ``estim_view`` that
    :func:`calibrated_model` adds to the scene's MJCF: placed at the camera's centre, its
    axes OpenCV's turned half a turn about x (MuJoCo's camera looks along its -z with y up),
    its vertical field of view ``fovy`` (degrees) and its width ``aspect`` times its height
    wide enough for the ray of every pixel of the camera's image. Each pixel of the picture
    then takes, by bilinear interpolation, the rendered colour along its own ray: its
    undistorted normalised coordinates ``(x', y')`` (``Camera.normalised``, OpenCV's
    ``undistortPoints``) land at ``f (x', y') + c`` in the pinhole picture of focal length
    ``f`` and centre ``c``. That is exact for a pinhole (the camera's projection of a point
    and the pinhole's are the same ray) up to the interpolation. A pixel where the
    distortion model has no inverse (the fixed-point undistortion does not give a point that
    projects back onto the pixel, beyond a strong distortion's fold) or whose ray lies
    beyond :data:`WIDEST` of the axis is left black rather than drawn wrong."""

    camera: Camera
    fovy: float
    aspect: float

    def to_mjv(self) -> mujoco.MjvCamera:
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        cam.fixedcamid = -1  # set by render_frames from the model's camera "estim_view"
        return cam

    def rays(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """The undistorted normalised coordinates ``(height, width, 2)`` of the pixel
        centres of the camera's picture drawn ``width`` x ``height`` pixels (its image
        scaled), and where they are valid ``(height, width)``: the projection of the
        undistorted point is back within :data:`ROUND_TRIP` pixels of the image's pixel."""
        w, h = self.camera.size
        # The centre of pixel (i, j) of the picture, in pixels of the camera's image.
        u = (np.arange(width) + 0.5) * (w / width) - 0.5
        v = (np.arange(height) + 0.5) * (h / height) - 0.5
        return _undistorted(self.camera, np.stack(np.meshgrid(u, v), axis=-1))


VIEW_CAMERA = "estim_view"
# The widest ray a calibrated view renders: tan of its angle from the optical axis, per
# image axis (80 degrees). Beyond, a pinhole picture would need an unbounded size.
WIDEST = math.tan(math.radians(80.0))
# A pixel whose undistorted ray projects back further than this (pixels) is not drawn.
ROUND_TRIP = 0.01


def _undistorted(camera: Camera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``camera.normalised(uv)`` and where it inverts the projection (``ROUND_TRIP``)."""
    xy = camera.normalised(uv)
    pinhole = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
    back = np.asarray(project(camera.matrix, camera.distortion, np.eye(3), np.zeros(3), pinhole))
    ok = np.all(np.isfinite(xy), axis=-1) & (np.linalg.norm(back - uv, axis=-1) <= ROUND_TRIP)
    return xy, ok & np.all(np.abs(xy) <= WIDEST, axis=-1)


def calibrated_view(camera: Camera) -> CalibratedView:
    """The :class:`CalibratedView` of a camera with a known image size: the pinhole's field
    of view from the undistorted rays through the image's border and a grid inside it.

    Raises:
        ValueError: no image size, or no pixel whose ray the distortion model gives."""
    if camera.size is None:
        raise ValueError(f"camera {camera.name!r}: a replay from its viewpoint needs its image size "
                         "(image_width, image_height or w, h in its file)")
    w, h = camera.size
    # Every pixel of the border (where a radial distortion reaches furthest) and a grid.
    edge_u, edge_v = np.arange(-0.5, w, 1.0), np.arange(-0.5, h, 1.0)
    grid = np.stack(np.meshgrid(np.linspace(-0.5, w - 0.5, 33), np.linspace(-0.5, h - 0.5, 33)), -1)
    uv = np.concatenate([np.stack([edge_u, np.full_like(edge_u, -0.5)], -1),
                         np.stack([edge_u, np.full_like(edge_u, h - 0.5)], -1),
                         np.stack([np.full_like(edge_v, -0.5), edge_v], -1),
                         np.stack([np.full_like(edge_v, w - 0.5), edge_v], -1), grid.reshape(-1, 2)])
    xy, ok = _undistorted(camera, uv)
    if not np.any(ok):
        raise ValueError(f"camera {camera.name!r}: its distortion model gives the ray of none of its pixels")
    # A pixel's margin on every side, for the bilinear interpolation at the border.
    tx, ty = (float(np.max(np.abs(xy[ok, i]))) * 1.01 for i in range(2))
    tx, ty = max(tx, 1e-3), max(ty, 1e-3)
    return CalibratedView(camera, math.degrees(2.0 * math.atan(ty)), tx / ty)


def calibrated_model(scene_path, view: CalibratedView) -> mujoco.MjModel:
    """The scene's MJCF with the camera ``estim_view`` of ``view`` added to its world."""
    spec = mujoco.MjSpec.from_file(os.fspath(scene_path))
    R = np.asarray(view.camera.rotation)
    cam = spec.worldbody.add_camera(name=VIEW_CAMERA, pos=view.camera.centre.tolist(), fovy=view.fovy)
    # MuJoCo's camera frame: x right, y up, looking along -z; OpenCV's rows of R are x
    # right, y down, z forward, so MuJoCo's axes in the world are R[0], -R[1], -R[2].
    frame = np.stack([R[0], -R[1], -R[2]], axis=1)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, frame.reshape(-1))
    cam.quat = quat
    return spec.compile()


class _Resample:
    """The pinhole picture that :class:`CalibratedView` renders (``size``: width, height)
    and its bilinear resampling into the camera's picture of ``width`` x ``height``."""

    def __init__(self, view: CalibratedView, width: int, height: int):
        xy, ok = view.rays(width, height)
        # As fine as the camera's picture at its centre: the picture's focal length in
        # its own pixels, fy scaled, and no more than four times the picture's size.
        focal = float(view.camera.matrix[1, 1]) * height / view.camera.size[1]
        tan = math.tan(math.radians(view.fovy) / 2)
        rows = min(max(2, math.ceil(2 * focal * tan)), 4 * max(width, height))
        cols = min(max(2, math.ceil(rows * view.aspect)), 4 * max(width, height))
        self.size = (cols, rows)
        # MuJoCo's pinhole: the vertical field of view spans the rows, square pixels, the
        # principal point at the centre; OpenCV's pixel centres are integers.
        f = rows / (2 * tan)
        c = f * xy[..., 0] + (cols - 1) / 2
        r = f * xy[..., 1] + (rows - 1) / 2
        ok &= (c >= 0) & (c <= cols - 1) & (r >= 0) & (r <= rows - 1)
        c, r = np.where(ok, c, 0.0), np.where(ok, r, 0.0)
        c0 = np.minimum(np.floor(c).astype(np.intp), cols - 2)
        r0 = np.minimum(np.floor(r).astype(np.intp), rows - 2)
        fc, fr = (c - c0)[..., None], (r - r0)[..., None]
        self.index = (r0, c0)
        self.weights = [(1 - fr) * (1 - fc) * ok[..., None], (1 - fr) * fc * ok[..., None],
                        fr * (1 - fc) * ok[..., None], fr * fc * ok[..., None]]

    def __call__(self, img: np.ndarray) -> np.ndarray:
        r0, c0 = self.index
        img = img.astype(np.float32)
        out = (self.weights[0] * img[r0, c0] + self.weights[1] * img[r0, c0 + 1]
               + self.weights[2] * img[r0 + 1, c0] + self.weights[3] * img[r0 + 1, c0 + 1])
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- rendering


def _as_model(model) -> mujoco.MjModel:
    if isinstance(model, mujoco.MjModel):
        return model
    path = os.fspath(model)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"scene file not found: {path}")
    return mujoco.MjModel.from_xml_path(path)


def _estim_scene(scene, model: mujoco.MjModel) -> Scene:
    """estim's scene for an MJCF path or a compiled model (the file MuJoCo renders)."""

    if isinstance(scene, (str, os.PathLike)):
        return load_scene(scene)
    return scene_from_model(model)


def _rgb(colour) -> np.ndarray:
    from matplotlib.colors import to_rgb

    return np.asarray(to_rgb(colour), np.float64)


def ball_colours(model, balls: Iterable[str]) -> dict[str, np.ndarray]:
    """RGB in [0, 1] per ball: the plots' colours (``estim.show._plots.COLOURS``), else the
    scene's rgba of the ball's geom, so the replay, the side view and the plots agree."""

    model = _as_model(model)
    out = {}
    for b in balls:
        if b in COLOURS:
            out[b] = _rgb(COLOURS[b])
        else:
            body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b)
            geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body]
            out[b] = np.asarray(model.geom_rgba[geoms[0], :3], np.float64) if geoms else _rgb("C0")
    return out


def _prepare(model, balls, width, height, colours):
    """A copy of the model set up for the replay: offscreen buffer large enough, a cheaper
    shadow map, the balls in their replay colours, other free balls hidden; and the qpos
    address of each ball's free joint."""
    model = _as_model(model)
    model = model.__copy__()
    # The offscreen framebuffer must hold the image; the scene file's size is a default.
    model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
    model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
    # A 4096^2 shadow map costs most of a software-rendered frame; 1024^2 looks the same
    # at replay sizes.
    model.vis.quality.shadowsize = min(int(model.vis.quality.shadowsize), 1024)
    adr, shown = {}, set()
    for j in range(model.njnt):
        if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
            continue
        body = int(model.jnt_bodyid[j])
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body)
        geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body]
        if name in balls:
            adr[name] = int(model.jnt_qposadr[j])
            shown.add(name)
            for g in geoms:
                model.geom_rgba[g, :3] = colours[name]
                model.geom_rgba[g, 3] = 1.0
        else:
            # A ball of the scene that is not replayed would sit at its release point.
            model.geom_rgba[geoms, 3] = 0.0
    missing = [b for b in balls if b not in shown]
    if missing:
        raise ValueError(f"ball(s) {missing} are not free bodies of the MuJoCo model")
    return model, adr


def _add_sphere(scn: mujoco.MjvScene, pos, radius: float, rgba) -> None:
    if scn.ngeom >= scn.maxgeom:
        return
    geom = scn.geoms[scn.ngeom]
    mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_SPHERE, np.array([radius, 0.0, 0.0]),
                        np.asarray(pos, np.float64), np.eye(3).ravel(),
                        np.asarray(rgba, np.float32))
    geom.category = mujoco.mjtCatBit.mjCAT_DECOR
    scn.ngeom += 1


def render_frames(model, motion: ReplayMotion, *, width: int = 640, height: int = 360,
                  camera: SideCamera | CalibratedView | None = None, ghosts: bool = True, trail: float = 0.3,
                  caption: bool = True, colours: Mapping | None = None) -> Iterator[np.ndarray]:
    """MuJoCo frames of a replay: ``(height [+ caption], width, 3)`` uint8 RGB arrays.

    Each frame places the fitted balls (free-joint ``qpos``, then ``mj_forward``) and adds
    the measured halos and trail dots to the visual scene. ``model`` is the scene's MJCF
    path or a ``mujoco.MjModel`` (not modified). ``camera`` defaults to
    :func:`side_camera`; a :class:`CalibratedView` renders through the model's camera
    ``estim_view`` (:func:`calibrated_model`). With ``caption``, a band under the picture gives the time and the
    fitted parameters; the picture itself is the first ``height`` rows either way.
    ``colours`` maps balls to colours (any matplotlib colour) in place of
    :func:`ball_colours`.

    Raises:
        RenderError: MuJoCo cannot make an offscreen OpenGL context here.
    """
    width, height = int(width), int(height)
    chosen = ball_colours(model, motion.balls)
    chosen.update({b: _rgb(c) for b, c in (colours or {}).items() if b in chosen})
    colours = chosen
    resample = _Resample(camera, width, height) if isinstance(camera, CalibratedView) else None
    size = resample.size if resample is not None else (width, height)
    model, adr = _prepare(model, motion.balls, *size, colours)
    camera = camera or side_camera(model, motion, width, height)
    model.vis.global_.fovy = camera.fovy  # a free camera's field of view is the model's
    data = mujoco.MjData(model)
    try:
        renderer = mujoco.Renderer(model, size[1], size[0])
    except Exception as err:
        raise RenderError(
            f"MuJoCo could not render offscreen (MUJOCO_GL={os.environ.get('MUJOCO_GL', '')!r}): "
            f"{err}. Set MUJOCO_GL=egl (or osmesa) where a GPU driver or Mesa is installed, "
            "or use the matplotlib side view (estim.render_sideview, `estim replay --view side`)"
        ) from err
    cam = camera.to_mjv()
    if isinstance(camera, CalibratedView):
        cam.fixedcamid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, VIEW_CAMERA)
        if cam.fixedcamid < 0:
            raise ValueError(f"a calibrated view needs the model's camera {VIEW_CAMERA!r} (calibrated_model)")
    band = _CaptionBand(motion, colours, width) if caption else None
    try:
        for k, t in enumerate(motion.t):
            for b in motion.balls:
                a = adr[b]
                data.qpos[a:a + 3] = motion.fitted[b][k]
                data.qpos[a + 3:a + 7] = (1.0, 0.0, 0.0, 0.0)
            mujoco.mj_forward(model, data)  # positions only; no physics step is taken
            renderer.update_scene(data, camera=cam)
            scn = renderer.scene
            # The ground's faint mirror image doubles the cost of a software-rendered frame.
            scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
            if ghosts:
                for b in motion.balls:
                    r, c = motion.radius[b], colours[b]
                    if trail > 0:
                        st, sp = motion.samples[b]
                        for p in sp[(st > t - trail) & (st <= t)]:
                            _add_sphere(scn, p, TRAIL_SCALE * r, (*c, TRAIL_ALPHA))
                    m = motion.measured[b][k]
                    if np.all(np.isfinite(m)):
                        _add_sphere(scn, m, GHOST_SCALE * r, (*c, GHOST_ALPHA))
            img = renderer.render()
            img = resample(img) if resample is not None else img
            yield band.under(img, k) if band is not None else img.copy()
    finally:
        renderer.close()


class _CaptionBand:
    """Time and fitted parameters, one line per ball in its colour, under the picture."""

    def __init__(self, motion: ReplayMotion, colours, width: int):
        from PIL import ImageFont

        self.motion, self.colours, self.width = motion, colours, width
        self.size = max(10, round(width / 46))
        try:
            self.font = ImageFont.load_default(size=self.size)
        except TypeError:  # Pillow < 10.1 has one bitmap font size
            self.font = ImageFont.load_default()
        self.line = round(1.45 * self.size)
        self.height = self.line * (1 + len(motion.balls)) + self.size // 2

    def under(self, img: np.ndarray, k: int) -> np.ndarray:
        from PIL import Image, ImageDraw

        band = Image.new("RGB", (self.width, self.height), (24, 24, 24))
        draw = ImageDraw.Draw(band)
        pad = self.size // 2
        m = self.motion
        draw.text((pad, pad // 2), f"t = {m.t[k]:6.3f} s", fill=(235, 235, 235), font=self.font)
        legend = "solid: fitted model   halo: measured sample   dots: recent samples"
        draw.text((self.width - pad, pad // 2), legend, fill=(170, 170, 170), font=self.font, anchor="ra")
        for i, b in enumerate(m.balls):
            y = pad // 2 + self.line * (i + 1)
            c = tuple(int(round(255 * v)) for v in self.colours[b])
            s = self.size
            draw.ellipse((pad, y + s * 0.15, pad + 0.8 * s, y + 0.95 * s), fill=c)
            text = f"{b:<9} {m.caption(b)}"
            draw.text((pad + 1.3 * s, y), text, fill=(235, 235, 235), font=self.font)
        return np.concatenate([img, np.asarray(band)], axis=0)


# --------------------------------------------------------------------------- writing


def _durations_ms(n: int, fps: float) -> list[int]:
    """Per-frame GIF durations in ms (multiples of 10, GIF's unit) whose running sums stay
    within 5 ms of k / fps: 30 fps alternates 30 and 40 ms instead of drifting at 30."""
    ends = np.round(np.arange(1, n + 1) * 100.0 / fps).astype(int) * 10
    return np.diff(np.concatenate([[0], ends])).tolist()


def _gif_palette(images, colours):
    """One 256-colour palette for every frame, from a sample of the frames plus shades of
    the key ``colours``: a small ball covers few pixels, and a palette made per frame
    would merge its colour into the background's."""
    from PIL import Image

    sample = [np.asarray(im) for im in images[:: max(1, len(images) // 8)]]
    h, w = sample[0].shape[:2]
    for c in colours:
        shades = np.clip(np.linspace(0.3, 1.2, 16)[:, None] * np.asarray(c, np.float64) * 255, 0, 255)
        block = np.repeat(shades.astype(np.uint8), -(-w // 16), axis=0)[:w]
        sample.append(np.broadcast_to(block[None], (max(h // 6, 1), w, 3)))
    return Image.fromarray(np.concatenate(sample, axis=0)).quantize(256, method=Image.Quantize.MEDIANCUT)


def write_gif(frames: Iterable[np.ndarray], path, fps: float, *, colours=()) -> int:
    """Write RGB frames as a looping GIF (Pillow) at ``fps``; returns the number of frames.

    GIF durations are hundredths of a second, so a frame rate that does not divide 100
    gets alternating durations with the right average (see ``_durations_ms``). All frames
    share one palette, which keeps shades of the key ``colours`` (RGB in [0, 1], the
    balls'). Pillow merges identical consecutive frames into one (their durations add);
    replay frames carry their time, so they never are identical.
    """
    from PIL import Image

    if not (math.isfinite(fps) and 0 < fps <= GIF_MAX_FPS):
        raise ValueError(f"a GIF can show 0 < fps <= {GIF_MAX_FPS:g} frames per second, got {fps!r}")
    images = [Image.fromarray(np.asarray(f, np.uint8)[..., :3]) for f in frames]
    if not images:
        raise ValueError("no frames to write")
    palette = _gif_palette(images, colours)
    images = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in images]
    durations = _durations_ms(len(images), fps)
    images[0].save(os.fspath(path), save_all=True, append_images=images[1:],
                   duration=durations if len(images) > 1 else durations[0], loop=0)
    return len(images)


def write_mp4(frames: Iterable[np.ndarray], path, fps: float) -> int:
    """Write RGB frames as an H.264 MP4 through ``ffmpeg`` (which must be on PATH); returns
    the number of frames. Odd image sizes are padded by a pixel (H.264 needs even ones).

    Raises:
        EncoderNotFoundError: no ``ffmpeg`` on PATH (checked before anything is rendered).
    """
    ffmpeg = shutil.which("ffmpeg")
    if ffmpeg is None:
        raise EncoderNotFoundError(
            f"cannot write {os.fspath(path)}: MP4 needs ffmpeg, and no ffmpeg was found on PATH; "
            "install ffmpeg, or write a .gif"
        )
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    it = iter(frames)
    first = next(it, None)
    if first is None:
        raise ValueError("no frames to write")
    h, w = first.shape[:2]
    cmd = [ffmpeg, "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
           "-s", f"{w}x{h}", "-r", f"{fps:g}", "-i", "-",
           "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-c:v", "libx264", "-pix_fmt", "yuv420p",
           os.fspath(path)]
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stderr=subprocess.PIPE)
    n = 0
    try:
        for f in _chain(first, it):
            f = np.ascontiguousarray(f, np.uint8)
            if f.shape[:2] != (h, w):
                raise ValueError(f"frame {n} is {f.shape[1]}x{f.shape[0]}, the first was {w}x{h}")
            proc.stdin.write(f[..., :3].tobytes())
            n += 1
    finally:
        proc.stdin.close()
        err = proc.stderr.read().decode(errors="replace")
        code = proc.wait()
    if code != 0:
        raise RuntimeError(f"ffmpeg failed (exit code {code}) writing {os.fspath(path)}: {err.strip()}")
    return n


def _chain(first, rest):
    yield first
    yield from rest


def write_video(frames: Iterable[np.ndarray], path, fps: float, *, colours=()) -> int:
    """:func:`write_gif` (keeping ``colours``) or :func:`write_mp4`, by the file's suffix."""
    suffix = os.path.splitext(os.fspath(path))[1].lower()
    if suffix == ".gif":
        return write_gif(frames, path, fps, colours=colours)
    if suffix == ".mp4":
        return write_mp4(frames, path, fps)
    raise ValueError(f"{os.fspath(path)}: the output must end in .gif or .mp4")


def check_output(path, fps: float) -> None:
    """Fail fast, before any rendering: the suffix, the frame rate, the encoder."""
    suffix = os.path.splitext(os.fspath(path))[1].lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"{os.fspath(path)}: the output must end in .gif or .mp4")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    if suffix == ".gif" and fps > GIF_MAX_FPS:
        raise ValueError(f"a GIF can show at most {GIF_MAX_FPS:g} frames per second, got {fps:g}")
    if suffix == ".mp4" and shutil.which("ffmpeg") is None:
        raise EncoderNotFoundError(
            f"cannot write {os.fspath(path)}: MP4 needs ffmpeg, and no ffmpeg was found on PATH; "
            "install ffmpeg, or write a .gif"
        )


@dataclass(frozen=True)
class ReplayInfo:
    """What a replay wrote: ``path``, ``n_frames`` at ``fps`` over ``[t_start, t_end]`` (s)
    on the data's clock, the ``balls``, and the ``renderer`` ("mujoco" or "matplotlib")."""

    path: str
    n_frames: int
    fps: float
    t_start: float
    t_end: float
    balls: tuple[str, ...]
    renderer: str


def render_replay(scene, fit, tracks, out, *, fps: float = 25.0, width: int = 640,
                  height: int = 360, camera: SideCamera | Camera | None = None,
                  trail: float = 0.3) -> ReplayInfo:
    """Render the fitted model against the measured tracks with MuJoCo and write ``out``
    (``.gif``, or ``.mp4`` with ffmpeg on PATH).

    Args:
        scene: the scene's MJCF path (MuJoCo renders this file), or a ``mujoco.MjModel``.
        fit: a fit.json path, its object, or an :class:`estim.FitResult`.
        tracks: a tracks CSV path, an :class:`estim.Tracks`, or ``ball -> (t, position)``.
        out: the output file.
        fps: frames per second: ``floor(span * fps) + 1`` frames over the data's span.
        width: width of the picture in pixels.
        height: height of the picture in pixels (a caption band is added below it).
        camera: default :func:`side_camera`; an :class:`estim.Camera` (calibrated, with its
            image size) renders from its viewpoint (:func:`calibrated_view`; ``scene`` must
            then be the MJCF path), ``width`` wide and as high as its image's aspect says
            (``height`` is not used), so the fitted ball lands where the video saw it.
        trail: seconds of recent measured samples shown as dots (0: none).

    Raises:
        RenderError: no offscreen OpenGL here (see :func:`estim.render_sideview`).
        EncoderNotFoundError: ``.mp4`` without ffmpeg.
        ValueError, FileNotFoundError, KeyError: bad input, named in the message.
    """
    check_output(out, fps)
    model = _as_model(scene)
    if isinstance(camera, Camera):
        camera = calibrated_view(camera)
        if not isinstance(scene, (str, os.PathLike)):
            raise ValueError("a replay from a calibrated camera's viewpoint needs the scene's MJCF path")
        model = calibrated_model(scene, camera)
        height = max(1, round(width * camera.camera.size[1] / camera.camera.size[0]))
    motion = replay_motion(_estim_scene(scene, model), fit, tracks, fps=fps)
    frames = render_frames(model, motion, width=width, height=height, camera=camera, trail=trail)
    n = write_video(frames, out, fps, colours=list(ball_colours(model, motion.balls).values()))
    return ReplayInfo(os.fspath(out), n, float(fps), float(motion.t[0]), float(motion.t[-1]),
                      motion.balls, "mujoco")
