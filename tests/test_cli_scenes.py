"""Every command on every bundled scene (data/scenes/*.xml), through ``estim.app._cli.main``
in-process, each checked on one number against a truth computed without the command:

- ``estim simulate``: the final state is what ``estim.simulate`` gives when called directly;
  in a vacuum the first bounce and the flight after it are the closed-form parabolas and the
  bounce law ``v+ = mu_t v_t - e v_n n``; in air the flight before the first contact is a
  fine Runge-Kutta integration (numpy) of the force laws of ``estim.model._air``.
- ``estim effects``: the linear-drag run against Stokes' law, whose flight has a closed form.
- ``estim fit``: tracks synthesized from known parameters (``estim.synthesize_tracks``) give
  them back within three reported standard errors.
- ``estim replay --view side`` of that fit: one frame every 1/fps over the data's span, at the
  size asked for.

``estim bench speed`` times the seed experiment (its three balls, no air): on the seed scene
it is tested in tests/test_cli.py (a fresh process and hundreds of calls); on every other
bundled scene it refuses at once, saying why. ``bench fit`` and ``bench accuracy`` take no
scene (tests/test_cli.py, tests/test_bench_accuracy.py).

Kept short: one ball per scene, a few tenths of a second of motion, fits on 0.8 s of
tracks at 60 frames per second.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import estim
from estim.app._cli import main
from estim.tracks._csv import write_tracks_csv

SCENES_DIR = Path(__file__).resolve().parents[1] / "data" / "scenes"
# One ball per scene, and the top of the surface under its release (from the XML: stairs'
# step1 is a box at z = 0.70 with half height 0.70; drop's table a box at z = -0.05 with
# half height 0.05).
SCENES = {"stairs.xml": ("golf", 1.40), "stairs_air.xml": ("golf", 1.40), "drop.xml": ("pingpong", 0.0)}
IN_AIR = ("stairs_air.xml",)  # the scenes with <option density viscosity>
E, MU_T, VX0 = 0.7, 0.95, 1.15
T_ONE_BOUNCE = 0.4  # s: after the first bounce (0.23 s on stairs, 0.31 s on drop), before the second
T_FLIGHT = 0.1  # s: before any contact


def _path(name: str) -> str:
    return str(SCENES_DIR / name)


def _cli(*args) -> dict:
    """``estim ARGS --json`` in-process: exit code 0, stdout one JSON object."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main([*args, "--json"])
    assert code == 0, (args, buf.getvalue()[-2000:])
    return json.loads(buf.getvalue())


def _simulate(name: str, t_end: float) -> dict:
    ball, _ = SCENES[name]
    return _cli("simulate", "--scene", _path(name), "--ball", ball, "--e", repr(E), "--mu-t", repr(MU_T),
                "--vx0", repr(VX0), "--t-end", repr(t_end))


def _state(final: dict) -> np.ndarray:
    return np.array([final[k] for k in ("x", "y", "z", "vx", "vy", "vz")])


def _integrated_flight(scene: estim.Scene, ball: str, position, velocity, t_end: float, steps: int = 2000):
    """Position and velocity at ``t_end`` of a ball in flight through the scene's still air:
    classical Runge-Kutta 4 on ``a = g + a_quad + a_lin`` (eqs. (1) and (2) of
    ``estim.model._air``: no spin, no wind), step ``t_end / steps`` (error ~ h^4: 1e-15)."""
    spec = scene.ball(ball)
    rho, eta = float(scene.air.density), float(scene.air.viscosity)
    area, cd = math.pi * spec.radius**2, float(estim.Params.for_ball(scene, ball, e=E, mu_t=MU_T).drag_coefficient)
    g = np.array([0.0, 0.0, -float(scene.gravity)])

    def rate(y):
        v = y[3:]
        a = g - (rho * cd * area / (2 * spec.mass)) * np.linalg.norm(v) * v - (6 * math.pi * eta * spec.radius / spec.mass) * v
        return np.concatenate([v, a])

    y, h = np.concatenate([position, velocity]).astype(np.float64), t_end / steps
    for _ in range(steps):
        k1 = rate(y)
        k2 = rate(y + 0.5 * h * k1)
        k3 = rate(y + 0.5 * h * k2)
        k4 = rate(y + h * k3)
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return y


# --------------------------------------------------------------------------- simulate


