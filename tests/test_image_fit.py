"""Fits in pixels (estim.fitting._image): shots of known parameters seen by calibrated
cameras, fitted back from their pixels; through the library and through `estim fit
--camera`."""

import json
import math
import sys
from types import SimpleNamespace

import cv2
import mujoco
import numpy as np
import pytest
from conftest import ROOT
from test_image_tracks import BEHIND, SIDE, _tracks

import estim
from estim.app._bench import camera_shot
from estim.app._cli import main
from estim.fitting._fit import BallFit
from estim.fitting._image import (
    AMBIGUOUS,
    DEPTH_LIMIT,
    DRIFT,
    _alternative,
    _choose,
    _depth_report,
    fit_image,
)
from estim.show._replay import calibrated_model, calibrated_view, render_frames, replay_motion
from estim.tracks._camera import Camera
from estim.tracks._image import ImageTracks

TRUTH = {"e": 0.88, "mu": 0.3, "position": [-0.2, -1.6, 0.25], "velocity": [0.4, 6.5, 1.6],
         "spin": [-120.0, 0.0, 40.0]}
T = np.arange(0.0, 0.6, 1 / 120)


def _shot(scene):
    p = estim.Params.for_ball(scene, "pingpong", e=TRUTH["e"], mu_t=0.0, mu=TRUTH["mu"],
                              position=np.array(TRUTH["position"]), velocity=np.array(TRUTH["velocity"]),
                              spin=np.array(TRUTH["spin"]))
    return np.asarray(estim.simulate(scene, p, 0.7, ts=T).position)


def _across(spin, velocity):
    """The spin's part across the velocity: what the Magnus force and a bounce read."""
    v = np.asarray(velocity) / np.linalg.norm(velocity)
    return np.asarray(spin) - np.dot(spin, v) * v


def test_one_camera_in_a_vacuum():
    # The table without air, one camera from the side at 3 m, 1 px of noise at 120 Hz: the
    # depth comes from gravity and the bounce on the table; the spin does nothing a topspin
    # bounce that grips can show, beyond what grips (mu is then not identifiable either).
    scene = estim.load_scene("data/scenes/table_tennis.xml").with_air(None)
    tracks = _tracks((SIDE,), T, _shot(scene), 1.0, seed=4)
    # 40 iterations: the spin's directions that a grip leaves open slow the loss's last
    # digits, and 30 stop a few 1e-5 short of the convergence test.
    bf = fit_image(scene, tracks, steps=40).balls["pingpong"]
    assert bf.unit == "px" and bf.converged and bf.at_noise_floor
    # One camera at 3 m and 1 px reads e to about 0.013 here: within three standard errors.
    assert bf.stderr["e"] < 0.02 and abs(bf.values["e"] - TRUTH["e"]) < 3 * bf.stderr["e"]
    assert abs(bf.rms_m - 1.0) < 0.1  # 1 px of noise
    release = np.array([bf.values[n] for n in ("x0", "y0", "z0")])
    assert np.linalg.norm(release - TRUTH["position"]) < 3 * bf.depth["along_axis_m"] + 0.003
    # The fitted 3-D path at the rows' times, to its depth's uncertainty (the weak direction).
    error = np.linalg.norm(bf.model_position - _shot(scene), axis=1)
    assert np.mean(error) < 0.02
    assert bf.depth["fixed"] and bf.depth["along_axis_m"] < 0.02
    assert "rms_px" in bf.to_json() and "rms_m" not in bf.to_json()


