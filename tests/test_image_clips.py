"""Shots of one ball filmed by a calibrated camera, fitted together with their restitution
shared (estim.fitting._pooled.fit_image_clips, `estim fit A B ... --camera CAM --shared e`):
shots of known parameters, fitted back from their pixels."""

import json

import numpy as np
import pytest
from test_image_tracks import SIDE, _tracks

import estim
from estim.app._cli import main

SCENE = "data/scenes/table_tennis.xml"
E, MU = 0.88, 0.3
# Three shots of one ball (its e and mu), each its own release and spin.
SHOTS = (((-0.2, -1.6, 0.25), (0.4, 6.5, 1.6), (-120.0, 0.0, 40.0)),
         ((0.3, -1.7, 0.30), (-0.5, 7.0, 1.2), (80.0, 10.0, -30.0)),
         ((0.0, -1.5, 0.20), (0.1, 5.8, 2.0), (-40.0, 0.0, 0.0)))
T = np.arange(0.0, 0.6, 1 / 25)


def _paths(scene):
    out = []
    for p, v, w in SHOTS:
        params = estim.Params.for_ball(scene, "pingpong", e=E, mu_t=0.0, mu=MU, position=np.array(p),
                                       velocity=np.array(v), spin=np.array(w))
        out.append(np.asarray(estim.simulate(scene, params, 0.7, ts=T).position))
    return out


@pytest.mark.slow
def test_shots_of_one_ball_share_their_restitution(tmp_path, capsys):
    # estim's own physics (air, the friction law's bounce), one camera from the side, 25
    # fps, 2 px of noise: each shot alone reads e to a few hundredths; together they read
    # one e, through the command line. A prior of one's own on e (in place of the scene's
    # 0.88 +- 0.05), 0.08 below the truth: the pixels of three shots move e back to it.
    scene = estim.load_scene(SCENE)
    paths = _paths(scene)
    files = []
    for k, path in enumerate(paths):
        tracks = _tracks((SIDE,), T, path, 2.0, seed=10 + k)
        files.append(str(tmp_path / f"shot{k}.csv"))
        with open(files[-1], "w") as f:
            f.write("t,ball,u,v\n" + "".join(f"{float(t)!r},pingpong,{u:.3f},{v:.3f}\n"
                                             for t, (u, v) in zip(tracks.t["pingpong"], tracks.uv["pingpong"], strict=True)))
    (tmp_path / "side.json").write_text(json.dumps(SIDE.to_json()))
    code = main(["fit", *files, "--camera", str(tmp_path / "side.json"), "--scene", SCENE, "--shared", "e", "--json",
                 "--prior", "e=0.80,0.10", "--out", str(tmp_path / "out")])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    shared = out["shared"]
    assert shared["n_clips"] == 3 and shared["group"] == "pingpong"
    assert abs(shared["e"] - E) < 3 * shared["stderr"]["e"] and abs(shared["e"] - E) < 0.04
    assert out["cameras"][0]["name"] == "side" and out["left_out"] == {}
    for k, path in enumerate(paths):
        clip, alone = out["clips"][f"shot{k}"], out["individual"][f"shot{k}"]
        assert clip["e"] == shared["e"] and clip["converged"]
        # The joint fit's 3-D path at the rows' times, against the truth (one camera's depth).
        fitted = np.asarray(clip["fitted"]["position"])
        assert np.mean(np.linalg.norm(fitted - path, axis=1)) < 0.03
        assert 1.0 < clip["rms_px"] < 2.5 and clip["depth"]["fixed"]  # 2 px of noise
        # The scene's priors stay (on each shot's own spin), and alone each shot takes the
        # prior given on e.
        assert "spin_x" in clip["prior"] and alone["prior"]["e"] == {"mean": 0.80, "sd": 0.10}
        # With one shared parameter a clip's own estimate is its fit alone.
        assert shared["per_clip"]["e"][f"shot{k}"]["value"] == alone["e"]
    # Together, the prior on the shared e counts once (counted once per clip it would
    # weigh three times).
    assert [clip["prior"]["e"] for clip in out["clips"].values() if "e" in clip["prior"]] == [{"mean": 0.80, "sd": 0.10}]
    own = [alone["e"] for alone in out["individual"].values()]
    assert shared["stderr"]["e"] < max(alone["stderr"]["e"] for alone in out["individual"].values())
    assert min(own) < shared["e"] < max(own)
    assert all((tmp_path / "out" / name).is_file() for name in ("fit.json", "forest.png", "pixels-shot0.png"))


@pytest.mark.slow
def test_the_joint_fit_leaves_its_start_where_its_first_steps_are_refused():
    """The three shots with the scene's priors: from the median start, the clips' loosely
    fixed spins and mu made the joint steps raise the loss until the damping had grown
    (the first ten refused); the joint fit then went on from there (its loss 16.70 ->
    16.49, settled), where it had stopped at its start, called converged, its shared e
    the median of the shots' own."""
    scene = estim.load_scene(SCENE)
    clips = {f"shot{k}": _tracks((SIDE,), T, path, 2.0, seed=10 + k) for k, path in enumerate(_paths(scene))}
    res = estim.fit_image_clips(scene, clips, shared=("e",), per_clip=False)
    assert res.converged
    history = res.clips.balls["shot0"].loss_history  # the ball's joint loss, iteration by iteration
    assert history[-1] < history[0] - 0.1
    e, stderr = res.shared["pingpong"].values["e"], res.shared["pingpong"].stderr["e"]
    assert e != np.median([bf.values["e"] for bf in res.individual.balls.values()])
    assert abs(e - E) < 3 * stderr and abs(e - E) < 0.04


def test_image_clips_are_refused_with_a_reason(tmp_path, capsys):
    scene = estim.load_scene(SCENE)
    tracks = _tracks((SIDE,), T, _paths(scene)[0], 2.0)
    with pytest.raises(ValueError, match="at least two clips"):
        estim.fit_image_clips(scene, {"a": tracks})
    with pytest.raises(ValueError, match="t0 is a clip's own"):
        estim.fit_image_clips(scene, {"a": tracks, "b": tracks}, shared=("t0",))
    # Clips that cannot be fitted alone are left out, each named with why; fewer than two
    # left is an error that lists them.
    short = _tracks((SIDE,), T[:5], _paths(scene)[0][:5], 2.0)
    with pytest.raises(ValueError, match=r"got 0 that could be fitted; left out: a: .*only 5 rows.*; left out: b: "):
        estim.fit_image_clips(scene, {"a": short, "b": short})
    two = _tracks((SIDE, SIDE), T, _paths(scene)[0], 2.0)
    with pytest.raises(ValueError, match=r"seen by \[1, 2\] cameras"):
        estim.fit_image_clips(scene, {"a": tracks, "b": two})
    (tmp_path / "side.json").write_text(json.dumps(SIDE.to_json()))
    (tmp_path / "a.csv").write_text("t,ball,u,v\n0.0,pingpong,1,2\n")
    code = main(["fit", str(tmp_path / "a.csv"), str(tmp_path / "a.csv"), "--camera", str(tmp_path / "side.json"),
                 "--scene", SCENE, "--shared", "e", "--distributed"])
    assert code == 2 and "--distributed with --camera" in capsys.readouterr().err
