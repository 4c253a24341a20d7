"""Calibrated pinhole cameras with OpenCV's conventions, and the files that describe them.

A :class:`Camera` maps a point ``X`` of the scene's world frame (metres) to the pixel
``(u, v)`` (u to the right, v down) as OpenCV's ``projectPoints`` does (the pinhole model of
OpenCV's calibration module, "Camera Calibration and 3D Reconstruction"):

    X_c = R X + t                         R = Rodrigues(rvec): world -> camera
    x' = X_c / Z_c,  y' = Y_c / Z_c,      r^2 = x'^2 + y'^2
    q = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
    x'' = x' q + 2 p1 x' y' + p2 (r^2 + 2 x'^2) + s1 r^2 + s2 r^4
    y'' = y' q + p1 (r^2 + 2 y'^2) + 2 p2 x' y' + s3 r^2 + s4 r^4
    (x''', y''') = T(tau_x, tau_y) (x'', y'')              (a tilted sensor; T = 1 untilted)
    u = fx x''' + cx,  v = fy y''' + cy,   K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]

with OpenCV's distortion coefficients in its order, ``(k1, k2, p1, p2, k3, k4, k5, k6, s1,
s2, s3, s4, tau_x, tau_y)``: radial (k1-k3), the rational model's denominator (k4-k6,
``CALIB_RATIONAL_MODEL``), tangential (p1, p2), thin prism (s1-s4,
``CALIB_THIN_PRISM_MODEL``) and the tilt of a sensor not square to the optical axis
(``CALIB_TILTED_MODEL``, a Scheimpflug camera): T maps ``(x'', y'', 1)`` through OpenCV's
``computeTiltProjectionMatrix``, ``M = P_z R_y(tau_y) R_x(tau_x)`` with ``P_z = [[m22, 0,
-m02], [0, m22, -m12], [0, 0, 1]]`` (``m`` = ``R_y R_x``), and divides by the third
component. A shorter vector (4, 5, 8 or 12 numbers) leaves the rest 0: most calibrations
give the plain model, k1 k2 p1 p2 [k3].

The camera looks along its +Z axis, its X to the right and Y down in the image. The
projection (:meth:`Camera.project`) is differentiable in JAX with respect to the point; a
point behind the camera (``Z_c <= 0``) has no image, and :meth:`Camera.project` answers
with the image of its mirror at ``Z_c = 1e-6`` (finite, far off the image) so that a fit
that strays there is pushed back rather than poisoned. :meth:`Camera.rays` inverts it
(the distortion by OpenCV's fixed-point iteration of ``undistortPoints``).

Camera files (:func:`read_camera`), one camera per file, in one of three forms:

- OpenCV's FileStorage, YAML (``%YAML:1.0``, matrices as ``!!opencv-matrix`` with
  ``rows``, ``cols``, ``dt``, ``data``) or JSON (matrices as objects with
  ``"type_id": "opencv-matrix"``), or by hand (a matrix as ``rows``, ``cols`` and
  ``data`` without the tag, as nested lists, or as a YAML block list of ``- x`` lines):
  ``camera_matrix``,
  ``distortion_coefficients`` (4, 5, 8, 12 or 14 numbers in OpenCV's order, above),
  ``rvec`` and ``tvec`` (the world-to-camera pose, as ``solvePnP`` gives it), and
  optionally ``image_width`` and ``image_height``; ROS's ``camera_info`` YAML (the same
  keys, with ``distortion_model``, ``rectification_matrix`` and ``projection_matrix``),
  with the pose added: its ``distortion_model`` must be OpenCV's (``plumb_bob`` or
  ``rational_polynomial``), and its rectification and projection
  matrices, which describe the rectified image, are read and not used (estim projects
  into the image as it was filmed, through ``camera_matrix`` and the distortion: a track
  taken on rectified images goes with a camera file of the projection matrix's K and no
  distortion);
- the short form, in YAML or JSON: ``rvec: [...]``, ``tvec: [...]``, ``f: ...`` (the focal
  length in pixels), ``w: ...`` and ``h: ...`` (the image size in pixels): principal point
  at the image centre ``((w - 1) / 2, (h - 1) / 2)`` in OpenCV's pixel-centre convention
  (pixel (0, 0) is the centre of the top-left pixel), no distortion.

A key estim does not know is an error naming it (a misspelt ``dist_coeffs`` must not leave
the distortion silently out); the bookkeeping keys of OpenCV's calibration sample
(``calibration_time``, ``avg_reprojection_error``, ...) are read and not used.
"""