def _write_cameras(tmp_path):
    """The side camera as OpenCV's FileStorage writes it, the camera from behind in the
    short form."""
    fs = cv2.FileStorage(str(tmp_path / "side.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1920)
    fs.write("image_height", 1080)
    fs.write("camera_matrix", np.asarray(SIDE.matrix))
    fs.write("distortion_coefficients", np.zeros((1, 5)))
    fs.write("rvec", SIDE.rvec.reshape(3, 1))
    fs.write("tvec", np.asarray(SIDE.translation).reshape(3, 1))
    fs.release()
    (tmp_path / "behind.json").write_text(json.dumps({"rvec": BEHIND.rvec.tolist(),
                                                      "tvec": np.asarray(BEHIND.translation).tolist(),
                                                      "f": 1400, "w": 1920, "h": 1080}))
    return [str(tmp_path / "side.yml"), str(tmp_path / "behind.json")]


@pytest.mark.slow
def test_two_cameras_in_air_with_a_clock_offset(tmp_path, capsys):
    # The table-tennis scene as shipped (air: drag and Magnus), the shot of the physics issue
    # seen by two cameras whose clocks differ by 4 ms, 1 px of noise, through the command
    # line. The synthetic-recovery targets of the issues: e within 0.01, the spin across
    # the flight within 10%, rms within 10% of the noise; and the clock offset. Then the
    # replay from the first camera's viewpoint.
    scene = estim.load_scene("data/scenes/table_tennis.xml")
    cams = [Camera.from_opencv(c.matrix, (), c.rvec, c.translation, name=n) for c, n in ((SIDE, "side"), (BEHIND, "behind"))]
    tracks = _tracks(cams, T, _shot(scene), 1.0, seed=5, offsets=(0.0, 0.004))
    with open(tmp_path / "shot.csv", "w") as f:
        f.write("t,ball,u,v,camera\n")
        for t, (u, v), k in zip(tracks.t["pingpong"], tracks.uv["pingpong"], tracks.view["pingpong"], strict=True):
            if t >= 0:
                f.write(f"{float(t)!r},pingpong,{u:.4f},{v:.4f},{k + 1}\n")
    cameras = _write_cameras(tmp_path)
    code = main(["fit", str(tmp_path / "shot.csv"), "--camera", cameras[0], "--camera", cameras[1],
                 "--scene", "data/scenes/table_tennis.xml", "--json", "--out", str(tmp_path / "out")])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    ball = out["balls"]["pingpong"]
    assert abs(ball["e"] - TRUTH["e"]) < 0.01
    assert abs(ball["dt_camera2"] - 0.004) < 5e-4
    spin = np.asarray(ball["release"]["spin"])
    want = _across(TRUTH["spin"], TRUTH["velocity"])
    assert np.linalg.norm(_across(spin, TRUTH["velocity"]) - want) < 0.1 * np.linalg.norm(want)
    assert abs(ball["rms_px"] - 1.0) < 0.1 and ball["at_noise_floor"]  # 1 px of noise
    assert len(ball["fitted"]["t"]) == len(ball["fitted"]["position"]) == np.sum(tracks.t["pingpong"] >= 0)
    assert [c["name"] for c in out["cameras"]] == ["side", "behind"]
    assert (tmp_path / "out" / "pixels.png").is_file() and (tmp_path / "out" / "path.png").is_file()
    code = main(["replay", str(tmp_path / "shot.csv"), str(tmp_path / "out" / "fit.json"), "--camera", cameras[0],
                 "--camera", cameras[1], "--scene", "data/scenes/table_tennis.xml", "--out",
                 str(tmp_path / "replay.gif"), "--width", "320"])
    assert code == 0 and "frames at 25 fps" in capsys.readouterr().out


def _report(stderr, names=("x0", "y0", "z0")):
    corr = np.eye(len(names))
    return BallFit(ball="pingpong", values={}, stderr=dict(zip(names, stderr, strict=True)), names=names,
                   correlation=corr, rms_m=1.0, noise_m=1.0, n_obs=10, n_outliers=0, n_bounces=1, converged=True,
                   at_noise_floor=True)


@pytest.mark.parametrize("position, noise, seed", [((3.2, 0.0, 0.8), 0.0, 0), ((0.0, -5.5, 1.6), 0.0, 0),
                                                   ((0.0, -5.5, 1.6), 0.3, 4)],
                         ids=["side-exact", "behind-exact", "behind-0.3px"])
def test_a_clean_track_fits_as_well_as_a_noisy_one(position, noise, seed):
    # Exact pixels, or 0.3 px of noise, at 25 fps: the noise read from the pixels is a few
    # hundredths to tenths of a pixel, the robust scale as small, and from a start that
    # misses by pixels the fit had settled on paths that explain part of the samples and
    # call the rest outliers (30, 59 and 49 cm off). The graduated scale, and a start that
    # assumes no less than 1 px of noise, lead the fit to the path itself.
    scene = estim.load_scene("data/scenes/table_tennis.xml")
    p = estim.Params.for_ball(scene, "pingpong", e=0.894, mu_t=0.0, mu=0.385, position=np.array([-0.048, -1.6, 0.293]),
                              velocity=np.array([0.0, 5.276, 1.044]), spin=np.array([98.774, 17.958, -4.795]))
    t = np.arange(0.0, 0.6, 1 / 25)
    path = np.asarray(estim.simulate(scene, p, 0.6, ts=t).position)
    cam = Camera.look_at(position, (0.0, 0.0, 0.1), focal=1500.0, size=(1920, 1080))
    uv = np.asarray(cam.project(path)) + np.random.default_rng(seed).normal(0.0, noise, (t.size, 2))
    tracks = ImageTracks("clean", ("pingpong",), (cam,), {"pingpong": t}, {"pingpong": uv},
                         {"pingpong": np.zeros(t.size, np.int64)})
    assert tracks.noise("pingpong") < 0.5
    bf = fit_image(scene, tracks).balls["pingpong"]
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.03
    assert bf.n_outliers == 0


def _mujoco_shot_fit(view, seed, position, velocity, spin, t_end=0.6, frames=slice(None), **contact):
    """A shot of MuJoCo's physics (its drag, Magnus and soft contact: the independent engine,
    ``docs/scripts/camera_views.py``) seen by one of the camera study's views at 25 fps
    until ``t_end`` (the ``frames`` of it) with 2 px of noise (draw ``seed``), fitted with
    ``fit_image``'s defaults. Returns the fit, the true path and the restitution MuJoCo's
    contact shows."""
    sys.path.insert(0, str(ROOT / "docs" / "scripts"))
    import camera_views

    t = np.arange(0.0, t_end, 1 / camera_views.FPS)
    path, e = camera_views.mujoco_shot(position, velocity, spin, t, **contact)
    t, path = t[frames], path[frames]
    cam = camera_views.VIEWS[view]
    uv = np.asarray(cam.project(path)) + 2.0 * np.random.default_rng(seed).normal(size=(t.size, 2))
    tracks = ImageTracks(view, ("pingpong",), (cam,), {"pingpong": t}, {"pingpong": uv},
                         {"pingpong": np.zeros(t.size, np.int64)})
    return fit_image(estim.load_scene(camera_views.SCENE), tracks).balls["pingpong"], path, e


@pytest.mark.parametrize(("wild", "read", "note", "within"), [
    ({4: (28.0, 28.0), 9: (-28.0, 28.0)}, 6.0, "2 row(s) (t = 0.160, 0.360 s)", 0.04),
    ({4: (28.0, 28.0), 9: (-28.0, 28.0), 6: (28.0, -28.0)}, 15.0, "3 row(s) (t = 0.160, 0.240, 0.360 s)", 0.03),
], ids=["two", "three"])
def test_wild_rows_are_read_past_and_the_noise_read_again(wild, read, note, within):
    """Detections 40 px off the ball (rows 4 and 9 of 15, 25 fps, 2 px of noise, a rally
    shot of estim's own physics seen at an angle; and row 6) spoil the third-difference
    windows. Two: the noise reads 8.5 px, and the fit at that level, its robust scale and
    its priors' weight set by it, lay 8.5 cm off (10-14 cm for three other noise draws; the
    same track without them 2.0 cm); the rows the fit misses by more than ``WILD`` noise
    levels are left out of a second reading, which finds the 2 px added (1-3 px), and the
    fit at it is the clean track's. Three: the noise reads 18.6 px, no row is missed by 3
    of those (the fit at that level lay 7.1 cm off); the three are missed by more than
    ``APART`` times the rms of the fit's misses of the others, and the fit at the second
    reading (3.7 px) misses the third by more than 3 of it: read again (``REREADS``), 1-3
    px, the fit 0.7 cm off when written (docs/pages/cameras.md, "Frames lost")."""
    sys.path.insert(0, str(ROOT / "docs" / "scripts"))
    import camera_views

    scene = estim.load_scene(camera_views.SCENE)
    params = estim.Params.for_ball(scene, "pingpong", e=0.856, mu_t=0.0, mu=0.223, position=np.array([0.001, -1.6, 0.248]),
                                   velocity=np.array([-0.204, 5.548, 1.203]), spin=np.array([66.333, -9.96, 28.019]))
    t = np.arange(0.0, 0.6, 1 / camera_views.FPS)
    path = np.asarray(estim.simulate(scene, params, float(t[-1]), ts=t).position)
    cam = camera_views.VIEWS["angle"]
    uv = np.asarray(cam.project(path)) + 2.0 * np.random.default_rng(0).normal(size=(t.size, 2))
    uv[list(wild)] += list(wild.values())
    tracks = ImageTracks("angle", ("pingpong",), (cam,), {"pingpong": t}, {"pingpong": uv},
                         {"pingpong": np.zeros(t.size, np.int64)})
    assert tracks.noise("pingpong") > read
    bf = fit_image(scene, tracks).balls["pingpong"]
    assert 1.0 < bf.noise_m < 3.0
    assert any(n.startswith(note) for n in bf.notes)
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < within


def test_the_second_reading_starts_from_paths_read_without_the_wild_rows():
    """Two detections about 40 px below the ball in rows 7 and 8 of 15 (a rally shot of
    estim's own physics seen from behind, 2 px of noise: the camera study's draw, seed 21's
    fourth shot) look like a bounce: the start read off the pixels bounced there, 0.32 s,
    against the shot's 0.44 s. Read without those rows, the starts bounce at 0.44 s, and
    the second pass from them ends 1.8 cm off the true path on average; from the starts
    read with them it ended 9.5 cm off (2.7 m with the study's unrounded values)."""
    sys.path.insert(0, str(ROOT / "docs" / "scripts"))
    import camera_views

    scene = estim.load_scene(camera_views.SCENE)
    params = estim.Params.for_ball(scene, "pingpong", e=0.857, mu_t=0.0, mu=0.341, position=np.array([-0.163, -1.6, 0.23]),
                                   velocity=np.array([0.379, 6.79, 1.2]), spin=np.array([71.701, -7.756, -44.811]))
    t = np.arange(0.0, 0.6, 1 / camera_views.FPS)
    path = np.asarray(estim.simulate(scene, params, float(t[-1]), ts=t).position)
    cam = camera_views.VIEWS["behind"]
    noise = np.array([[2.64, 0.83], [0.95, -0.43], [-0.12, 1.73], [1.52, 0.93], [-0.01, 2.02], [-2.18, -1.03],
                      [0.44, 2.2], [-2.4, -2.07], [-2.34, 1.42], [1.56, 3.0], [4.43, -2.33], [-0.35, -1.06],
                      [-2.11, 0.09], [-1.06, 0.29], [-0.68, -2.81]])
    uv = np.asarray(cam.project(path)) + noise
    uv[[7, 8]] += [[3.4, 39.9], [-19.7, 34.8]]
    tracks = ImageTracks("behind", ("pingpong",), (cam,), {"pingpong": t}, {"pingpong": uv},
                         {"pingpong": np.zeros(t.size, np.int64)})
    bf = fit_image(scene, tracks).balls["pingpong"]
    assert any(n.startswith("2 row(s) (t = 0.280, 0.320 s)") for n in bf.notes)
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.04


def test_a_track_run_on_to_the_floor_is_said_to_need_a_restitution_per_surface():
    """A rally shot of MuJoCo's physics not returned: it bounces on the table, flies off its
    end and lands on the floor, whose default contact keeps a small part of the normal speed
    where the table's keeps 0.83; seen from the side to 1.6 s (40 frames, 2 px). estim's laws
    hold one e for every surface: the fit reads one between the two, far from the table's,
    and says that its path bounces on the table and then on the floor, surfaces the scene
    declares different. The rows before the ball reaches the floor fit as a rally shot does:
    e to 0.03 of MuJoCo's table contact, the path to 6 cm, and no such note (the camera
    study's draw, seed 1: 10.2 cm and e 0.36 for the whole track, 4.3 cm and 0.845 before
    the floor, written)."""
    shot = dict(position=np.array([-0.0898, -1.6, 0.2687]), velocity=np.array([0.1262, 6.5838, 1.1788]),
                spin=np.array([0.4559, -8.4954, 33.9313]), blunt_drag=0.4255 / 2, damping=0.0462, friction=0.2445)
    bf, path, e = _mujoco_shot_fit("side", 0, t_end=1.6, **shot)
    assert path[:, 2].min() < -0.7  # on the floor, 0.76 m below the table's top
    assert [m["surfaces"] for m in bf.missing_physics if "surfaces" in m] == [["table", "floor"]]
    assert any(n.startswith("the fitted path bounces on 'table' and then on 'floor'") for n in bf.notes)
    assert abs(bf.values["e"] - e) > 0.3
    before = int(np.flatnonzero(path[:, 2] < -0.3)[0])
    bf, path, e = _mujoco_shot_fit("side", 0, t_end=1.6, frames=slice(0, before), **shot)
    assert not any("surfaces" in m for m in bf.missing_physics)
    assert abs(bf.values["e"] - e) < 0.03
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.06


@pytest.mark.parametrize(("before", "after", "note", "within"), [
    (0, 2, "2 row(s) at the track's ends (t = 0.360, 0.400 s)", 0.03),
    (1, 0, "1 row(s) at the track's ends (t = -0.040 s)", 0.03),
    (1, 2, "3 row(s) at the track's ends (t = -0.040, 0.360, 0.400 s)", 0.03),
    (0, 0, None, 0.03),
], ids=["returned", "incoming", "both", "clean"])
def test_rows_past_a_hit_at_the_track_s_ends_are_fitted_without(before, after, note, within):
    """A drive of estim's own physics (the camera study's seed 3, its first drive: 15 m/s
    with 400 rad/s of topspin, 9 frames at 25 fps), seen from the side with 2 px of noise,
    tracked on past the opponent's return (hit half a frame after its last frame, the ball
    goes back at 8 m/s: 2 rows more), or from a row before the release (the incoming ball
    at 8 m/s, hit half a frame before it). With the return's rows in the fit its path lay
    7.2 cm off at 2.7 px rms (no note); the fit misses the last row by more than ``WILD``
    noise levels and ``HIT_APART`` times the noise its other misses show, and without it
    the row before (``HITS``): 1.4 cm off when written, the track's own without them. The
    incoming row was missed as much (1.4 cm off before, 1.0 now, the row named). With
    both, the fit without the last row passed through the first (the release) and missed
    the second by 86 px, the fit 12.6 cm off: an end row goes where the fit misses it or
    the row next to it (1.0 cm). The track without them keeps every row (1.4 cm)."""
    sys.path.insert(0, str(ROOT / "docs" / "scripts"))
    import camera_views

    scene = estim.load_scene(camera_views.SCENE)
    position, velocity = np.array([-0.0714271, -1.6689062, 0.4513921]), np.array([-0.7953602, 14.9483784, 0.2878547])
    params = estim.Params.for_ball(scene, "pingpong", e=0.8704385, mu_t=0.0, mu=0.3742278, position=position,
                                   velocity=velocity, spin=np.array([-408.1264306, -35.366543, 39.685269]))
    dt = 1 / camera_views.FPS
    t = np.arange(9) * dt
    path = np.asarray(estim.simulate(scene, params, float(t[-1]), ts=t).position)
    hit = path[-1] + (path[-1] - path[-2]) / 2
    back = [hit + np.array([0.25, -8.0, 1.5]) * (k - 0.5) * dt + [0.0, 0.0, -9.81 / 2 * ((k - 0.5) * dt) ** 2]
            for k in range(1, after + 1)]
    came = [position - velocity * dt / 2 + np.array([0.2, 8.0, -1.0]) * dt / 2] * before
    times = np.concatenate([-dt * np.arange(before, 0, -1), t, t[-1] + dt * np.arange(1, after + 1)])
    cam = camera_views.VIEWS["side"]
    rows = np.concatenate([np.reshape(came, (-1, 3)), path, np.reshape(back, (-1, 3))])
    uv = np.asarray(cam.project(rows)) + 2.0 * np.random.default_rng(0).normal(size=(times.size, 2))
    tracks = ImageTracks("side", ("pingpong",), (cam,), {"pingpong": times}, {"pingpong": uv},
                         {"pingpong": np.zeros(times.size, np.int64)})
    bf = fit_image(scene, tracks).balls["pingpong"]
    ends = [n for n in bf.notes if "at the track's ends" in n]
    assert (ends == []) if note is None else (len(ends) == 1 and ends[0].startswith(note))
    assert np.mean(np.linalg.norm(bf.model_position[before:before + t.size] - path, axis=1)) < within


@pytest.mark.parametrize("seed", [3, 5])
def test_a_start_read_below_the_table_is_lifted_out_of_it(seed):
    """Seen from far behind, the start read off the pixels has its release below the
    table's top (a first flight of 11 frames seen end-on, its depth fixed only by the
    bounce's ray). With noise draw 5 the fit refused to start there ("starts inside
    'table'": a shot left without an answer); with draw 3 the start lay just under the
    table and the fit found a path under it that bounces on the floor, 3 m off. A start is
    now moved along the rays to the nearest depth whose release and first flight lie
    outside the solids (``_released_outside``): both fits end above the table, in the
    truth's basin (from the true values the fit of draw 3 ends on the same path, 21 cm
    off: what one camera from behind fixes of this shot)."""
    bf, path, _ = _mujoco_shot_fit("behind", seed, (-0.15, -1.6, 0.18), (0.45, 6.4, 1.1), (90.0, 17.0, 30.0),
                                   blunt_drag=0.25, damping=0.06, friction=0.4)
    assert bf.values["z0"] > 0.0 and np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.25


def test_a_side_view_does_not_read_a_spin_no_ball_has():
    """A rally shot of MuJoCo's physics seen from the side (the camera study's seed 0, its
    fourth shot; noise draw 3). Without the scene's prior on the spin (0 +- 1000 rad/s per
    axis: the spins of play reach 630-800 rad/s) the fit read 1,403 rad/s about the
    flight's own axis, which bent the path along the lens, 6.1 cm off, and its spin across
    the flight 400 rad/s from MuJoCo's; with it, the largest component is 220 rad/s, the
    spin across the flight about 60 rad/s from MuJoCo's (whose Magnus force is stronger
    than estim's at a given spin) and the path 2.6 cm off."""
    spin = np.array([77.259, -8.154, -8.527])
    velocity = np.array([-0.251, 6.901, 1.074])
    bf, path, _ = _mujoco_shot_fit("side", 3, (-0.261, -1.6, 0.208), velocity, spin,
                                   blunt_drag=0.553 / 2, damping=0.046, friction=0.353)
    fitted = np.array([bf.values[f"spin_{c}"] for c in "xyz"])
    assert np.max(np.abs(fitted)) < 600.0
    assert np.linalg.norm(_across(fitted, velocity) - _across(spin, velocity)) < 100.0
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.04


def test_a_chop_whose_lift_is_a_textbook_balls_is_fitted_from_the_side():
    """A chop of MuJoCo's physics (the camera study's first chop, ``--kind chop --magnus
    0.76``: 300 rad/s of backspin, 22 frames, one bounce), its Magnus coefficient 0.76 so
    that its lift is about the textbook curve estim holds (at MuJoCo's default, 1, it is
    1.6-1.9 times that, and such chops were fitted 18 cm off from the side on average).
    MuJoCo's angular drag halves the spin in a quarter of a second, which estim's constant
    spin cannot follow: the fit reads the backspin as backspin, at about half the release's
    (six noise draws: 6.3-8.3 cm, 129-143 rad/s about x)."""
    spin, velocity = np.array([301.7, 23.0, 7.0]), np.array([-0.483, 8.253, 1.869])
    bf, path, e = _mujoco_shot_fit("side", 0, (0.137, -2.53, 0.016), velocity, spin, t_end=0.88,
                                   blunt_drag=0.587 / 2, damping=0.0513, friction=0.2, magnus=0.76)
    assert e is not None and bf.n_bounces == 1
    fitted = np.array([bf.values[f"spin_{c}"] for c in "xyz"])
    assert np.dot(_across(fitted, velocity), _across(spin, velocity)) > 0.0
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.10


@pytest.mark.parametrize("seed", [3, 4, 10])
def test_a_fit_that_leans_on_a_prior_or_misses_its_pixels_starts_again_along_the_rays(seed):
    """The ball comes at the camera (far behind the end it flies to): with noise draws 3, 4
    and 10, one start's fit ran to e = 0.02, 0.22 or into the net (a robust loss of 3.3 per
    pixel coordinate) and the best fit ended 3 m, 1 m and 3 m off (beyond the far end,
    bouncing on the floor, for 3 and 10). Such a fit is doubted (``_doubted``) and the
    start moved along the rays by 1.25 and 0.8 (``DEEPER``): each now ends within 11 cm
    of the truth, e within 0.05 of what MuJoCo's contact shows."""
    bf, path, e = _mujoco_shot_fit("front", seed, (0.22, -1.6, 0.2), (0.12, 6.4, 1.4), (25.0, 1.5, 38.0),
                                   blunt_drag=0.23, damping=0.043, friction=0.27)
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.12 and abs(bf.values["e"] - e) < 0.05


def test_a_start_that_read_a_short_drop_is_re_aimed_at_its_bounce():
    """The camera study's first shot of estim's physics (seed 0) seen from in front, the ball
    coming at the camera: the start read its first flight as a short drop near the bounce
    (released 2.5 m nearer the camera than the truth, hardly moving towards it). The start's
    fits were doubted, and moved along the rays with their velocity scaled (``scaled``) the
    only one to reach a low loss was a path beyond the far end bouncing on the floor, 3 m
    off (its loss 3.85, the truth's 3.54). Moved with its first flight re-aimed at the bounce
    (``Reconstruction.released_at``) the start reaches the truth's path."""
    sys.path.insert(0, str(ROOT / "docs" / "scripts"))
    import camera_views

    scene = estim.load_scene(camera_views.SCENE)
    t = np.arange(0.0, 0.6, 1 / camera_views.FPS)
    _, path = camera_views.draw_shot(np.random.default_rng(0), scene, t)
    cam = camera_views.VIEWS["front"]
    uv = np.asarray(cam.project(path)) + 2.0 * np.random.default_rng([0, 1]).normal(0.0, 1.0, (t.size, 2))
    tracks = ImageTracks("front", ("pingpong",), (cam,), {"pingpong": t}, {"pingpong": uv},
                         {"pingpong": np.zeros(t.size, np.int64)})
    bf = fit_image(scene, tracks).balls["pingpong"]
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.1


def test_the_depth_report_projects_the_release_covariance_on_the_axis():
    cam = Camera.look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), focal=1000.0, size=(640, 480))  # looks along +y
    fixed = _depth_report(_report([0.001, 0.004, 0.002]), cam)
    assert fixed["fixed"] and fixed["along_axis_m"] == pytest.approx(0.004)
    assert fixed["across_axis_m"] == pytest.approx(math.sqrt((0.001**2 + 0.002**2) / 2))
    open_ = _depth_report(_report([0.001, 2 * DEPTH_LIMIT, 0.002]), cam)
    assert not open_["fixed"] and "known only to 10.0 cm" in open_["note"]
    unknown = _depth_report(_report([0.001, float("nan"), 0.002]), cam)
    assert not unknown["fixed"] and "cannot be determined" in unknown["note"]


