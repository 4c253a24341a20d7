"""Cameras: OpenCV's projection (against OpenCV itself and against MuJoCo's camera
projection sensor), its inverse, and camera files (as OpenCV's FileStorage writes them)."""

import json

import cv2
import jax
import mujoco
import numpy as np
import pytest

from estim.tracks._camera import Camera, CameraArrays, CameraError, read_camera, rodrigues

RNG = np.random.default_rng(3)
K = np.array([[1400.0, 0.0, 955.0], [0.0, 1390.0, 541.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.21, 0.06, 0.0012, -0.0021, 0.011])
RVEC = np.array([1.2, -0.3, 0.4])
TVEC = np.array([0.1, 0.2, 3.0])


def _points_in_front(camera, n=40):
    p = RNG.normal(size=(3 * n, 3)) * 0.6
    return p[np.asarray(camera.depth(p)) > 1.0][:n]


# OpenCV's longer distortion vectors: the rational model (k4 k5 k6, CALIB_RATIONAL_MODEL) and
# the thin prism (s1-s4, CALIB_THIN_PRISM_MODEL), with values a calibration of a wide lens gives.
RATIONAL = np.concatenate([DIST, [0.12, -0.03, 0.02]])
PRISM = np.concatenate([RATIONAL, [0.004, -0.001, -0.003, 0.0008]])
# A tilted sensor (CALIB_TILTED_MODEL: tau_x, tau_y in radians), as a Scheimpflug camera has.
TILTED = np.concatenate([PRISM, [0.05, -0.03]])


def _written_out(pts, dist):
    """OpenCV's projection (its documentation, "Camera Calibration and 3D Reconstruction")
    written out term by term, for a distortion vector of 5, 8, 12 or 14 numbers; the tilt as
    OpenCV's computeTiltProjectionMatrix builds it."""
    k = np.zeros(14)
    k[:len(dist)] = dist
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tx, ty = k
    pc = pts @ cv2.Rodrigues(RVEC)[0].T + TVEC
    x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    r2 = x**2 + y**2
    q = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    xd = x * q + 2 * p1 * x * y + p2 * (r2 + 2 * x**2) + s1 * r2 + s2 * r2**2
    yd = y * q + p1 * (r2 + 2 * y**2) + 2 * p2 * x * y + s3 * r2 + s4 * r2**2
    rot_x = np.array([[1, 0, 0], [0, np.cos(tx), np.sin(tx)], [0, -np.sin(tx), np.cos(tx)]])
    rot_y = np.array([[np.cos(ty), 0, -np.sin(ty)], [0, 1, 0], [np.sin(ty), 0, np.cos(ty)]])
    m = rot_y @ rot_x
    tilt = np.array([[m[2, 2], 0, -m[0, 2]], [0, m[2, 2], -m[1, 2]], [0, 0, 1]]) @ m
    w = np.stack([xd, yd, np.ones_like(xd)], axis=1) @ tilt.T
    xd, yd = w[:, 0] / w[:, 2], w[:, 1] / w[:, 2]
    return np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)


@pytest.mark.parametrize("dist", [DIST, RATIONAL, PRISM, TILTED], ids=["plain", "rational", "thin-prism", "tilted"])
def test_projection_is_opencvs(dist):
    cam = Camera.from_opencv(K, dist, RVEC, TVEC)
    pts = _points_in_front(cam)
    expected, _ = cv2.projectPoints(pts, RVEC, TVEC, K, dist)
    assert np.abs(np.asarray(cam.project(pts)) - expected[:, 0]).max() < 1e-9
    assert np.abs(np.asarray(cam.project(pts)) - _written_out(pts, dist)).max() < 1e-9
    # Each longer model's extra terms move the pixels (else the comparison proves nothing).
    shorter = {5: 0, 8: 5, 12: 8, 14: 12}[len(dist)]
    assert np.abs(_written_out(pts, dist) - _written_out(pts, dist[:shorter or 5])).max() > (1.0 if shorter else -1.0)
    assert np.abs(np.asarray(cam.rotation) - cv2.Rodrigues(RVEC)[0]).max() < 1e-15
    assert np.abs(cam.rvec - RVEC).max() < 1e-14


