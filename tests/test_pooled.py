"""Several clips fitted together (``estim.fitting._pooled``): the Schur-complement step
against a dense solve, recovery of a known shared e, sharded against unsharded, the command
line and its refusals, the forest plot, and the calibration of the shared standard errors."""

from __future__ import annotations

import dataclasses
import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import estim
from estim.app._cli import main
from estim.fitting._pooled import Clip, _Arrow, _arrow_step, fit_clips

ROOT = Path(__file__).resolve().parents[1]
DROP = str(ROOT / "data" / "scenes" / "drop.xml")
DROP_AIR = str(ROOT / "data" / "scenes" / "drop_air.xml")
PNG = b"\x89PNG\r\n\x1a\n"


def drops(scene, e, n, seed, *, drag_coefficient=0.5, noise=1e-3, rate=100.0, span=1.2, heights=(0.5, 1.0),
          group=None):
    """``n`` clips of the scene's ping-pong ball dropped from ``heights`` with a small
    sideways speed (known per clip), ``span`` seconds (one length: one compile) sampled at
    ``rate`` with Gaussian noise."""
    rng = np.random.default_rng(seed)
    clips, truth = [], []
    for k in range(n):
        z0, vx = rng.uniform(*heights), rng.uniform(-0.3, 0.3)
        p = estim.Params.for_ball(scene, "pingpong", e=e, mu_t=0.8, position=(0.0, 0.0, z0),
                                  velocity=(vx, 0.0, 0.0), drag_coefficient=drag_coefficient)
        ts = np.arange(round(span * rate)) / rate
        pos = np.array(estim.simulate(scene, p, span, ts=ts).position) + rng.normal(0.0, noise, (len(ts), 3))
        pos[:, 1] = np.nan
        label = f"c{k}" if group is None else f"{group}c{k}"
        clips.append(Clip(label=label, ball="pingpong", t=ts, position=pos, fixed={"y0": 0.0}, group=group))
        truth.append({"z0": z0, "vx0": vx})
    return clips, truth