def test_a_second_path_that_fits_as_well_is_reported():
    """Another start's fit within ``AMBIGUOUS`` of the chosen one's loss, with a path more
    than ``DEPTH_LIMIT`` away on average, is reported with its distance and a note; one
    that fits worse, or lies near, is not."""
    path = np.zeros((5, 3))
    chosen = SimpleNamespace(model_position=path, values={"e": 0.88})

    def rival(shift, e=0.8):
        return SimpleNamespace(model_position=path + [0.0, shift, 0.0], values={"e": e})

    alt = _alternative(chosen, 10.0, [(rival(0.3), 11.5)])
    assert alt["distance_m"] == pytest.approx(0.3) and alt["loss_difference"] == pytest.approx(1.5)
    assert alt["values"] == {"e": 0.8} and "30 cm" in alt["note"] and "e = 0.800" in alt["note"]
    assert _alternative(chosen, 10.0, [(rival(0.3), 10.0 + AMBIGUOUS)]) is None
    assert _alternative(chosen, 10.0, [(rival(0.5 * DEPTH_LIMIT), 10.5)]) is None
    assert _alternative(chosen, 10.0, [(rival(0.2), 11.9), (rival(0.4), 10.1)])["distance_m"] == pytest.approx(0.4)
    assert "about as well (robust loss -1.50)" in _alternative(chosen, 10.0, [(rival(0.3), 8.5)])["note"]
    # A doubted rival far below the chosen loss (``_choose`` set it aside): it explains the
    # pixels better, and the note says so.
    assert "better (robust loss -6.26) but was set aside" in _alternative(chosen, 10.0, [(rival(0.3), 3.74)])["note"]


