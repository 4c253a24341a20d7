"""Replay: MuJoCo frames (projection of the fitted balls, halos of measured samples), the
matplotlib side view, GIF frame counts and durations, MP4 through ffmpeg, ``estim replay``.

The scene is the seed staircase; the "fit" is written by hand with balls spread out in x so
that none hides another, and the "measured" samples float 0.15 m above the release height,
where no fitted ball ever is, so a halo can be told from a ball. Images are small and
replays short: the costs are one compiled single-ball simulation (shared with
``estim simulate``) and a few software-rendered frames.
"""

from __future__ import annotations

import json
import os
import stat
import sys
from pathlib import Path

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from PIL import Image

import estim
from estim.app._cli import main
from estim.show import _replay
from estim.show._plots import COLOURS

SCENE = str(Path(__file__).resolve().parents[1] / "data" / "scenes" / "stairs.xml")
G = 9.81
FIT = {
    "bocce": {"e": 0.58, "mu_t": 0.95, "vx0": 0.5, "x0": -0.2, "z0": 1.73},
    "golf": {"e": 0.72, "mu_t": 0.97, "vx0": 1.0, "x0": 0.0, "z0": 1.70},
    "pingpong": {"e": 0.80, "mu_t": 0.93, "vx0": 1.5, "x0": 0.15, "z0": 1.69},
}
LIFT = 0.15  # the measured samples float this far above the release height
T_END = 0.6
W, H = 320, 180
# Close to the balls, so that each covers many pixels.
CAMERA = estim.SideCamera(lookat=(0.35, 0.0, 1.55), distance=2.0, azimuth=90.0, elevation=-10.0,
                          fovy=30.0)
PURE = {"bocce": (1.0, 0.0, 0.0), "golf": (0.0, 1.0, 0.0), "pingpong": (0.0, 0.0, 1.0)}


def tracks_dict(t_end=T_END, rate=60.0):
    t = np.arange(0.0, t_end + 1e-9, 1.0 / rate)
    out = {}
    for b, v in FIT.items():
        pos = np.stack([v["x0"] + v["vx0"] * t, np.full_like(t, np.nan), np.full_like(t, v["z0"] + LIFT)], 1)
        out[b] = (t, pos)
    return out


@pytest.fixture(scope="module")
def motion(stairs):
    return estim.replay_motion(stairs, {"balls": FIT}, tracks_dict(), fps=10)


@pytest.fixture(scope="module")
def gl_camera():
    """MuJoCo's own OpenGL camera for CAMERA: the independent projection."""
    model = mujoco.MjModel.from_xml_path(SCENE)
    model.vis.global_.fovy = CAMERA.fovy
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    with mujoco.Renderer(model, H, W) as renderer:
        renderer.update_scene(data, camera=CAMERA.to_mjv())
        scn = renderer.scene
        # The two eyes of MuJoCo's stereo pair straddle the camera; mono rendering uses
        # their average.
        cam = mujoco.mjv_averageCamera(scn.camera[0], scn.camera[1])
    return {k: np.array(getattr(cam, k), dtype=np.float64) for k in
            ("pos", "forward", "up", "frustum_center", "frustum_bottom", "frustum_top", "frustum_near")}


def gl_project(cam, p):
    """(column, row) of world point p through MuJoCo's GL camera (perspective frustum)."""
    fwd, up = cam["forward"], cam["up"]
    right = np.cross(fwd, up)
    rel = np.asarray(p) - cam["pos"]
    depth = rel @ fwd
    u = (rel @ right) * cam["frustum_near"] / depth
    v = (rel @ up) * cam["frustum_near"] / depth
    top, bottom = float(cam["frustum_top"]), float(cam["frustum_bottom"])
    half_w = 0.5 * (top - bottom) * W / H
    centre = float(cam["frustum_center"])
    col = (u - (centre - half_w)) / (2 * half_w) * W
    row = (top - v) / (top - bottom) * H
    return np.array([col, row])


def pixel(img, px):
    c, r = int(px[0]), int(px[1])
    assert 0 <= c < img.shape[1] and 0 <= r < img.shape[0], f"{px} lies outside the image"
    return img[r, c].astype(float)


def frames(motion, **kw):
    return list(estim.render_frames(SCENE, motion, width=W, height=H, camera=CAMERA, caption=False, **kw))


# --------------------------------------------------------------------------- the motion