from __future__ import annotations

import json
import math
import os
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

__all__ = ["Camera", "CameraArrays", "CameraError", "project", "read_camera", "rodrigues"]

# Z_c below which a point counts as behind the camera (m).
_MIN_DEPTH = 1e-6
_UNDISTORT_ITERATIONS = 20
# OpenCV's distortion coefficients (module docstring), and the lengths of the vectors it writes.
N_DISTORTION = 14
_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)

_MATRIX_KEYS = ("camera_matrix",)
_DISTORTION_KEYS = ("distortion_coefficients",)
_SHORT_KEYS = ("rvec", "tvec", "f", "w", "h")
_SIZE_KEYS = ("image_width", "image_height")
# ROS's camera_info (sensor_msgs/CameraInfo as camera_calibration_parsers writes it): the
# rectified image's matrices, read and not used, and the name of the distortion model.
_RECTIFIED = ("rectification_matrix", "projection_matrix")
_DISTORTION_MODEL = "distortion_model"
_OPENCV_MODELS = ("plumb_bob", "rational_polynomial")
_ROS_KEYS = _RECTIFIED + (_DISTORTION_MODEL,)
# Written by OpenCV's calibration sample beside the camera; read and not used.
_BOOKKEEPING = ("calibration_time", "calibration_date", "nframes", "nr_of_frames", "board_width", "board_height",
                "board_size", "square_size", "marker_size", "aspect_ratio", "aspectRatio", "flags", "flagValue",
                "fix_aspect_ratio", "fix_principal_point", "zero_tangent_dist", "fisheye_model",
                "avg_reprojection_error", "per_view_reprojection_errors", "extrinsic_parameters", "image_points",
                "grid_points", "camera_name", "name")


class CameraError(ValueError):
    """A camera file that cannot be read; the message names the file and the problem."""


def rodrigues(rvec) -> np.ndarray:
    """The rotation matrix of the rotation vector ``rvec`` (axis times angle, radians):
    ``R = I + sin(a) [k]_x + (1 - cos(a)) [k]_x^2`` with ``a = |rvec|``, ``k = rvec / a``
    (Rodrigues' formula, as OpenCV's ``Rodrigues``)."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    a = float(np.linalg.norm(r))
    if a < 1e-300:
        return np.eye(3)
    k = r / a
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(a) * kx + (1.0 - math.cos(a)) * kx @ kx


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    """The rotation vector of the rotation matrix ``R`` (the inverse of :func:`rodrigues`)."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    a = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if a < 1e-12:
        return 0.5 * w
    if math.pi - a < 1e-6:  # near a half turn: the axis from R + I
        k = np.sqrt(np.clip((np.diag(R) + 1.0) / 2.0, 0.0, None))
        i = int(np.argmax(k))
        k = (R[:, i] + np.eye(3)[:, i]) / (2.0 * k[i])
        return a * k / np.linalg.norm(k)
    return a * w / (2.0 * math.sin(a))