def test_of_paths_the_pixels_cannot_tell_apart_the_one_nearer_the_start_is_kept():
    """``_choose``: of the fits within ``AMBIGUOUS`` of the least loss, the one whose path
    lies nearest the start path read through the physics (NaN rows skipped); a fit nearer
    the start but more than ``AMBIGUOUS`` above the least loss is not kept. A fit whose
    path lies more than ``DRIFT`` from the start is doubted, and kept only where every fit
    is, whatever its loss."""
    start = SimpleNamespace(position=np.array([[0.0, 0.0, 0.2], [0.0, 1.0, 0.1], [np.nan] * 3]))

    def fit(shift, loss):
        return (SimpleNamespace(model_position=start.position + [0.0, shift, 0.0], values={}, prior={}, n_obs=10), loss)

    near, far = fit(0.05, 10.0), fit(0.9, 9.0)
    assert DRIFT == 1.0
    assert _choose([far, near], start) is near
    assert _choose([far, fit(0.05, 9.0 + AMBIGUOUS)], start) is far
    assert _choose([fit(0.5, 9.5), near, far], start) is near
    drifted = fit(2.9, 5.0)
    assert _choose([drifted, near], start) is near
    assert _choose([drifted, fit(3.5, 9.0)], start) is drifted


def test_a_fit_of_positions_refuses_camera_offsets():
    scene = estim.load_scene("data/scenes/table_tennis.xml")
    t = np.arange(0.0, 0.3, 0.01)
    pos = np.stack([0 * t, t, 0.3 - 4.9 * t**2], axis=1)
    with pytest.raises(ValueError, match=r"dt_camera2.*cameras this data does not have"):
        estim.fit(scene, {"pingpong": (t, pos)}, free=("e", "dt_camera2"))