def test_frame_times():
    # floor(span * fps) + 1 frames, 1/fps apart, the first at the data's first time.
    t = estim.frame_times(0.0, 2.2, 25.0)
    assert len(t) == 56 and t[-1] == pytest.approx(2.2) and np.allclose(np.diff(t), 0.04)
    assert len(estim.frame_times(0.5, 1.0, 30.0)) == 16  # 15 intervals
    assert len(estim.frame_times(0.0, 0.99, 10.0)) == 10  # no frame after the end
    with pytest.raises(ValueError, match="fps"):
        estim.frame_times(0.0, 1.0, 0.0)


def test_motion_follows_the_fit_and_the_data(motion, stairs):
    assert motion.balls == tuple(FIT) and motion.n_frames == 7
    np.testing.assert_allclose(motion.t, np.arange(7) / 10)
    for b, v in FIT.items():
        y = stairs.ball(b).position[1]
        # Free fall until the first impact (a 0.25 m drop takes 0.226 s): the closed form.
        for k in (0, 1, 2):
            t = motion.t[k]
            want = (v["x0"] + v["vx0"] * t, y, v["z0"] - 0.5 * G * t**2)
            np.testing.assert_allclose(motion.fitted[b][k], want, atol=1e-12)
        # Measured: the 60 Hz sample at each 10 Hz frame, y (absent in the data) the model's.
        np.testing.assert_allclose(motion.measured[b][:, 0], v["x0"] + v["vx0"] * motion.t, atol=1e-12)
        np.testing.assert_allclose(motion.measured[b][:, 2], v["z0"] + LIFT)
        np.testing.assert_allclose(motion.measured[b][:, 1], y)
        # Every parameter of the registry: the fit's where it gives one, else the default.
        # (the air's parameters and the friction law's mu do not act in this scene)
        defaults = {"y0": y, "vy0": 0.0, "vz0": 0.0, "t0": 0.0, "pixel_scale": 1.0, "compression": 0.0}
        assert motion.params[b] == {**v, **defaults}
        assert motion.caption(b) == f"e = {v['e']:.3f}   mu_t = {v['mu_t']:.3f}   vx0 = {v['vx0']:.3f} m/s"


def test_dropped_sample_gives_no_halo(stairs):
    data = tracks_dict()
    t, pos = data["golf"]
    pos = pos.copy()
    pos[np.isclose(t, 0.3)] = np.nan  # the sample at frame 3 is lost
    data["golf"] = (t, pos)
    m = estim.replay_motion(stairs, {"balls": FIT}, data, fps=10)
    assert np.isnan(m.measured["golf"][3]).all()
    assert np.isfinite(m.measured["golf"][[2, 4]]).all()


def test_missing_ball_in_fit_is_named(stairs):
    fit = {"balls": {b: v for b, v in FIT.items() if b != "golf"}}
    with pytest.raises(ValueError, match="golf"):
        estim.replay_motion(stairs, fit, tracks_dict())


AIR_SCENE = str(Path(SCENE).with_name("stairs_air.xml"))
# A ping-pong ball fitted in air with every parameter the registry has (as `estim fit
# --also vz0 vy0 y0 t0 drag_coefficient spin` writes it): the replay must use them all.
AIR_FIT = {"e": 0.8, "mu_t": 0.93, "x0": -0.2, "y0": 0.28, "z0": 1.72, "vx0": 1.3, "vy0": 0.15,
           "vz0": 0.6, "t0": 0.05, "drag_coefficient": 0.6, "spin_x": 0.0, "spin_y": -60.0, "spin_z": 8.0}


