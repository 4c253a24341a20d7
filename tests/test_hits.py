"""Hits (``estim.fitting._hits``): a tracked shot that something the scene lacks strikes (the
opponent's racket at its end, the serve's racket after a toss at its start) is fitted on
its longest stretch between hits, against the shot's known parameters; bounces on the
table, its edges and spinning flights in air are no hits."""

import glob
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from test_fit_friction import mujoco_shot

import estim
from estim.app._bench import TABLE_SHOT
from estim.app._cli import main
from estim.fitting._hits import hits
from estim.tracks._csv import read_tracks_csv

ROOT = Path(__file__).resolve().parents[1]
TABLE = str(ROOT / "data" / "scenes" / "table_tennis.xml")
REALDATA = ROOT.parent / "shared" / "realdata" / "pingpong_drop_nicofighter45"
RATE = 180.0


def _params(scene, position, velocity, spin, e=TABLE_SHOT["e"], mu=TABLE_SHOT["mu"]):
    return estim.Params.for_ball(scene, "pingpong", e=e, mu_t=1.0, mu=mu, position=position, velocity=velocity,
                                 spin=spin)


def _write(path, t, pos, seed):
    pos = pos + np.random.default_rng(seed).normal(0.0, 0.002, pos.shape)
    with open(path, "w") as f:
        f.write("t,ball,x,y,z\n" + "".join(f"{a:.6f},pingpong,{x:.5f},{y:.5f},{z:.5f}\n"
                                           for a, (x, y, z) in zip(t, pos, strict=True)))