class Camera(eqx.Module):
    """A calibrated pinhole camera (module docstring).

    Attributes:
        name: what the camera is called (its file's stem), for messages and the pixel
            tracks' ``camera`` column.
        matrix: ``(3, 3)`` the intrinsic matrix K (pixels).
        distortion: ``(14,)`` k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tau_x, tau_y
            (OpenCV's order; module docstring).
        rotation: ``(3, 3)`` R, world to camera.
        translation: ``(3,)`` t, world to camera (m): ``X_c = R X + t``.
        size: the image's ``(width, height)`` in pixels, where known.
    """

    name: str = eqx.field(static=True)
    matrix: Float[Array, "3 3"]
    distortion: Float[Array, "14"]
    rotation: Float[Array, "3 3"]
    translation: Float[Array, "3"]
    size: tuple[int, int] | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        K = np.asarray(self.matrix)
        if K.shape != (3, 3) or np.asarray(self.distortion).shape != (N_DISTORTION,) or np.asarray(self.rotation).shape != (3, 3) \
                or np.asarray(self.translation).shape != (3,):
            raise CameraError(f"camera {self.name!r}: K must be 3x3, the distortion {N_DISTORTION} numbers, R 3x3 and t 3 numbers")
        for what, a in (("camera matrix", K), ("distortion", self.distortion), ("rotation", self.rotation),
                        ("translation", self.translation)):
            if not np.all(np.isfinite(np.asarray(a))):
                raise CameraError(f"camera {self.name!r}: the {what} has a value that is not finite: {np.asarray(a).tolist()}")
        if not (K[0, 0] > 0 and K[1, 1] > 0 and K[0, 1] == 0 and K[1, 0] == 0 and K[2, 0] == 0 and K[2, 1] == 0
                and K[2, 2] == 1):
            raise CameraError(f"camera {self.name!r}: the camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
                              f"with fx, fy > 0 (pixels; no skew, which OpenCV's projection ignores), got {K.tolist()}")
        R = np.asarray(self.rotation)
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise CameraError(f"camera {self.name!r}: the rotation is not a rotation matrix: {R.tolist()}")

    @classmethod
    def from_opencv(cls, matrix, distortion=(), rvec=(0.0, 0.0, 0.0), tvec=(0.0, 0.0, 0.0), *, name: str = "camera",
                    size: tuple[int, int] | None = None) -> Camera:
        """A camera from OpenCV's ``cameraMatrix``, ``distCoeffs``, ``rvec`` and ``tvec``."""
        d = np.asarray(distortion, dtype=np.float64).reshape(-1)
        if d.size not in _DISTORTION_LENGTHS:
            raise CameraError(f"camera {name!r}: {d.size} distortion coefficients; OpenCV's are 4, 5, 8, 12 or 14")
        full = np.zeros(N_DISTORTION)
        full[:d.size] = d
        rvec = np.asarray(rvec, dtype=np.float64).reshape(-1)
        tvec = np.asarray(tvec, dtype=np.float64).reshape(-1)
        if rvec.shape != (3,) or tvec.shape != (3,):
            raise CameraError(f"camera {name!r}: rvec and tvec need 3 numbers each, got {rvec.size} and {tvec.size}")
        return cls(name=name, matrix=np.asarray(matrix, dtype=np.float64), distortion=full, rotation=rodrigues(rvec),
                   translation=tvec, size=None if size is None else (int(size[0]), int(size[1])))

    @classmethod
    def look_at(cls, position, target, *, focal: float, size: tuple[int, int], up=(0.0, 0.0, 1.0),
                name: str = "camera") -> Camera:
        """A camera without distortion at ``position`` looking at ``target`` (world frame,
        m), the image's up along the world's ``up`` as far as the view allows; focal length
        in pixels, principal point at the image centre (the short form's)."""
        c, forward = np.asarray(position, dtype=np.float64), np.asarray(target, dtype=np.float64)
        z = (forward - c) / np.linalg.norm(forward - c)
        x = np.cross(z, np.asarray(up, dtype=np.float64))
        if np.linalg.norm(x) < 1e-9:
            raise CameraError(f"camera {name!r}: the view direction is along up; give another up")
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        w, h = size
        K = [[focal, 0.0, (w - 1) / 2], [0.0, focal, (h - 1) / 2], [0.0, 0.0, 1.0]]
        return cls.from_opencv(K, (), _rotation_vector(R), -R @ c, name=name, size=size)

    @property
    def rvec(self) -> np.ndarray:
        """The rotation vector of R (OpenCV's ``rvec``)."""
        return _rotation_vector(np.asarray(self.rotation))

    @property
    def centre(self) -> np.ndarray:
        """The camera's optical centre in the world frame, ``-R^T t`` (m)."""
        return -np.asarray(self.rotation).T @ np.asarray(self.translation)

    def depth(self, points) -> np.ndarray:
        """``Z_c`` of world points ``(..., 3)``: their distance along the optical axis (m)."""
        p = np.asarray(points, dtype=np.float64)
        return p @ np.asarray(self.rotation)[2] + float(self.translation[2])

    def project(self, points: Float[Array, "*batch 3"]) -> Float[Array, "*batch 2"]:
        """Pixels ``(u, v)`` of world points (module docstring); JAX, differentiable
        (compiled: called eagerly, as the plots do, its operations would each compile)."""
        return _project_compiled(self.matrix, self.distortion, self.rotation, self.translation, points)

    def normalised(self, uv) -> np.ndarray:
        """The undistorted normalised image coordinates ``(x', y')`` of pixels ``(..., 2)``
        (NumPy): K inverted, then the distortion by fixed-point iteration, as OpenCV's
        ``undistortPoints`` (exact for a camera without distortion)."""
        uv = np.asarray(uv, dtype=np.float64)
        K = np.asarray(self.matrix)
        yd = (uv[..., 1] - K[1, 2]) / K[1, 1]
        xd = (uv[..., 0] - K[0, 2]) / K[0, 0]
        d = np.asarray(self.distortion)
        if np.any(d[12:] != 0):  # the tilt undone first, as OpenCV's undistortPoints does
            w = np.stack([xd, yd, np.ones_like(xd)], axis=-1) @ np.linalg.inv(_tilt(d)).T
            xd, yd = w[..., 0] / w[..., 2], w[..., 1] / w[..., 2]
        x, y = xd.copy(), yd.copy()
        if np.any(d[:12] != 0):
            for _ in range(_UNDISTORT_ITERATIONS):
                radial, dx, dy = _distortion_terms(d, x, y)
                x, y = (xd - dx) / radial, (yd - dy) / radial
        return np.stack([x, y], axis=-1)

    def rays(self, uv) -> np.ndarray:
        """Unit directions ``(..., 3)`` in the world frame of the rays from :attr:`centre`
        through pixels ``(..., 2)`` (NumPy)."""
        xy = self.normalised(uv)
        d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1) @ np.asarray(self.rotation)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def to_json(self) -> dict:
        """The camera in OpenCV's terms (``camera_matrix``, ``distortion_coefficients``,
        ``rvec``, ``tvec``), as plain lists."""
        d = np.asarray(self.distortion)
        # The shortest of OpenCV's lengths (5 at least) that holds every coefficient not 0.
        nonzero = np.flatnonzero(d)
        length = min(n for n in (5, 8, 12, N_DISTORTION) if n > (nonzero[-1] if nonzero.size else 0))
        out = {"name": self.name, "camera_matrix": np.asarray(self.matrix).tolist(),
               "distortion_coefficients": d[:length].tolist(),
               "rvec": self.rvec.tolist(), "tvec": np.asarray(self.translation).tolist()}
        if self.size is not None:
            out["image_width"], out["image_height"] = self.size
        return out