@pytest.mark.parametrize("dist", [DIST, TILTED], ids=["plain", "tilted"])
def test_projection_derivative_matches_finite_differences(dist):
    cam = Camera.from_opencv(K, dist, RVEC, TVEC)
    p = _points_in_front(cam, 1)[0]
    J = np.asarray(jax.jacfwd(cam.project)(p))
    h = 1e-6
    fd = np.stack([(np.asarray(cam.project(p + h * e)) - np.asarray(cam.project(p - h * e))) / (2 * h)
                   for e in np.eye(3)], axis=1)
    assert np.abs(J - fd).max() < 1e-4 * np.abs(J).max()


@pytest.mark.parametrize("dist", [DIST, RATIONAL, PRISM, TILTED], ids=["plain", "rational", "thin-prism", "tilted"])
def test_undistortion_and_rays_invert_the_projection(dist):
    cam = Camera.from_opencv(K, dist, RVEC, TVEC)
    pts = _points_in_front(cam)
    uv = np.asarray(cam.project(pts))
    ours = cam.normalised(uv)
    theirs = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist, criteria=(cv2.TERM_CRITERIA_COUNT, 20, 0))[:, 0]
    assert np.abs(ours - theirs).max() < 1e-12
    # Each point lies on its pixel's ray (to the accuracy of 20 fixed-point iterations).
    d = cam.rays(uv)
    v = pts - cam.centre
    miss = np.linalg.norm(v - np.sum(v * d, axis=1)[:, None] * d, axis=1)
    assert miss.max() < 1e-6


@pytest.mark.parametrize("focal", [(900.0, 900.0), (1400.0, 1320.0)])
def test_projection_is_mujocos_camera_projection(focal):
    # MuJoCo's camprojection sensor projects a site through an MJCF camera (which looks
    # along its -z, y up: OpenCV's axes turned half a turn about x) onto an image whose
    # pixel (0, 0) is the corner of the top-left pixel: OpenCV's pixel + 0.5, with the
    # principal point at the image centre.
    w, h = 1280, 720
    cam = Camera.look_at((2.5, -1.5, 1.2), (0.1, 0.2, 0.0), focal=focal[0], size=(w, h))
    cam = Camera.from_opencv([[focal[0], 0, (w - 1) / 2], [0, focal[1], (h - 1) / 2], [0, 0, 1]], (), cam.rvec,
                             np.asarray(cam.translation), size=(w, h))
    R, c = np.asarray(cam.rotation), [float(v) for v in cam.centre]
    pts = _points_in_front(cam, 12)
    sites = "".join(f'<site name="s{i}" pos="{" ".join(repr(float(v)) for v in p)}"/>' for i, p in enumerate(pts))
    sensors = "".join(f'<camprojection site="s{i}" camera="cv"/>' for i in range(len(pts)))
    xyaxes = " ".join(repr(float(v)) for v in np.concatenate([R[0], -R[1]]))
    xml = (f'<mujoco><worldbody><camera name="cv" pos="{c[0]!r} {c[1]!r} {c[2]!r}" xyaxes="{xyaxes}" '
           f'resolution="{w} {h}" focalpixel="{focal[0]} {focal[1]}" sensorsize="1 1"/>{sites}</worldbody>'
           f'<sensor>{sensors}</sensor></mujoco>')
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    theirs = data.sensordata.reshape(-1, 2) - 0.5
    # MuJoCo stores the focal length in float32: agreement to its precision.
    assert np.abs(np.asarray(cam.project(pts)) - theirs).max() < 2e-4