def test_too_few_rows_are_refused_in_pixels():
    """A track with fewer rows than a fit needs is refused naming its rows of pixels (the
    3-D start's samples are not what the user gave)."""
    scene = estim.load_scene("data/scenes/table_tennis.xml").with_air(None)
    tracks = _tracks((SIDE,), T[:20:4], _shot(scene)[:20:4], 1.0, seed=4)
    with pytest.raises(ValueError, match=r"'pingpong': only 5 rows with both pixels; a fit needs at least 6"):
        fit_image(scene, tracks)


@pytest.mark.parametrize(("view", "seed"), [("side", 0), ("angle", 0), ("behind", 1)])
def test_a_fast_shot_of_six_frames_is_fitted(view, seed):
    """A drive at 12 m/s with 300 rad/s of topspin (MuJoCo's flight) tracked for six frames
    at 25 fps, its bounce among them: a shot hit hard is that short from hit to hit. It was
    refused (a fit needed 8 rows); 12 pixel coordinates hold the 11 parameters, and the fit
    finds the bounce on the table and the path within 5 cm (2.4 and 2.5 cm). From behind,
    with noise draw 1, no bounce time rebounded in the start (three rows a flight ran off
    along their rays) and the fit ended 6.8 m off, behind the camera; its start now has the
    bounce (``estim.tracks._reconstruct``: sixteenths of a frame, the restitution's prior)
    and the fit ends within 7 cm (docs/pages/cameras.md, "Short tracks")."""
    bf, path, _ = _mujoco_shot_fit(view, seed, (0.1, -1.5, 0.3), (0.0, 12.0, 1.3), (-300.0, 10.0, 40.0), t_end=0.4,
                                   frames=slice(3, 9), blunt_drag=0.25, damping=0.045, friction=0.3)
    assert bf.n_obs == 6 and bf.contacts == (("table", "+z"),)
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < (0.07 if view == "behind" else 0.05)