class CameraArrays(eqx.Module):
    """Cameras stacked as arrays, without their names: what a compiled fit carries.
    :meth:`project` takes, per point, the index of the camera that sees it."""

    matrix: Float[Array, "cameras 3 3"]
    distortion: Float[Array, "cameras 14"]
    rotation: Float[Array, "cameras 3 3"]
    translation: Float[Array, "cameras 3"]

    @classmethod
    def of(cls, cameras) -> CameraArrays:
        """The arrays of a sequence of :class:`Camera`."""
        cameras = tuple(cameras)
        return cls(*(np.stack([np.asarray(getattr(c, f)) for c in cameras])
                     for f in ("matrix", "distortion", "rotation", "translation")))

    def project(self, points: Float[Array, "n 3"], which) -> Float[Array, "n 2"]:
        """Pixels of ``points``, each seen by the camera ``which[i]``."""
        return project(self.matrix[which], self.distortion[which], self.rotation[which], self.translation[which],
                       points)


def project(matrix, distortion, rotation, translation, points):
    """OpenCV's projection (module docstring) of world points ``(..., 3)`` by cameras whose
    arrays broadcast against them (``(..., 3, 3)``, ``(..., 14)``, ``(..., 3, 3)``,
    ``(..., 3)``); JAX, differentiable in every argument."""
    pc = jnp.einsum("...ij,...j->...i", rotation, jnp.asarray(points)) + translation
    z = jnp.maximum(pc[..., 2], _MIN_DEPTH)
    x, y = pc[..., 0] / z, pc[..., 1] / z
    radial, dx, dy = _distortion_terms(distortion, x, y)
    w = jnp.einsum("...ij,...j->...i", _tilt(distortion),
                   jnp.stack([x * radial + dx, y * radial + dy, jnp.ones_like(x)], axis=-1))
    xd, yd = w[..., 0] / w[..., 2], w[..., 1] / w[..., 2]  # (untilted: w = (x'', y'', 1) exactly)
    return jnp.stack([matrix[..., 0, 0] * xd + matrix[..., 0, 2], matrix[..., 1, 1] * yd + matrix[..., 1, 2]],
                     axis=-1)