def test_arrow_step_is_the_dense_levenberg_marquardt_step():
    """The Schur-complement step equals the damped Gauss-Newton step of the whole problem
    solved densely: unknowns (a, b_1, ..., b_U), Jacobian with the arrow's blocks."""
    rng = np.random.default_rng(0)
    U, m, P, shared, lam = 4, 9, 4, (1, 3), 0.1
    local = tuple(k for k in range(P) if k not in shared)
    J, u = rng.normal(size=(U, m, P)), rng.normal(size=(U, m))
    w = rng.uniform(0.3, 1.0, size=(U, m))
    theta = np.tile(rng.normal(size=P), (U, 1))
    state = _Arrow(theta=jnp.asarray(theta), best_theta=jnp.asarray(theta), best_value=jnp.array([jnp.inf]),
                   damping=jnp.array([lam * 3.0]), hessian=jnp.zeros((U, P, P)), gradient=jnp.zeros((U, P)))
    group, real = jnp.ones((U, 1)), jnp.ones(U, bool)
    new = _arrow_step(shared, local, group, real, state, jnp.asarray(J), jnp.asarray(u), jnp.asarray(w),
                      jnp.ones(U))
    # The dense system: columns [a (2), b_1 (2), ..., b_U (2)].
    k, p = len(shared), len(local)
    big = np.zeros((U * m, k + U * p))
    for i in range(U):
        big[i * m:(i + 1) * m, :k] = J[i][:, shared]
        big[i * m:(i + 1) * m, k + i * p:k + (i + 1) * p] = J[i][:, local]
    sw = np.sqrt(w.reshape(-1))
    H = (big * sw[:, None]).T @ (big * sw[:, None])
    g = (big * sw[:, None]).T @ (u.reshape(-1) * sw)
    step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), -g)
    got = np.asarray(new.theta) - theta
    np.testing.assert_allclose(got[:, shared], np.tile(step[:k], (U, 1)), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(got[:, local], step[k:].reshape(U, p), rtol=1e-10, atol=1e-12)


def test_shared_e_recovered_from_clips():
    """Five drops of a ball with e = 0.8 (vacuum, 1 mm noise): the shared e is within three
    standard errors of the truth, every clip's release height within 3 mm of its own, and
    the clips agree with each other (heterogeneity Q near its degrees of freedom)."""
    scene = estim.load_scene(DROP)
    clips, truth = drops(scene, 0.8, 5, 1)
    res = fit_clips(scene, clips, shared=("e",), restarts=0)
    sf = res.shared["pingpong"]
    assert sf.stderr["e"] > 0 and abs(sf.values["e"] - 0.8) < 3 * sf.stderr["e"], (sf.values, sf.stderr)
    assert sf.stderr["e"] < 1e-3
    for c, t in zip(clips, truth, strict=True):
        bf = res.clips.balls[c.label]
        assert bf.values["e"] == sf.values["e"]
        assert abs(bf.values["z0"] - t["z0"]) < 3e-3, (c.label, bf.values["z0"], t["z0"])
        assert bf.at_noise_floor
    q, dof = sf.heterogeneity["e"]
    assert dof == 4 and q < 20 and not sf.disagree
    payload = res.to_json()
    assert payload["shared"]["e"] == sf.values["e"] and payload["shared"]["stderr"]["e"] == sf.stderr["e"]
    assert set(payload["clips"]) == {c.label for c in clips}


def test_a_clip_that_disagrees_is_named():
    """Four clips of e = 0.8 and one of e = 0.6: the odd one is named, its own e read as 0.6,
    the clips' heterogeneity far above its degrees of freedom, and the robust loss keeps
    the shared e at the four clips' 0.8."""
    scene = estim.load_scene(DROP)
    clips, _ = drops(scene, 0.8, 4, 2)
    odd, _ = drops(scene, 0.6, 1, 3)
    clips.append(dataclasses.replace(odd[0], label="odd"))
    res = fit_clips(scene, clips, shared=("e",), restarts=0)
    sf = res.shared["pingpong"]
    assert [d[0] for d in sf.disagree] == ["odd"], sf.disagree
    assert abs(sf.per_clip["e"]["odd"][0] - 0.6) < 0.005
    assert sf.heterogeneity["e"][0] > 100 * sf.heterogeneity["e"][1]
    assert abs(sf.values["e"] - 0.8) < 1e-3
    assert any("shared value" in n for n in res.clips.balls["odd"].notes)


SHARDED = textwrap.dedent("""
    import json, sys
    import jax
    from estim.fitting._job import fit_files
    assert len(jax.devices()) == 4, jax.devices()
    paths = {paths!r}
    one, _ = fit_files(paths, {drop!r}, shared=("e",), devices=jax.devices()[:1])
    four, _ = fit_files(paths, {drop!r}, shared=("e",))
    print(json.dumps([one.to_json(), four.to_json()]))
""")


def test_sharded_and_distributed_match_one_device(tmp_path):
    """The clip axis split over 4 CPU devices of one process, and over 2 x 2 devices of two
    processes (``estim fit ... --shared e --distributed``: two "hosts" joined by
    ``jax.distributed``, whose sums JAX reduces across the processes with its CPU
    collectives, Gloo), gives what one device gives, to 1e-10: the shared e, its standard
    error, each clip's release state (mu_t to 1e-8). 6 clips: padded to 8 on 4 devices.
    Of the two processes only process 0 prints the result (its standard output holds the
    JSON alone: Gloo's messages go to standard error) and writes ``--out``."""
    scene = estim.load_scene(DROP)
    clips, _ = drops(scene, 0.8, 6, 4)
    paths = _clip_files(tmp_path, clips)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    # Files, not pipes: a process blocked on a full pipe would hold the others at JAX's
    # shutdown barrier.
    logs = [(tmp_path / f"stdout{k}", tmp_path / f"stderr{k}") for k in range(3)]
    commands = [[sys.executable, "-c", SHARDED.format(paths=paths, drop=DROP)]]
    commands += [[sys.executable, "-m", "estim", "fit", *paths, "--scene", DROP, "--shared", "e", "--json",
                  "--distributed", "--out", str(tmp_path / f"out{k}")] for k in range(2)]
    runs = []
    for k, (command, (out, err)) in enumerate(zip(commands, logs, strict=True)):
        # (Added to the suite's XLA_FLAGS, not in their place: tests/conftest.py.)
        devices = f"--xla_force_host_platform_device_count={4 if k == 0 else 2}"
        extra = {"XLA_FLAGS": f"{env.get('XLA_FLAGS', '')} {devices}".strip()}
        if k:
            extra.update(JAX_NUM_PROCESSES="2", JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}", JAX_PROCESS_ID=str(k - 1))
        with open(out, "w") as o, open(err, "w") as e:
            runs.append(subprocess.Popen(command, env=dict(env, **extra), stdout=o, stderr=e, text=True))
    for r, (_, err) in zip(runs, logs, strict=True):
        assert r.wait(timeout=900) == 0, err.read_text()[-3000:]
    one, four = json.loads(logs[0][0].read_text().strip().splitlines()[-1])
    two = json.loads(logs[1][0].read_text())
    assert logs[2][0].read_text() == "", "only process 0 reports"
    assert "split over 4 devices" in logs[1][1].read_text()
    assert (tmp_path / "out0" / "fit.json").is_file() and not (tmp_path / "out1").exists()
    for other in (four, two):
        assert abs(one["shared"]["e"] - other["shared"]["e"]) < 1e-10
        assert abs(one["shared"]["stderr"]["e"] - other["shared"]["stderr"]["e"]) < 1e-10
        # mu_t, which a drop's few bounces hardly determine, to 1e-8: the one- and
        # four-device programs round differently, and the fit amplifies it there (2.1e-9
        # apart in mu_t of clip c2, session 16, on either contact geometry; 1e-7 of its
        # standard error).
        for label, clip in one["clips"].items():
            for name in ("x0", "z0", "vx0", "mu_t"):
                assert abs(clip[name] - other["clips"][label][name]) < (1e-8 if name == "mu_t" else 1e-10), (label, name)


def _clip_files(folder, clips) -> list[str]:
    """Each clip written to ``folder/LABEL.csv``; the paths."""
    paths = [str(folder / f"{c.label}.csv") for c in clips]
    for path, c in zip(paths, clips, strict=True):
        _write_csv(path, c)
    return paths


def _write_csv(path, clip):
    with open(path, "w") as f:
        f.write("t,ball,x,z\n")
        for t, p in zip(clip.t, clip.position, strict=True):
            f.write(f"{t:.4f},{clip.ball},{p[0]:.6f},{p[2]:.6f}\n")


def test_cli_refuses_what_one_track_needs_with_shared(tmp_path, capsys):
    """``--shared`` fits many clips: a prior (counted once per clip) and the effect sizes
    (those of one track) are refused, with a message that says so."""
    path = tmp_path / "c.csv"
    path.write_text("t,ball,x,z\n0,pingpong,0,0.3\n")
    for flag, words in ((["--prior", "e=0.8,0.1"], "takes no priors"), (["--effects"], "those of one track")):
        assert main(["fit", str(path), str(path), "--scene", DROP, "--shared", "e", *flag]) == 2
        assert words in capsys.readouterr().err


def test_cli_fits_files_together(tmp_path, capsys):
    """``estim fit A B C --shared e --json --out``: the shared e near the truth, per clip
    what a single fit gives, fit.json and the forest plot written."""
    scene = estim.load_scene(DROP)
    clips, _ = drops(scene, 0.8, 3, 5)
    paths = _clip_files(tmp_path, clips)
    out = tmp_path / "out"
    code = main(["fit", *paths, "--scene", DROP, "--shared", "e", "--json", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    payload = json.loads(captured.out)
    assert abs(payload["shared"]["e"] - 0.8) < 3 * payload["shared"]["stderr"]["e"] + 1e-4
    assert set(payload["clips"]) == {"c0", "c1", "c2"}
    for clip in payload["clips"].values():
        assert {"e", "mu_t", "x0", "z0", "vx0", "stderr", "rms_m", "noise_m", "source"} <= set(clip)
    assert json.loads((out / "fit.json").read_text()) == payload
    for name in ("forest.png", "fit.png"):
        assert (out / name).read_bytes().startswith(PNG)


REALDATA = ROOT.parent / "shared" / "realdata" / "pingpong_drop_nicofighter45"


def test_a_clip_that_cannot_be_placed_in_metres_is_left_out_and_named(capsys):
    """Four real racket drops, two of which have no motion a pixel fit can place in metres:
    racket 0 never moves (the ball held still), racket 4 ends five frames after its bounce
    (too few to fit the flight that meets the fall at the surface's row). They are left out
    and named, with why, and the other two are fitted as if given alone."""
    racket = [REALDATA / "racket" / f"tracked-{k}.txt" for k in (0, 4, 9, 12)]
    if not all(f.is_file() for f in racket):
        pytest.skip(f"real data not found at {REALDATA}")
    rows = [np.loadtxt(f, delimiter=";", usecols=(1,)) for f in racket[:2]]
    assert np.ptp(rows[0]) < 2.0  # px: no motion
    assert rows[1].size - 1 - np.argmax(rows[1]) < 8  # samples after the bounce: fewer than a flight needs
    pixels = ["--pixels", "--frame-interval", "0.01", "--ball", "pingpong"]
    code = main(["fit", *map(str, racket), "--scene", DROP, *pixels, "--shared", "e", "--json"])
    captured = capsys.readouterr()
    assert code in (0, 1), captured.err
    payload = json.loads(captured.out)
    assert set(payload["left_out"]) == {"tracked-0", "tracked-4"}
    assert "no flight" in payload["left_out"]["tracked-0"]
    assert "no bounce with fitted flights on both sides" in payload["left_out"]["tracked-4"]
    assert "left out tracked-4" in captured.err
    assert set(payload["clips"]) == {"tracked-9", "tracked-12"}
    alone, _ = estim.fit_files(racket[2:], DROP, shared=("e",), pixels=True, ball="pingpong", frame_interval=0.01)
    assert alone.left_out == {}
    assert payload["shared"]["e"] == pytest.approx(alone.shared["pingpong"].values["e"], abs=1e-12)
    # Nothing left to share: the error names what was left out and why.
    _fails(["fit", *map(str, racket[:2]), str(racket[2]), "--scene", DROP, *pixels, "--shared", "e"], capsys,
           "only one clip", "left out: tracked-0")


def _fails(argv, capsys, *words):
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, (argv, err)
    for w in words:
        assert w.lower() in err.lower(), (w, err)


def test_cli_refuses_what_it_cannot_share(tmp_path, capsys):
    scene = estim.load_scene(DROP)
    clips, _ = drops(scene, 0.8, 2, 6)
    a, b = str(tmp_path / "a.csv"), str(tmp_path / "b.csv")
    _write_csv(a, clips[0])
    _write_csv(b, clips[1])
    _fails(["fit", a, b, "--scene", DROP], capsys, "2 files", "--shared")
    _fails(["fit", a, "--scene", DROP, "--shared", "e"], capsys, "only one clip")
    _fails(["fit", a, a, "--scene", DROP, "--shared", "e"], capsys, "given twice")
    _fails(["fit", a, b, "--scene", DROP, "--shared", "t0"], capsys, "t0")
    _fails(["fit", a, b, "--scene", DROP, "--shared", "drag_coefficient"], capsys, "air")
    _fails(["fit", a, "--scene", DROP, "--devices", "2"], capsys, "--shared")
    with pytest.raises(SystemExit):
        main(["fit", a, b, "--scene", DROP, "--shared", "restitution"])


def test_forest_plot_draws_every_clip(tmp_path):
    """One panel per shared parameter; per clip its own estimate and its one-by-one fit."""
    from estim.show._forest import plot_forest

    scene = estim.load_scene(DROP)
    clips, _ = drops(scene, 0.8, 3, 7)
    res = fit_clips(scene, clips, shared=("e",), restarts=0)
    fig = plot_forest(res, tmp_path / "forest.png")
    (ax,) = fig.axes
    assert len(ax.containers) == 2 * len(clips)  # an error bar per clip and per one-by-one fit
    assert [t.get_text() for t in ax.get_yticklabels()] == ["c2", "c1", "c0"]
    assert (tmp_path / "forest.png").read_bytes().startswith(PNG)


def test_pixel_scale_recovers_a_wrong_scale():
    """A track whose metres came from a scale 5% too small (positions shrunk by 1/1.05 about
    the surface under the first sample): fitting pixel_scale reads 1.05 back, and e with it."""
    scene = estim.load_scene(DROP)
    (clip,), (truth,) = drops(scene, 0.8, 1, 8)
    anchor = np.array([clip.position[0, 0], 0.0, 0.0])  # the drop scene's table top is z = 0
    shrunk = anchor + (clip.position - anchor) / 1.05
    res = estim.fit(scene, {"c": (clip.t, shrunk)}, free=("e", "mu_t", "vx0", "x0", "z0", "pixel_scale"),
                    fixed={"c": {"y0": 0.0}}, balls={"c": "pingpong"}, anchors={"c": tuple(anchor)})
    bf = res.balls["c"]
    assert abs(bf.values["pixel_scale"] - 1.05) < max(3 * bf.stderr["pixel_scale"], 2e-3), bf.values
    assert abs(bf.values["e"] - 0.8) < 3e-3 and abs(bf.values["z0"] - truth["z0"]) < 5e-3