@pytest.mark.parametrize("fy, distortion", [(1400.0, ()), (1330.0, (-0.3, 0.1, 0.002, -0.001, 0.0))],
                         ids=["pinhole", "distorted"])
def test_the_replay_from_a_calibrated_camera_puts_the_ball_where_the_camera_sees_it(fy, distortion):
    # MuJoCo renders the fitted ball through a pinhole from the calibrated camera's pose,
    # resampled along each pixel's ray; the ball's centre in the picture is the calibrated
    # camera's projection (OpenCV's forward formula, not the resampling's inverse) of the
    # fitted position, with the principal point off the centre, and, in the second case,
    # fx and fy 5% apart and a strong barrel distortion.
    path = "data/scenes/table_tennis.xml"
    cam = Camera.from_opencv([[1400, 0, 1010], [0, fy, 490], [0, 0, 1]], distortion, SIDE.rvec, SIDE.translation,
                             size=(1920, 1080))
    pinhole = Camera.from_opencv([[1400, 0, 1010], [0, fy, 490], [0, 0, 1]], (), SIDE.rvec, SIDE.translation)
    view = calibrated_view(cam)
    values = {"e": TRUTH["e"], "mu": TRUTH["mu"], **dict(zip(("x0", "y0", "z0"), TRUTH["position"], strict=True)),
              **dict(zip(("vx0", "vy0", "vz0"), TRUTH["velocity"], strict=True))}
    t = np.arange(0.0, 0.5, 0.01)
    motion = replay_motion(estim.load_scene(path).with_air(None), {"balls": {"pingpong": values}},
                           {"pingpong": (t, np.full((t.size, 3), np.nan))}, fps=25)
    width, scale = 960, 960 / 1920
    frames = render_frames(calibrated_model(path, view), motion, width=width, height=540, camera=view,
                           caption=False, ghosts=False)
    moved = []
    for k, img in enumerate(frames):
        if k % 3:
            continue
        assert img.shape == (540, 960, 3)
        img = img.astype(float)
        orange = (img[..., 0] > 150) & (img[..., 0] > img[..., 2] + 80) & (img[..., 1] > 60)
        rows, cols = np.nonzero(orange)
        seen = np.array([cols.mean(), rows.mean()])
        # OpenCV's pixel centres at a scale of one half: u' = (u + 0.5) s - 0.5.
        p = motion.fitted["pingpong"][k]
        want = (np.asarray(cam.project(p)) + 0.5) * scale - 0.5
        radius = 1400 * scale * 0.02 / float(cam.depth(p))
        assert np.linalg.norm(seen - want) < 0.5 * radius + 1.0, (k, seen, want)
        moved.append(np.linalg.norm(want - ((np.asarray(pinhole.project(p)) + 0.5) * scale - 0.5)))
    # The distortion moves the ball by many times the tolerance near the picture's edges.
    assert max(moved) > (25.0 if distortion else -1.0)