_project_compiled = jax.jit(project)


def _distortion_terms(distortion, x, y):
    """The distortion of normalised image coordinates ``(x', y')`` (module docstring) as
    ``(q, dx, dy)``: ``x'' = x' q + dx``, ``y'' = y' q + dy``. NumPy or JAX: the projection
    and OpenCV's fixed-point undistortion (``x' = (x'' - dx) / q``) share it."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = (distortion[..., i] for i in range(12))
    r2 = x * x + y * y
    r4 = r2 * r2
    q = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4
    dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r4
    return q, dx, dy


def _tilt(distortion):
    """OpenCV's ``computeTiltProjectionMatrix`` of the tilt ``(tau_x, tau_y)`` (the last two
    coefficients): ``M = P_z R_y R_x`` (module docstring), ``(..., 3, 3)``; the identity,
    exactly, for no tilt. NumPy or JAX, as ``distortion`` is."""
    xp = jnp if isinstance(distortion, jax.Array) else np
    tx, ty = distortion[..., 12], distortion[..., 13]
    cx, sx, cy, sy = xp.cos(tx), xp.sin(tx), xp.cos(ty), xp.sin(ty)
    rows = ((cy, sy * sx, -sy * cx), (xp.zeros_like(tx), cx, sx), (sy, -cy * sx, cy * cx))  # R_y R_x
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = rows
    projected = ((m22 * m00 - m02 * m20, m22 * m01 - m02 * m21, m22 * m02 - m02 * m22),
                 (m22 * m10 - m12 * m20, m22 * m11 - m12 * m21, m22 * m12 - m12 * m22),
                 (m20, m21, m22))
    return xp.stack([xp.stack(r, axis=-1) for r in projected], axis=-2)


# ------------------------------------------------------------------------------- files


def read_camera(path: str | os.PathLike, *, name: str | None = None) -> Camera:
    """Read a camera file (module docstring): OpenCV FileStorage YAML or JSON, or the
    short form. The camera is named ``name`` (default: the file's stem).

    Raises:
        FileNotFoundError: no such file.
        CameraError: a file that does not parse, a key estim does not know, a missing or
            malformed entry; the message names the file and the entry.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"camera file not found: {path}")
    with open(path, encoding="utf-8-sig") as f:
        text = f.read()
    name = os.path.splitext(os.path.basename(path))[0] if name is None else name
    stripped = text.lstrip()
    try:
        if stripped.startswith("{"):
            try:
                entries = json.loads(text)
            except json.JSONDecodeError as err:
                raise CameraError(f"line {err.lineno}: not valid JSON ({err.msg})") from None
            if not isinstance(entries, dict):
                raise CameraError("a camera file holds one object of named entries")
        else:
            entries = _parse_yaml(text)
        return _camera_from(entries, name)
    except CameraError as err:
        raise CameraError(f"{path}: {err}") from None