@pytest.mark.parametrize("name", SCENES)
def test_simulate_gives_the_library_s_final_state(name):
    """Through one bounce: the command's final state is ``estim.simulate``'s for the scene's
    ball (its radius, mass and release point) with the same e, mu_t and vx0, to rounding."""
    scene, (ball, _) = estim.load_scene(_path(name)), SCENES[name]
    out = _simulate(name, T_ONE_BOUNCE)
    params = estim.Params.for_ball(scene, ball, e=E, mu_t=MU_T, velocity=(VX0, 0.0, 0.0))
    traj = estim.simulate(scene, params, T_ONE_BOUNCE)
    library = np.concatenate([np.asarray(traj.final.position), np.asarray(traj.final.velocity)])
    np.testing.assert_allclose(_state(out["final"]), library, rtol=0, atol=1e-12)
    assert out["n_impacts"] == 1 and out["final"]["t"] == T_ONE_BOUNCE


@pytest.mark.parametrize("name", [n for n in SCENES if n not in IN_AIR])
def test_simulate_in_a_vacuum_is_the_closed_form(name):
    """Released at rest vertically from height h above the surface (centre h + r): the
    bounce at sqrt(2 h / g) with vz = -g t1, then vx -> mu_t vx, vz -> e g t1 and a
    parabola again (m, m/s; 1e-12)."""
    scene, (ball, top) = estim.load_scene(_path(name)), SCENES[name]
    assert scene.air is None
    spec, g = scene.ball(ball), float(scene.gravity)
    x0, y0, z0 = spec.position
    out = _simulate(name, T_ONE_BOUNCE)
    t1 = math.sqrt(2 * (z0 - spec.radius - top) / g)
    (hit,) = out["events"]
    assert hit["kind"] == "impact"
    np.testing.assert_allclose([hit["t"], hit["x"], hit["z"], hit["vx"], hit["vz"]],
                               [t1, x0 + VX0 * t1, top + spec.radius, VX0, -g * t1], rtol=0, atol=1e-12)
    tau, up = T_ONE_BOUNCE - t1, E * g * t1
    closed = [x0 + VX0 * t1 + MU_T * VX0 * tau, y0, top + spec.radius + up * tau - 0.5 * g * tau**2,
              MU_T * VX0, 0.0, up - g * tau]
    np.testing.assert_allclose(_state(out["final"]), closed, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", IN_AIR)
def test_simulate_in_air_follows_the_force_laws(name):
    """Before the first contact the flight through the scene's air is the Runge-Kutta
    integration of gravity plus quadratic and linear drag: within 1e-9 m and m/s (the ODE
    path's tolerances, rtol 1e-8 and atol 1e-9; 1e-11 measured), while drag moves the ball
    by far more than that from the vacuum parabola."""
    scene, (ball, _) = estim.load_scene(_path(name)), SCENES[name]
    spec = scene.ball(ball)
    out = _simulate(name, T_FLIGHT)
    assert out["n_events"] == 0
    truth = _integrated_flight(scene, ball, spec.position, (VX0, 0.0, 0.0), T_FLIGHT)
    np.testing.assert_allclose(_state(out["final"]), truth, rtol=0, atol=1e-9)
    g, t = float(scene.gravity), T_FLIGHT
    vacuum = [spec.position[0] + VX0 * t, spec.position[1], spec.position[2] - 0.5 * g * t * t, VX0, 0.0, -g * t]
    assert np.max(np.abs(truth - vacuum)) > 1e-5


# --------------------------------------------------------------------------- effects

VISCOSITY = 1e-3  # Pa s: a thick fluid, so that linear drag moves the ball by 0.1-0.8 mm in 0.1 s


def _stokes(position, velocity, g: float, k: float, t: float) -> np.ndarray:
    """Flight under gravity and linear drag ``a = -g z - k v`` (closed form)."""
    q = -math.expm1(-k * t) / k  # (1 - exp(-k t)) / k
    v = np.asarray(velocity, dtype=np.float64)
    terminal = np.array([0.0, 0.0, -g / k])
    return np.asarray(position) + terminal * t + (v - terminal) * q


@pytest.mark.parametrize("name", SCENES)
def test_effects_linear_drag_is_stokes_law(name):
    """The linear-drag run (viscosity only) against the vacuum, before any contact: the
    displacement is Stokes' closed form with k = 6 pi eta r / m (relative 1e-6; 1e-12
    measured: the ODE path's rtol 1e-8 bounds the error far below the 0.1-0.8 mm)."""
    scene, (ball, _) = estim.load_scene(_path(name)), SCENES[name]
    out = _cli("effects", "--scene", _path(name), "--ball", ball, "--e", repr(E), "--mu-t", repr(MU_T),
               "--vx0", repr(VX0), "--t-end", repr(T_FLIGHT), "--viscosity", repr(VISCOSITY))
    run = next(x for x in out["effects"] if x["effect"] == "linear drag")
    assert run["air"]["density"] == 0.0 and run["air"]["viscosity"] == VISCOSITY
    got = run["balls"][ball]
    spec, g = scene.ball(ball), float(scene.gravity)
    k = 6 * math.pi * VISCOSITY * spec.radius / spec.mass
    v0 = (VX0, 0.0, 0.0)
    vacuum = np.asarray(spec.position) + np.asarray(v0) * T_FLIGHT + np.array([0.0, 0.0, -0.5 * g * T_FLIGHT**2])
    delta = (_stokes(spec.position, v0, g, k, T_FLIGHT) - vacuum) * 1e3  # mm
    assert got["bounces"] == got["bounces_baseline"] == 0
    assert got["final_dx_mm"] == pytest.approx(delta[0], rel=1e-6)
    assert got["final_mm"] == pytest.approx(np.linalg.norm(delta), rel=1e-6)
    assert np.linalg.norm(delta) > 0.05  # the check measures something


# --------------------------------------------------------------------------- fit, replay

TRUTH = {"e": 0.75, "mu_t": 0.9, "vx0": 1.0}
FIT_T_END, FPS, NOISE = 0.8, 60.0, 0.001


@pytest.fixture(scope="module", params=list(SCENES))
def fitted(request, tmp_path_factory):
    """``estim fit`` on 0.8 s of synthetic tracks of the scene's ball (60 frames/s, 1 mm
    noise, a few dropped frames, outliers and lost coordinates) made with TRUTH."""
    name = request.param
    scene, (ball, _) = estim.load_scene(_path(name)), SCENES[name]
    tracks = estim.synthesize_tracks(scene, {ball: TRUTH}, t_end=FIT_T_END, frame_rate=FPS, noise=NOISE,
                                     n_outliers=1, seed=5)
    folder = tmp_path_factory.mktemp(name.replace(".xml", ""))
    csv = folder / "tracks.csv"
    write_tracks_csv(csv, tracks)
    out = _cli("fit", str(csv), "--scene", _path(name), "--out", str(folder / "fit"))
    return name, ball, tracks, csv, folder, out


def test_fit_recovers_the_parameters_of_the_tracks(fitted):
    name, ball, _, _, folder, out = fitted
    got = out["balls"][ball]
    assert got["converged"] and (folder / "fit" / "fit.json").is_file()
    for key, true in TRUTH.items():
        err = got["stderr"][key]
        assert err is not None and 0 < err < 0.01, (name, key, err)  # 3e-4 to 2e-3 measured
        assert abs(got[key] - true) < 3 * err, (name, key, got[key], true, err)
    assert got["rms_m"] == pytest.approx(NOISE, rel=0.3)  # the residuals are the noise put in


def test_replay_side_view_of_the_fit(fitted):
    """``estim replay --view side``: a frame every 1/fps from the first sample to the last
    (``floor(span fps) + 1``), each shown 1000/fps ms, at the size asked for."""
    name, ball, tracks, csv, folder, _ = fitted
    gif = folder / "replay.gif"
    fps, width, height = 10, 160, 90
    assert main(["replay", str(csv), str(folder / "fit" / "fit.json"), "--scene", _path(name), "--view", "side",
                 "--out", str(gif), "--fps", str(fps), "--width", str(width), "--height", str(height)]) == 0
    span = float(tracks.t[ball][-1] - tracks.t[ball][0])
    with Image.open(gif) as im:
        assert im.size == (width, height)
        assert im.n_frames == math.floor(span * fps + 1e-9) + 1
        durations = []
        for k in range(im.n_frames):
            im.seek(k)
            durations.append(im.info["duration"])
    assert durations == [1000 // fps] * len(durations)


@pytest.mark.parametrize("name", [n for n in SCENES if n != "stairs.xml"])
def test_bench_speed_says_why_it_needs_the_seed_scene(name, capsys):
    scene = estim.load_scene(_path(name))
    assert main(["bench", "speed", "--scene", _path(name)]) == 2
    err = capsys.readouterr().err
    assert "times the seed experiment" in err
    assert ("it has air" in err) == (scene.air is not None)
    assert ("it lacks" in err) == (not {"bocce", "golf", "pingpong"} <= {b.name for b in scene.balls})