def test_camera_arrays_project_each_row_by_its_camera():
    a = Camera.from_opencv(K, DIST, RVEC, TVEC, name="a")
    b = Camera.look_at((0.0, -4.0, 1.5), (0.0, 0.0, 0.0), focal=1000.0, size=(1920, 1080), name="b")
    pts = _points_in_front(a, 6)
    which = np.array([0, 1, 1, 0, 1, 0])
    got = np.asarray(CameraArrays.of((a, b)).project(pts, which))
    for i, k in enumerate(which):
        assert np.allclose(got[i], np.asarray((a, b)[k].project(pts[i])), rtol=0, atol=1e-9)


def test_a_point_behind_the_camera_projects_finitely():
    cam = Camera.look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), focal=1000.0, size=(640, 480))
    uv = np.asarray(cam.project(np.array([0.1, -5.0, 0.1])))
    assert np.all(np.isfinite(uv)) and np.abs(uv).max() > 1e5


@pytest.mark.parametrize("dist", [DIST, TILTED], ids=["plain", "tilted"])
@pytest.mark.parametrize("ext", ["yml", "json"])
def test_reads_what_opencvs_file_storage_writes(tmp_path, ext, dist):
    path = tmp_path / f"left.{ext}"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "Thu Nov 26 2026")
    fs.write("image_width", 1920)
    fs.write("image_height", 1080)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(1, -1))
    fs.write("avg_reprojection_error", 0.31)
    fs.write("rvec", RVEC.reshape(3, 1))
    fs.write("tvec", TVEC.reshape(3, 1))
    fs.release()
    cam = read_camera(path)
    assert cam.name == "left" and cam.size == (1920, 1080)
    pts = _points_in_front(cam)
    expected, _ = cv2.projectPoints(pts, RVEC, TVEC, K, dist)
    assert np.abs(np.asarray(cam.project(pts)) - expected[:, 0]).max() < 1e-9
    # Written back in OpenCV's terms (the shortest of its lengths that holds the model), the
    # same camera.
    back = cam.to_json()
    assert back["distortion_coefficients"] == dist.tolist()
    again = Camera.from_opencv(back["camera_matrix"], back["distortion_coefficients"], back["rvec"], back["tvec"])
    assert np.abs(np.asarray(again.project(pts)) - expected[:, 0]).max() < 1e-9


def _rows(a) -> str:
    return "".join(f"  - {list(map(float, row))}\n" for row in np.atleast_2d(a))


@pytest.mark.parametrize("text", [
    # A YAML block list per matrix row and per vector item, comments and a blank line between.
    "camera_matrix:\n" + _rows(K) + "distortion_coefficients:\n" + _rows(DIST[:, None])
    + "rvec:  # world to camera\n" + "".join(f"- {x}  # axis {k}\n\n" for k, x in enumerate(RVEC))
    + "tvec:\n" + _rows(TVEC[:, None]),
    # JSON matrices as rows, cols and data without OpenCV's type_id; vectors as 3 x 1 lists.
    json.dumps({"camera_matrix": {"rows": 3, "cols": 3, "dt": "d", "data": K.ravel().tolist()},
                "distortion_coefficients": {"rows": 1, "cols": 5, "data": DIST.tolist()},
                "rvec": RVEC[:, None].tolist(), "tvec": TVEC[:, None].tolist()}),
])
def test_reads_what_people_write_by_hand(tmp_path, text):
    path = tmp_path / "hand.yml"
    path.write_text(text)
    cam = read_camera(path)
    pts = _points_in_front(cam)
    expected, _ = cv2.projectPoints(pts, RVEC, TVEC, K, DIST)
    assert np.abs(np.asarray(cam.project(pts)) - expected[:, 0]).max() < 1e-9


def _ros_matrix(key, a) -> str:
    a = np.atleast_2d(a)
    return f"{key}:\n  rows: {a.shape[0]}\n  cols: {a.shape[1]}\n  data: {a.ravel().tolist()}\n"