def _camera_from(entries: dict, name: str) -> Camera:
    entries = {k: _matrix(v, k) for k, v in entries.items()}
    known = _MATRIX_KEYS + _DISTORTION_KEYS + _SHORT_KEYS + _SIZE_KEYS + _ROS_KEYS + _BOOKKEEPING
    unknown = [k for k in entries if k not in known]
    if unknown:
        raise CameraError(f"unknown entr{'y' if len(unknown) == 1 else 'ies'} {unknown}; a camera file has "
                          "camera_matrix, distortion_coefficients, rvec, tvec (and image_width, image_height), "
                          "or the short form rvec, tvec, f, w, h")
    short = [k for k in ("f", "w", "h") if k in entries]
    full = [k for k in _MATRIX_KEYS + _DISTORTION_KEYS + _SIZE_KEYS + _ROS_KEYS if k in entries]
    if short and full:
        raise CameraError(f"both the short form's {short} and OpenCV's {full}: give one of the two")
    missing = [k for k in (_SHORT_KEYS if short else _MATRIX_KEYS + ("rvec", "tvec")) if k not in entries]
    if missing:
        form = "the short form needs rvec, tvec, f, w and h" if short else \
            "OpenCV's form needs camera_matrix, rvec and tvec (distortion_coefficients optional)"
        raise CameraError(f"no {missing}: {form}")
    model = entries.get(_DISTORTION_MODEL, _OPENCV_MODELS[0])
    if model not in _OPENCV_MODELS:
        raise CameraError(f"distortion_model {model!r}: estim models OpenCV's pinhole distortion "
                          f"({' or '.join(_OPENCV_MODELS)}), not this one")
    vector = {k: _numbers(entries[k], k) for k in entries if k not in _BOOKKEEPING + (_DISTORTION_MODEL,)}
    if short:
        f, w, h = (_scalar(vector[k], k) for k in ("f", "w", "h"))
        if not f > 0:
            raise CameraError(f"f = {f!r}: the focal length must be > 0 pixels")
        if not (w >= 1 and h >= 1 and float(w).is_integer() and float(h).is_integer()):
            raise CameraError(f"w = {w!r}, h = {h!r}: the image size must be whole numbers of pixels >= 1")
        K = [[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]]
        return Camera.from_opencv(K, (), vector["rvec"], vector["tvec"], name=name, size=(int(w), int(h)))
    K = np.asarray(vector["camera_matrix"], dtype=np.float64)
    if K.size != 9:
        raise CameraError(f"camera_matrix has {K.size} numbers; it is 3 x 3")
    size = None
    if any(k in vector for k in _SIZE_KEYS):
        if not all(k in vector for k in _SIZE_KEYS):
            raise CameraError("image_width and image_height go together")
        size = (int(_scalar(vector["image_width"], "image_width")), int(_scalar(vector["image_height"], "image_height")))
    return Camera.from_opencv(K.reshape(3, 3), vector.get("distortion_coefficients", ()), vector["rvec"],
                              vector["tvec"], name=name, size=size)


def _matrix(value, key):
    """An ``opencv-matrix`` entry (YAML's ``!!opencv-matrix``, JSON's ``type_id``, or an
    untagged mapping of ``rows``, ``cols`` and ``data``) as a flat list of its data, checked
    against its rows and columns; other values unchanged."""
    if not isinstance(value, dict):
        return value
    tag = value.get("type_id", value.get("!!"))
    if tag == "opencv-matrix" or (tag is None and {"rows", "cols", "data"} <= set(value)):
        try:
            rows, cols, data = int(value["rows"]), int(value["cols"]), value["data"]
        except (KeyError, TypeError, ValueError):
            raise CameraError(f"{key}: an opencv-matrix needs rows, cols and data") from None
        data = data if isinstance(data, list) else [data]
        if len(data) != rows * cols:
            raise CameraError(f"{key}: {len(data)} numbers in data for a {rows} x {cols} matrix")
        return data
    return value


def _numbers(value, key) -> list[float]:
    if isinstance(value, dict):
        raise CameraError(f"{key}: a mapping of {sorted(value)}; a matrix is rows, cols and data "
                          "(OpenCV's opencv-matrix), a vector a list of numbers")
    flat = np.asarray(value, dtype=object).reshape(-1).tolist() if isinstance(value, list) else [value]
    out = []
    for v in flat:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise CameraError(f"{key}: {v!r} is not a finite number")
        out.append(float(v))
    return out