def test_a_replay_refuses_a_camera_it_cannot_render():
    with pytest.raises(ValueError, match="image size"):
        calibrated_view(Camera.from_opencv(np.asarray(SIDE.matrix)))
    # The principal point far off the image and a distortion that folds at 0.05 of the
    # axis: the projection has no pixel of the image's in its range.
    with pytest.raises(ValueError, match="ray of none of its pixels"):
        calibrated_view(Camera.from_opencv([[1400, 0, -5000], [0, 1400, 540], [0, 0, 1]], (-50.0, 0, 0, 0, 0),
                                           size=(1920, 1080)))


def test_mujoco_as_the_camera():
    # A closed loop through pixels estim did not draw: MuJoCo renders the shot through a
    # camera of its own (pos, xyaxes, fovy in the MJCF), the ball is found in each frame
    # (MuJoCo's segmentation: the pixels of the ball's geom; their centroid), and the
    # pixels are fitted through the OpenCV camera that MuJoCo's describes (focal length
    # (h / 2) / tan(fovy / 2); MuJoCo's pixel (0, 0) is a corner, OpenCV's a centre).
    scene = estim.load_scene("data/scenes/table_tennis.xml").with_air(None)
    path = _shot(scene)
    w, h, fovy = 960, 540, 40.0
    pos, target = np.array([2.8, -0.6, 0.9]), np.array([0.0, 0.0, 0.1])
    forward = (target - pos) / np.linalg.norm(target - pos)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    xml = open("data/scenes/table_tennis.xml").read().replace(
        "<worldbody>", f'<worldbody><camera name="film" pos="{" ".join(map(str, pos))}" '
                       f'xyaxes="{" ".join(map(str, [*right, *up]))}" fovy="{fovy}"/>', 1)
    model = mujoco.MjModel.from_xml_string(xml.replace('offwidth="960" offheight="540"', f'offwidth="{w}" offheight="{h}"'))
    data = mujoco.MjData(model)
    ball = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "pingpong")
    renderer = mujoco.Renderer(model, h, w)
    renderer.enable_segmentation_rendering()
    uv = np.full((T.size, 2), np.nan)
    for k, p in enumerate(path):
        data.qpos[:3] = p
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera="film")
        rows, cols = np.nonzero(renderer.render()[..., 0] == ball)
        if rows.size:
            uv[k] = (cols.mean(), rows.mean())  # pixel centres: OpenCV's convention already
    renderer.close()
    assert np.isfinite(uv).all()
    focal = (h / 2) / np.tan(np.radians(fovy) / 2)
    cam = Camera.look_at(pos, target, focal=focal, size=(w, h), name="film")
    tracks = estim.ImageTracks("mujoco", ("pingpong",), (cam,), {"pingpong": T}, {"pingpong": uv},
                               {"pingpong": np.zeros(T.size, np.int64)})
    bf = fit_image(scene, tracks).balls["pingpong"]
    error = np.linalg.norm(bf.model_position - path, axis=1)
    assert bf.rms_m < 0.5 and np.mean(error) < 0.01, (bf.rms_m, np.mean(error))
    assert abs(bf.values["e"] - TRUTH["e"]) < 0.02


@pytest.mark.parametrize("late", [0.6, 12.34])
def test_a_track_on_a_late_clock_is_released_at_its_first_row(tmp_path, late):
    """The bench's one-camera shot on a later clock (every time ``late`` s later: a video's,
    or a shot cut from a rally): `estim fit --camera` takes the release at the first row
    and says so, and fits what it fits on the release's own clock (the same values to
    rounding). Before, released at t = 0, the model flew unseen up to the first row: 0.6 s
    late the fit ended 1.3 m off there, and 12.34 s late the start read the release 12 s
    back along the first flight, a kilometre under the floor, and the fit refused it."""
    from estim.fitting._job import fit_image_csv

    track, camera = camera_shot(str(tmp_path))
    lines = open(track).read().splitlines()
    shifted_track = tmp_path / "late.csv"
    shifted_track.write_text("\n".join([lines[0]] + [f"{float(a) + late!r},{rest}" for a, rest in
                                                      (row.split(",", 1) for row in lines[1:])]) + "\n")
    scene = estim.load_scene("data/scenes/table_tennis.xml")
    (on_time, _), (shifted, _) = (fit_image_csv(p, [camera], scene) for p in (track, shifted_track))
    a, b = on_time.balls["pingpong"], shifted.balls["pingpong"]
    assert f"the track's clock starts at t = {late:.3f} s" in b.notes[0]
    assert not any("clock starts" in note for note in a.notes)
    assert b.values["t0"] == pytest.approx(late, abs=1e-9) and a.values["t0"] == 0.0
    for name in ("e", "mu", "x0", "y0", "z0", "vx0", "vy0", "vz0"):
        assert b.values[name] == pytest.approx(a.values[name], abs=1e-6), name


@pytest.mark.parametrize("seed", [12, 20, 30])
def test_a_fit_that_runs_metres_from_its_start_is_doubted_and_not_kept(seed):
    """A drive at 13 m/s with topspin, seen from in front (11 frames, the ball coming at the
    camera). With noise draws 12, 20 and 30 the fit ended 2.5-2.6 m off: a path released
    5 m behind the table, below its top, that passes under it and bounces on the floor,
    at a robust loss up to 3 below the truth's basin (MuJoCo's flight is not estim's
    model). With 12 both starts' fits ran there, 2.4 m from the start read off the pixels
    (whose bounce on the table held its depth); with 20 and 30 a fit from the first start
    lay 5 cm from the truth, and a start moved along the rays found the floor's path. A
    fit more than ``DRIFT`` (1 m) from the start is now doubted (the moved starts run),
    and a doubted fit is kept only where every fit is: each ends within 10 cm of the truth
    (31 draws of this shot: all within 7.2 cm; before, these three 2.5 m off)."""
    bf, path, _ = _mujoco_shot_fit("front", seed, (-0.06, -1.53, 0.3), (-0.15, 13.3, 1.5), (-220.0, -4.0, 52.0),
                                   t_end=0.44, blunt_drag=0.25, damping=0.0456, friction=0.36)
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.1