@pytest.mark.parametrize(("model", "distortion"), [("plumb_bob", DIST), ("rational_polynomial", RATIONAL)])
def test_reads_a_ros_camera_info_with_the_pose_added(tmp_path, model, distortion):
    """ROS's camera_info YAML as camera_calibration_parsers writes it (a rectified image's
    rectification and projection matrices beside the raw image's K and distortion), with
    rvec and tvec added: projected as OpenCV projects the raw image."""
    P = np.hstack([K * 0.97, np.zeros((3, 1))])
    P[2, 2] = 1.0
    path = tmp_path / "ros.yaml"
    path.write_text("image_width: 1920\nimage_height: 1080\ncamera_name: courtside\n" + _ros_matrix("camera_matrix", K)
                    + f"distortion_model: {model}\n" + _ros_matrix("distortion_coefficients", distortion)
                    + _ros_matrix("rectification_matrix", np.eye(3)) + _ros_matrix("projection_matrix", P)
                    + f"rvec: {RVEC.tolist()}\ntvec: {TVEC.tolist()}\n")
    cam = read_camera(path)
    pts = _points_in_front(cam)
    expected, _ = cv2.projectPoints(pts, RVEC, TVEC, K, np.asarray(distortion))
    assert np.abs(np.asarray(cam.project(pts)) - expected[:, 0]).max() < 1e-9
    assert cam.size == (1920, 1080)


@pytest.mark.parametrize("text", [
    "rvec: [0.1, -0.2, 0.3]\ntvec: [0.0, 0.1, 2.5]\nf: 1200\nw: 1920\nh: 1080\n",
    json.dumps({"rvec": [0.1, -0.2, 0.3], "tvec": [0.0, 0.1, 2.5], "f": 1200, "w": 1920, "h": 1080}),
])
def test_the_short_form(tmp_path, text):
    path = tmp_path / "cam.txt"
    path.write_text(text)
    cam = read_camera(path)
    assert np.allclose(np.asarray(cam.matrix), [[1200, 0, 959.5], [0, 1200, 539.5], [0, 0, 1]])
    assert np.allclose(np.asarray(cam.rotation), rodrigues([0.1, -0.2, 0.3]))
    assert cam.size == (1920, 1080) and not np.any(np.asarray(cam.distortion))