def test_replay_uses_every_fitted_parameter(tmp_path):
    """fit.json with a fitted drag coefficient, spin, 3-D release state and release time:
    the replayed positions are estim.simulate's with those parameters (from t0 on; before
    it the ball waits at the release point), and far (centimetres) from a replay that
    drops the drag coefficient and the spin, as the replay used to."""
    scene = estim.load_scene(AIR_SCENE)
    names = ["e", "mu_t", "vx0", "x0", "z0", "y0", "vy0", "vz0", "t0", "drag_coefficient",
             "spin_x", "spin_y", "spin_z"]
    fit = tmp_path / "fit.json"
    fit.write_text(json.dumps({"balls": {"pingpong": {
        **AIR_FIT, "stderr": {n: 0.001 for n in names}, "rms_m": 0.001, "converged": True,
        "correlation": {"names": names, "matrix": np.eye(len(names)).tolist()}}}}))
    t = np.arange(0.0, 0.9 + 1e-9, 1 / 60)
    tracks = {"pingpong": (t, np.full((t.size, 3), 0.5))}
    motion = estim.replay_motion(scene, str(fit), tracks, fps=20)
    v = AIR_FIT
    assert motion.params["pingpong"] == {**v, "lift_factor": 1.0, "pixel_scale": 1.0,
                                         "compression": 0.0}  # (defaults: not in this fit)
    assert motion.free["pingpong"] == tuple(names)
    caption = motion.caption("pingpong")
    for part in ("vy0 = 0.150 m/s", "drag_coefficient = 0.600", "spin_y = -60.000 rad/s"):
        assert part in caption, caption

    def simulated(drag, spin):
        p = estim.Params.for_ball(scene, "pingpong", e=v["e"], mu_t=v["mu_t"],
                                  position=(v["x0"], v["y0"], v["z0"]), velocity=(v["vx0"], v["vy0"], v["vz0"]),
                                  drag_coefficient=drag, spin=spin)
        after = motion.t >= v["t0"]
        ts = motion.t[after] - v["t0"]
        return after, np.asarray(estim.simulate(scene, p, float(ts[-1]), ts=jnp.asarray(ts)).position)

    after, want = simulated(v["drag_coefficient"], (v["spin_x"], v["spin_y"], v["spin_z"]))
    got = motion.fitted["pingpong"]
    # The replay samples the dense solution of one simulation; estim.simulate here the
    # solution at the sample times: the same ODE solution, to its interpolation (1e-9 m).
    np.testing.assert_allclose(got[after], want, atol=1e-9)
    np.testing.assert_array_equal(got[~after], np.tile([v["x0"], v["y0"], v["z0"]], (int((~after).sum()), 1)))
    _, old = simulated(0.47, (0.0, 0.0, 0.0))  # what the replay showed before
    assert np.max(np.linalg.norm(old - want, axis=1)) > 0.01


def test_replay_refuses_a_spin_in_a_vacuum(stairs):
    fit = {"balls": {b: dict(v, spin_y=(30.0 if b == "golf" else 0.0)) for b, v in FIT.items()}}
    with pytest.raises(ValueError, match="'golf'.*spin_y = 30.*scene with air"):
        estim.replay_motion(stairs, fit, tracks_dict())


def test_replay_reads_the_old_fit_json_keys(stairs):
    """A fit.json written before the registry (its 11 parameter keys, no spin_x, spin_z)
    replays as before, with the values it gives."""
    old = {b: dict(v, vz0=0.0, t0=0.0, y0=stairs.ball(b).position[1], vy0=0.0, drag_coefficient=0.47,
                   spin_y=0.0) for b, v in FIT.items()}
    m = estim.replay_motion(stairs, {"balls": old}, tracks_dict(), fps=10)
    for b in FIT:
        np.testing.assert_array_equal(m.fitted[b], estim.replay_motion(stairs, {"balls": FIT}, tracks_dict(),
                                                                        fps=10).fitted[b])


# --------------------------------------------------------------------------- MuJoCo frames


def test_camera_projection_matches_mujoco(gl_camera, motion):
    for b in motion.balls:
        for p in (motion.fitted[b][3], motion.measured[b][3]):
            # MuJoCo keeps its GL camera in float32: agreement to a thousandth of a pixel.
            np.testing.assert_allclose(CAMERA.project(p, W, H), gl_project(gl_camera, p), atol=1e-3)


def test_fitted_balls_at_their_projected_pixels(gl_camera, motion):
    """Each ball's own colour, and only it, at the pixel where MuJoCo's camera projects it.

    With pure red, green and blue balls the check is unambiguous: the ball's channel
    dominates there. With the default colours, shading aside, the pixel is the ball's
    colour times a brightness plus some white (diffuse and specular light)."""
    pure = frames(motion, colours=PURE, ghosts=False)
    plain = frames(motion, ghosts=False)
    colours = _replay.ball_colours(SCENE, motion.balls)
    for k in (0, 3, 6):
        for b in motion.balls:
            px = gl_project(gl_camera, motion.fitted[b][k])
            p = pixel(pure[k], px)
            ch = int(np.argmax(PURE[b]))
            others = [i for i in range(3) if i != ch]
            assert p[ch] > 60 and p[ch] > 1.8 * max(p[others]), (k, b, p)
            # Default colours: p ~ s c + w (1, 1, 1), s > 0.5, w >= 0.
            c = colours[b] * 255
            A = np.stack([c, np.ones(3)], 1)
            (s, w), *_ = np.linalg.lstsq(A, pixel(plain[k], px), rcond=None)
            resid = np.abs(A @ (s, w) - pixel(plain[k], px)).max()
            assert s > 0.5 and w > -10 and resid < 25, (k, b, s, w, resid)