def _scalar(values: list[float], key) -> float:
    if len(values) != 1:
        raise CameraError(f"{key}: one number expected, got {len(values)}")
    return values[0]


# OpenCV's FileStorage YAML: top-level ``key: value``, where a value is a scalar, a flow
# sequence ``[ ... ]`` (possibly over several lines) or a nested mapping (indented lines,
# e.g. an ``!!opencv-matrix``). Enough of YAML for the files OpenCV writes and people type;
# anything else is an error naming the line.
_KEY = re.compile(r"^(\s*)([A-Za-z_][\w-]*)\s*:\s*(.*)$")


def _parse_yaml(text: str) -> dict:
    lines = text.splitlines()
    entries, stack = {}, [(-1, None)]  # (indent, the mapping being filled)
    stack[0] = (-1, entries)
    i = 0
    while i < len(lines):
        raw = lines[i]
        line = raw.split("#", 1)[0].rstrip() if not raw.lstrip().startswith("%") else ""
        i += 1
        if not line.strip() or line.strip() == "---":
            continue
        m = _KEY.match(line)
        if m is None:
            raise CameraError(f"line {i}: expected 'key: value', got {raw.strip()!r}")
        indent, key, rest = len(m.group(1)), m.group(2), m.group(3).strip()
        while stack and indent <= stack[-1][0]:
            stack.pop()
        if not stack:
            raise CameraError(f"line {i}: unexpected indentation")
        target = stack[-1][1]
        tag = None
        if rest.startswith("!!"):
            tag, _, rest = rest.partition(" ")
            tag, rest = tag[2:], rest.strip()
        if rest == "" and not tag and _item(lines, i)[1] is not None:
            target[key], i = _block_sequence(lines, i, key, indent)
            continue
        if rest == "":
            child = {"!!": tag} if tag else {}
            target[key] = child
            stack.append((indent, child))
            continue
        if rest.startswith("[") or rest.startswith("{"):
            opener, closer = rest[0], "]" if rest[0] == "[" else "}"
            start = i
            while rest.count(opener) > rest.count(closer) and i < len(lines):
                rest += " " + lines[i].split("#", 1)[0].strip()
                i += 1
            if opener == "{":
                raise CameraError(f"line {start}: {key}: flow mappings are not read; write one 'key: value' per line")
            target[key] = _flow_sequence(rest, key, start)
        else:
            target[key] = _scalar_text(rest, key, i)
    return entries


_ITEM = re.compile(r"^(\s*)-(?:\s+(.*))?$")


def _item(lines: list[str], i: int):
    """The first line from ``i`` that holds anything but a comment: its index and, where it
    is a block list's item (``- value``), the match (else None)."""
    while i < len(lines) and not lines[i].split("#", 1)[0].strip():
        i += 1
    return i, (_ITEM.match(lines[i].split("#", 1)[0].rstrip()) if i < len(lines) else None)


def _block_sequence(lines: list[str], i: int, key: str, indent: int) -> tuple[list, int]:
    """The items of a block list from line ``i`` (``- 1.2`` one a line, each a number or a
    flow list ``[...]``), and the index of the line after it."""
    items = []
    while True:
        at, m = _item(lines, i)
        if m is None or len(m.group(1)) < indent:
            return items, i
        i = at + 1
        text = (m.group(2) or "").strip()
        if not text or text == "-" or text.startswith("- "):  # (empty, or a list in a list)
            raise CameraError(f"line {i}: {key}: a list's item must be a number or [numbers] on its line")
        items.append(_flow_sequence(text, key, i) if text.startswith("[") else _scalar_text(text, key, i))


def _flow_sequence(text: str, key: str, line: int) -> list:
    try:
        return json.loads(re.sub(r"\.(?=[\],\s])", ".0", text.replace("\n", " ")))
    except json.JSONDecodeError:
        raise CameraError(f"line {line}: {key}: {text!r} is not a list of numbers") from None


def _scalar_text(text: str, key: str, line: int):
    s = text.strip().strip('"').strip("'")
    try:
        return int(s)
    except ValueError:
        pass
    try:
        return float(s)
    except ValueError:
        return s