@pytest.mark.parametrize(("text", "message"), [
    ("rvec: [0, 0, 0]\ntvec: [0, 0, 1]\nf: 1000\nw: 640\n", r"no \['h'\]"),
    ("rvec: [0, 0, 0]\ntvec: [0, 0, 1]\nf: -5\nw: 640\nh: 480\n", "focal length must be > 0"),
    ("rvec: [0, 0, 0]\ntvec: [0, 0]\nf: 1000\nw: 640\nh: 480\n", "3 numbers"),
    ("rvec: [0, 0, 0]\ntvec: [0, 0, 1]\nf: 1000\nw: 640\nh: 480\ndist_coeffs: [0.1, 0, 0, 0]\n",
     r"unknown entry \['dist_coeffs'\]"),
    ("rvec: [0, 0, 0]\ntvec: [0, 0, 1]\nf: 1000\nw: 640\nh: 480\ncamera_matrix: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n",
     "give one of the two"),
    ("camera_matrix: [1000, 3, 320, 0, 1000, 240, 0, 0, 1]\nrvec: [0, 0, 0]\ntvec: [0, 0, 1]\n", "no skew"),
    ("camera_matrix: [1000, 0, 320, 0, 1000, 240, 0, 0, 1]\nrvec: [0, 0, 0]\ntvec: [0, 0, 1]\n"
     "distortion_coefficients: [0.1, 0, 0, 0, 0, 0.2]\n", "6 distortion coefficients; OpenCV's are 4, 5, 8, 12 or 14"),
    ("camera_matrix: [1000, 0, 320, 0, 1000, 240, 0, 0]\nrvec: [0, 0, 0]\ntvec: [0, 0, 1]\n", "has 8 numbers"),
    ("rvec: [0, 0, nan]\ntvec: [0, 0, 1]\nf: 1000\nw: 640\nh: 480\n", "not a list of numbers"),
    ("this is not a camera\n", "expected 'key: value'"),
    ("rvec:\n  - - 0.1\ntvec: [0, 0, 1]\nf: 1000\nw: 640\nh: 480\n", "line 2: rvec: a list's item"),
    ("rvec:\n  - 0.1\n  - x\n  - 0.3\ntvec: [0, 0, 1]\nf: 1000\nw: 640\nh: 480\n", "rvec: 'x' is not a finite number"),
    ('{"camera_matrix": {"rows": 3, "data": [1, 0, 0, 0, 1, 0, 0, 0, 1]}, "rvec": [0, 0, 0], "tvec": [0, 0, 1]}',
     r"camera_matrix: a mapping of \['data', 'rows'\]"),
    ('{"camera_matrix": {"rows": 3, "cols": 3, "data": [1, 0, 0, 0, 1, 0]}, "rvec": [0, 0, 0], "tvec": [0, 0, 1]}',
     "6 numbers in data for a 3 x 3 matrix"),
    ('{"rvec": [0, 0, 0], ', "not valid JSON"),
    ("camera_matrix: [1000, 0, 320, 0, 1000, 240, 0, 0, 1]\ndistortion_model: equidistant\n"
     "distortion_coefficients: [0.1, 0.01, 0, 0]\nrvec: [0, 0, 0]\ntvec: [0, 0, 1]\n",
     "distortion_model 'equidistant': estim models OpenCV's pinhole distortion"),
    ("rvec: [0, 0, 0]\ntvec: [0, 0, 1]\nf: 1000\nw: 640\nh: 480\ndistortion_model: plumb_bob\n",
     "give one of the two"),
])
def test_a_camera_file_that_does_not_parse_names_the_problem(tmp_path, text, message):
    path = tmp_path / "bad.yml"
    path.write_text(text)
    with pytest.raises(CameraError, match=message) as err:
        read_camera(path)
    assert str(path) in str(err.value)


def test_a_missing_camera_file():
    with pytest.raises(FileNotFoundError, match="camera file not found"):
        read_camera("/nonexistent/cam.yml")


def test_the_bench_camera_shot(tmp_path):
    # `estim bench fit`'s one-camera shot (estim.app._bench.camera_shot) is what its table
    # says: 15 frames at 25 fps, the camera file read back as OpenCV's camera, the pixels
    # OpenCV's projection of the shot (its true path) plus 2 px of noise, one bounce in view
    # (the centre one radius above the table's top, z = 0).
    from estim.app._bench import CAMERA_SHOT, _shot_path, camera_shot
    from estim.tracks._image import read_image_tracks_csv

    track, camera_path = camera_shot(str(tmp_path))
    cam = read_camera(camera_path)
    seen = read_image_tracks_csv(track, [cam])
    t, uv = seen.t["pingpong"], seen.uv["pingpong"]
    np.testing.assert_allclose(t, np.arange(15) / CAMERA_SHOT["fps"], atol=1e-6)
    fine = np.linspace(0.0, t[-1], 601)
    _, path = _shot_path(np.concatenate([t, fine]))
    truth, fine = path[: t.size], path[t.size:]
    expected, _ = cv2.projectPoints(truth, cam.rvec, np.asarray(cam.translation), np.asarray(cam.matrix),
                                    np.asarray(cam.distortion))
    noise = uv - expected[:, 0]
    assert abs(np.std(noise) - CAMERA_SHOT["noise_px"]) < 0.5 and np.abs(noise.mean(axis=0)).max() < 1.5
    low = np.flatnonzero((fine[1:-1, 2] < fine[:-2, 2]) & (fine[1:-1, 2] <= fine[2:, 2])) + 1
    assert low.size == 1 and abs(fine[low[0], 2] - 0.02) < 3e-3  # (the grid's 1 ms at about 2.5 m/s)
    assert 0.0 < fine[low[0], 1] < 1.37 and np.all(np.abs(fine[:, 0]) < 0.7625)  # on the table's far half