def test_halo_of_a_measured_sample(gl_camera, motion):
    # No trail: its dots sit on the samples too, and the halo alone is under test.
    with_halo = frames(motion, colours=PURE, trail=0.0)
    without = frames(motion, colours=PURE, ghosts=False)
    for k in (0, 4):
        for b in motion.balls:
            px = gl_project(gl_camera, motion.measured[b][k])
            ch = int(np.argmax(PURE[b]))
            a, z = pixel(with_halo[k], px), pixel(without[k], px)
            # A translucent sphere of the ball's colour: that channel rises, the pixel now
            # leans to it; without halos the pixel there is background (no ball nearby).
            assert a[ch] > z[ch] + 25, (k, b, a, z)
            assert a[ch] > max(np.delete(a, ch)), (k, b, a)
    # Far from every ball and sample (the bottom corner), halos change nothing.
    np.testing.assert_array_equal(with_halo[0][-3:, -3:], without[0][-3:, -3:])


# --------------------------------------------------------------------------- GIF, MP4


def read_gif(path):
    im = Image.open(path)
    durations = []
    for k in range(im.n_frames):
        im.seek(k)
        durations.append(im.info["duration"])
    return im.n_frames, im.size, durations


def test_replay_gif_frames_and_durations(tmp_path):
    out = tmp_path / "replay.gif"
    info = estim.render_replay(SCENE, {"balls": FIT}, tracks_dict(), out, fps=10, width=160, height=90)
    n, size, durations = read_gif(out)
    span = T_END
    assert n == info.n_frames == int(np.floor(span * 10 + 1e-9)) + 1 == 7
    assert size[0] == 160 and size[1] > 90  # the caption band is below the picture
    assert durations == [100] * 7
    assert info.renderer == "mujoco" and info.t_start == 0.0 and info.t_end == pytest.approx(0.6)


def test_sideview_gif_at_30_fps(tmp_path):
    # GIF durations are whole hundredths: 30 fps alternates 30 and 40 ms, keeping time.
    out = tmp_path / "side.gif"
    info = estim.render_sideview(SCENE, {"balls": FIT}, tracks_dict(t_end=1.0), out, fps=30,
                                 width=320, height=180)
    n, size, durations = read_gif(out)
    assert n == info.n_frames == 31 and size == (320, 180)
    assert all(abs(d - 1000 / 30) <= 10 for d in durations)
    ends = np.cumsum(durations)
    np.testing.assert_allclose(ends, np.arange(1, n + 1) * 1000 / 30, atol=5)


def test_sideview_pixels(motion, stairs):
    view = estim.SideView(stairs, motion, 480, 270, trail=0.0)
    for k in (0, 3, 6):
        img = view.frame(k)
        for b in motion.balls:
            c = np.array([int(COLOURS[b][i:i + 2], 16) for i in (1, 3, 5)], float)
            # The fitted ball: its colour, exactly (no shading in 2-D).
            np.testing.assert_allclose(pixel(img, view.to_pixels(motion.fitted[b][k])), c, atol=2)
            # The halo, alpha 0.35 over the white axes.
            halo = 0.35 * c + 0.65 * 255
            np.testing.assert_allclose(pixel(img, view.to_pixels(motion.measured[b][k])), halo, atol=3)


def test_gif_rejects_too_high_a_frame_rate(tmp_path):
    with pytest.raises(ValueError, match="50"):
        estim.write_gif([np.zeros((4, 4, 3), np.uint8)] * 2, tmp_path / "x.gif", 60)


def test_mp4_without_ffmpeg_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # an empty folder: no ffmpeg
    with pytest.raises(estim.EncoderNotFoundError, match="ffmpeg"):
        estim.write_mp4([np.zeros((4, 4, 3), np.uint8)], tmp_path / "x.mp4", 25)
    with pytest.raises(estim.EncoderNotFoundError, match="ffmpeg"):
        estim.render_replay(SCENE, {"balls": FIT}, tracks_dict(), tmp_path / "x.mp4")