@pytest.mark.parametrize("seed", [7, 11, 14])
def test_a_fit_that_rebounds_off_the_net_is_no_answer(seed):
    """A rally shot seen as television films one: 10 m behind the end the ball leaves,
    3.5 m up, through a long lens (the study's "broadcast" view). From there a ball that
    comes back off the net looks much like one that flies on after its bounce: with noise
    draws 7, 11 and 14 both starts' fits ran towards the camera until the ball met the
    net and came back, 97-120 cm off (3 of 16 draws of this shot). The fit now reports the
    solid and face of each impact (``BallFit.contacts``), and a path that rebounds off a
    solid on which no start bounces is no path (``_fit_starts``: its loss infinite, so
    the starts moved along the rays run): each ends on the table's top, within 10 cm of
    the truth (2.9-4.9 cm; of the 16 draws, none beyond 18 cm)."""
    bf, path, _ = _mujoco_shot_fit("broadcast", seed, (0.3, -1.6, 0.264), (-0.042, 6.87, 1.37), (-38.5, -2.9, -41.8),
                                   blunt_drag=0.294, damping=0.0425, friction=0.35)
    assert bf.contacts == (("table", "+z"),)
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.1


@pytest.mark.parametrize("seed", [1, 4])
def test_a_fit_that_ran_into_the_net_runs_again_with_the_net_set_aside(seed):
    """A serve of MuJoCo's physics seen from in front (the camera study's fourth serve of
    seed 0, its values to the last digit: MuJoCo's soft contact sends a copy rounded to
    four digits into the net), passing 4 cm over the net with 250 rad/s of backspin. Its
    start lies within 3 cm of its path with both bounces, but the fits ran low into the
    net's face and settled there, 31-34 cm off (6 of 8 noise draws, these two among them):
    a path that rebounds off the net is no path, and none was left. The starts now run
    again with what no start bounces on set aside (``Scene.set_aside``: the net and the
    floor), polished in the whole scene from where they end (``_fit_starts``): the path
    within 2.1 cm on 7 of the 8 draws, its two bounces on the table."""
    bf, path, _ = _mujoco_shot_fit(
        "front", seed, (-0.33001154853058723, -1.5700368908249076, 0.17438044426706123),
        (-0.42356097908178303, 4.602693070811222, -1.7514032720715917),
        (251.79198252337247, -47.73894694531199, -50.15721130605692), t_end=0.74,
        blunt_drag=0.4946407942777138 / 2, damping=0.03933056601353649, friction=0.2711812439034581)
    assert bf.contacts == (("table", "+z"), ("table", "+z"))
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.04


def test_a_ball_that_clips_the_net_is_answered_and_said_to_miss():
    """A lob in estim's own physics that clips the net's top (its centre 1.9 cm above it,
    at 0.65 s) and flies on high, seen from the side at 25 fps (25 frames, 2 px). The
    starts have no bounce on a net (no upward face 2 mm wide holds one), so a start's
    parabola spans the clip and falls at about 3 g; the fit used to run the check of a
    track's units on that start, and refused the shot as one in feet (every one of 8 noise
    draws). The check is for tracks in metres; the pixels are answered: a path (here about
    60 cm off) whose rms, several times the noise, says it misses them."""
    scene = estim.load_scene("data/scenes/table_tennis.xml")
    p = estim.Params.for_ball(scene, "pingpong", e=0.864, mu_t=0.0, mu=0.23, position=np.array([-0.395, -2.785, 0.259]),
                              velocity=np.array([0.784, 4.933, 4.564]), spin=np.array([-197.6, 5.0, 61.7]))
    t = np.arange(25) / 25.0
    run = estim.simulate(scene, p, 1.0, ts=t)
    (contact,) = np.asarray(run.events.position)[: int(run.events.count)]
    assert abs(contact[1]) < 0.02 and contact[2] > 0.1525  # the net's top, not the table
    side = Camera.look_at((3.2, 0.0, 0.8), (0.0, 0.0, 0.1), focal=1500.0, size=(1920, 1080), name="side")
    bf = fit_image(scene, _tracks((side,), t, np.asarray(run.position), 2.0, seed=0)).balls["pingpong"]
    assert not bf.at_noise_floor and bf.rms_m > 3 * 2.0
    assert any("above the noise level" in n for n in bf.notes)


@pytest.mark.parametrize("seed", [20, 31, 42])
def test_a_path_the_camera_could_not_have_seen_is_no_answer(seed):
    """A drive at 13.6 m/s with 330 rad/s of topspin, seen from in front (10 frames). With
    noise draws 20, 31 and 42 every fit was doubted, and the one kept, of least loss, was
    a path released 5 m behind the table below its top, that passes under the table and
    bounces on the floor, 2.6 m off: the front camera, looking down on the table, could not
    have seen the ball there. A fit whose path lies behind a box whose top a ball bounces
    on, as seen from its camera, at more than half of its rows, or behind the camera at
    any row, is now no path (``_hidden``: its loss infinite): each fit ends within 12 cm of
    the truth (of 46 draws of this shot, 4 ended 2.6 m off with the camera's own check
    alone; now one, 4.8 m off, at a path 40 cm before the lens, all its fits doubted)."""
    bf, path, _ = _mujoco_shot_fit("front", seed, (0.06, -1.66, 0.38), (-0.3, 13.6, 1.4), (-330.0, -13.0, 82.0),
                                   t_end=0.4, blunt_drag=0.28, damping=0.052, friction=0.22)
    assert np.mean(np.linalg.norm(bf.model_position - path, axis=1)) < 0.12