def _fit(path, capsys):
    code = main(["fit", str(path), "--scene", TABLE, "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    return json.loads(captured.out)["balls"]["pingpong"], captured.err


def _close_to_the_shot(ball):
    assert abs(ball["e"] - TABLE_SHOT["e"]) < 0.01 and abs(ball["mu"] - TABLE_SHOT["mu"]) < 0.03
    assert ball["at_noise_floor"] and ball["converged"]


def test_the_returned_ball_is_cut_off(tmp_path, capsys):
    # The table-tennis shot of the bench, tracked at 180 Hz with 2 mm noise; at t = 0.5 s,
    # 20 cm above the table, the opponent's racket returns it. Fitted whole, its e, mu and
    # spin bent towards the return (e 0.912, mu 0.145, spin_y 69 rad/s for a true 10).
    scene = estim.load_scene(TABLE)
    s = TABLE_SHOT
    t1 = 0.5
    t = np.arange(0.0, t1, 1 / RATE)
    run = estim.simulate(scene, _params(scene, s["position"], s["velocity"], s["spin"]), t1, ts=np.append(t, t1))
    x1, v1 = np.asarray(run.position)[-1], np.asarray(run.velocity)[-1]
    back = _params(scene, x1, (-v1[0], -0.8 * v1[1], 1.5), (100.0, 0.0, 0.0))
    t2 = np.arange(1, 36) / RATE
    after = np.asarray(estim.simulate(scene, back, 0.2, ts=t2).position)
    _write(tmp_path / "shot.csv", np.concatenate([t, t1 + t2]), np.concatenate([np.asarray(run.position)[:-1], after]), 1)
    ball, err = _fit(tmp_path / "shot.csv", capsys)
    assert "something the scene does not have hit the ball" in ball["notes"][0]
    assert "35 of 125 samples left out" in ball["notes"][0] and "t = 0.500 s" in ball["notes"][0]
    assert "hit the ball" in err  # the progress line
    assert len(ball["fitted"]["t"]) == t.size
    _close_to_the_shot(ball)
    assert np.linalg.norm(np.array(ball["release"]["spin"]) - s["spin"]) < 0.1 * np.linalg.norm(s["spin"])


def test_a_serve_after_its_toss_starts_at_the_hit(tmp_path, capsys):
    # The ball tossed up by hand for 0.3 s, then served: the shot after the hit is the
    # longer stretch, fitted from its first sample as the release (t0).
    scene = estim.load_scene(TABLE)
    s = TABLE_SHOT
    t_toss = np.arange(0.0, 0.3, 1 / RATE)
    start = np.array(s["position"]) - np.array([0.0, 0.0, 0.2])
    toss = start + np.outer(t_toss, [0.0, 0.0, 2.0]) - np.outer(0.5 * 9.81 * t_toss**2, [0.0, 0.0, 1.0])
    hit = start + np.array([0.0, 0.0, 2.0 * 0.3 - 0.5 * 9.81 * 0.09])
    t_shot = np.arange(0.0, 0.5, 1 / RATE)
    shot = np.asarray(estim.simulate(scene, _params(scene, hit, s["velocity"], s["spin"]), 0.5, ts=t_shot).position)
    _write(tmp_path / "serve.csv", np.concatenate([t_toss, 0.3 + t_shot]), np.concatenate([toss, shot]), 2)
    ball, _ = _fit(tmp_path / "serve.csv", capsys)
    assert f"{t_toss.size} of {t_toss.size + t_shot.size} samples left out" in ball["notes"][0]
    assert ball["release"]["t"] == pytest.approx(0.3, abs=1e-6)
    assert np.allclose(ball["release"]["position"], hit, atol=0.01)
    assert np.allclose(ball["release"]["velocity"], s["velocity"], atol=0.1)
    _close_to_the_shot(ball)
    # A ball held still in the hand before the same shot: its release is a hit too.
    held = np.concatenate([np.tile(hit, (t_toss.size, 1)), shot])
    held += np.random.default_rng(3).normal(0.0, 0.002, held.shape)
    found = hits(np.concatenate([t_toss, 0.3 + t_shot]), held, scene, 0.02)
    # (The shot's first sample is still at the hand: the cut falls on it or after it.)
    assert len(found) == 1 and found[0][0] - t_toss.size in (0, 1)


def test_bounces_edges_and_spinning_flights_are_no_hits():
    # Shots of every spin the camera study draws (topspin to backspin, sidespin), 180 Hz,
    # 2 mm noise, each bouncing once on the table, each with a glitch; a shot of MuJoCo's
    # physics; the bundled staircase tracks (60 fps, bounces on treads and their edges,
    # dropped frames, outliers); the real drops in metres.
    scene = estim.load_scene(TABLE)
    sys.path.insert(0, str(ROOT / "docs" / "scripts"))
    import camera_views

    rng = np.random.default_rng(3)
    t = np.arange(0.0, 0.6, 1 / RATE)
    for k in range(8):
        _, path = camera_views.draw_shot(rng, scene, t)
        path = path + rng.normal(0.0, 0.002, path.shape)
        # A tracker's glitch: a burst of 1 to 8 samples 10 cm off, mid-flight, jumps away and back.
        path[20:21 + k] += 0.1
        assert hits(t, path, scene, 0.02) == []
    # MuJoCo's own physics, whose soft contact spreads the bounce over milliseconds.
    t_mj, path = mujoco_shot(noise=0.002)[:2]
    assert hits(t_mj, path, scene, 0.02) == []
    stairs = estim.load_scene(ROOT / "data" / "scenes" / "stairs.xml")
    tracks = read_tracks_csv(ROOT / "data" / "tracks" / "stairs_demo.csv", scene=stairs)
    for b in tracks.balls:
        spec = stairs.ball(b)
        assert hits(tracks.t[b], tracks.position[b], stairs, spec.radius, spec.position[1]) == []
    files = sorted(glob.glob(str(REALDATA / "table" / "tracked-*.txt")))
    if not files:
        pytest.skip(f"real data not found at {REALDATA}")
    drop = estim.load_scene(ROOT / "data" / "scenes" / "drop_air.xml")
    for f in files:
        clip = estim.read_pixel_clip(f, drop, ball="pingpong", frame_interval=0.01)
        assert hits(clip.t, clip.position, drop, 0.02, 0.0) == [], f