def test_mp4_pipes_every_frame_to_ffmpeg(tmp_path, monkeypatch):
    # A stand-in ffmpeg that records its arguments and the bytes it was sent.
    fake = tmp_path / "ffmpeg"
    fake.write_text(
        f"#!{sys.executable}\n"
        "import json, sys\n"
        "data = sys.stdin.buffer.read()\n"
        "json.dump({'args': sys.argv[1:], 'bytes': len(data)}, open(sys.argv[-1], 'w'))\n"
    )
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("PATH", str(tmp_path) + os.pathsep + os.environ.get("PATH", ""))
    frames_ = [np.full((6, 10, 3), k, np.uint8) for k in range(5)]
    out = tmp_path / "x.mp4"
    assert estim.write_mp4(frames_, out, 25) == 5
    rec = json.loads(out.read_text())
    assert rec["bytes"] == 5 * 6 * 10 * 3
    args = rec["args"]
    assert args[args.index("-s") + 1] == "10x6" and args[args.index("-r") + 1] == "25"


# --------------------------------------------------------------------------- CLI, demo


@pytest.fixture()
def files(tmp_path):
    tracks = tmp_path / "tracks.csv"
    data = tracks_dict()
    rows = ["t,ball,x,z"]
    for k in range(len(data["golf"][0])):
        for b in FIT:
            t, p = data[b]
            rows.append(f"{float(t[k])!r},{b},{float(p[k, 0])!r},{float(p[k, 2])!r}")
    tracks.write_text("\n".join(rows) + "\n")
    fit = tmp_path / "fit.json"
    fit.write_text(json.dumps({"balls": FIT}))
    return tracks, fit


def cli_error(capsys, *args) -> str:
    capsys.readouterr()
    assert main(["replay", *args]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.startswith("estim replay: error:")
    return err


def test_cli_replay(capsys, tmp_path, files):
    tracks, fit = files
    out = tmp_path / "r.gif"
    assert main(["replay", str(tracks), str(fit), "--scene", SCENE, "--out", str(out),
                 "--fps", "5", "--width", "160", "--height", "90", "--view", "side"]) == 0
    assert "4 frames" in capsys.readouterr().out
    n, size, durations = read_gif(out)
    assert n == 4 and size == (160, 90) and durations == [200] * 4


def test_cli_replay_bad_input(capsys, tmp_path, files):
    tracks, fit = files
    assert "not found" in cli_error(capsys, str(tmp_path / "nope.csv"), str(fit))
    assert "not found" in cli_error(capsys, str(tracks), str(tmp_path / "nope.json"))
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"balls": {b: v for b, v in FIT.items() if b != "pingpong"}}))
    assert "pingpong" in cli_error(capsys, str(tracks), str(partial), "--scene", SCENE,
                                   "--out", str(tmp_path / "x.gif"))
    assert ".gif or .mp4" in cli_error(capsys, str(tracks), str(fit), "--out", str(tmp_path / "x.avi"))
    assert "50" in cli_error(capsys, str(tracks), str(fit), "--out", str(tmp_path / "x.gif"), "--fps", "60")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert "JSON" in cli_error(capsys, str(tracks), str(bad), "--out", str(tmp_path / "x.gif"))


def test_cli_mp4_without_ffmpeg(capsys, tmp_path, files, monkeypatch):
    tracks, fit = files
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert "ffmpeg" in cli_error(capsys, str(tracks), str(fit), "--out", str(tmp_path / "x.mp4"))
    assert not (tmp_path / "x.mp4").exists()


def test_demo_replays(tmp_path, files, capsys):
    """The demo's replay step: replay.gif (MuJoCo) and sideview.gif from out/fit.json."""
    from estim.app._demo import write_replays

    tracks, fit = files
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "fit.json").write_text(fit.read_text())
    written = write_replays(tmp_path / "out", scene_path=SCENE, tracks_path=tracks, fps=5)
    assert [os.path.basename(f) for f in written] == ["replay.gif", "sideview.gif"]
    for f in written:
        assert read_gif(f)[0] == 4


def test_demo_says_when_mujoco_cannot_render(tmp_path, files, capsys, monkeypatch):
    from estim.app import _demo
    def broken(*args, **kwargs):
        raise _replay.RenderError("no OpenGL here")

    monkeypatch.setattr(_replay, "render_replay", broken)
    tracks, fit = files
    (tmp_path / "fit.json").write_text(fit.read_text())
    written = _demo.write_replays(tmp_path, scene_path=SCENE, tracks_path=tracks, fps=5)
    assert [os.path.basename(f) for f in written] == ["sideview.gif"]
    assert "replay.gif not written: no OpenGL here" in capsys.readouterr().err
