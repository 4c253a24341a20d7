"""The ``estim`` command line (``estim.app._cli.main`` in-process, one console subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import estim
from estim.app._cli import main

ROOT = Path(__file__).resolve().parent.parent
SCENE = str(ROOT / "data" / "scenes" / "stairs.xml")
SEED_E = {"bocce": 0.55, "golf": 0.70, "pingpong": 0.85}
IMPACTS = {"bocce": 9, "golf": 6, "pingpong": 4}
FINAL_X = {"bocce": 2.2427444662, "golf": 2.3048901184, "pingpong": 2.3278961376}
GOLF_GRAD = (0.19213914, 6.81524982, 2.17816532)


def run_json(capsys, *args) -> dict:
    capsys.readouterr()
    assert main(["simulate", "--scene", SCENE, *args, "--json"]) == 0
    out = capsys.readouterr().out
    return json.loads(out)


def run_error(capsys, *args) -> str:
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:  # argparse errors
        code = main(list(args))
        raise SystemExit(code)
    assert info.value.code == 2
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    return captured.err


@pytest.fixture(scope="module")
def golf_sens():
    """Golf with sensitivities, computed once for the module."""
    import io
    from contextlib import redirect_stdout

    buf = io.StringIO()
    with redirect_stdout(buf):
        code = main(["simulate", "--scene", SCENE, "--ball", "golf", "--e", "0.7",
                     "--mu-t", "0.98", "--vx0", "1.15", "--sensitivities", "--json"])
    assert code == 0
    return json.loads(buf.getvalue())


@pytest.mark.parametrize("ball", ["bocce", "golf", "pingpong"])
def test_simulate_json_known_results(capsys, ball):
    out = run_json(capsys, "--ball", ball, "--e", str(SEED_E[ball]), "--mu-t", "0.98",
                   "--vx0", "1.15")
    assert out["ball"] == ball
    assert out["n_impacts"] == IMPACTS[ball]
    assert len(out["events"]) == IMPACTS[ball]
    assert all(ev["kind"] == "impact" for ev in out["events"])
    assert out["final"]["x"] == pytest.approx(FINAL_X[ball], abs=1e-9)
    assert out["final"]["t"] == pytest.approx(2.3)
    assert set(out["final"]) >= {"t", "x", "y", "z", "vx", "vy", "vz"}
    for ev in out["events"]:
        assert set(ev) >= {"t", "x", "y", "z", "vx", "vy", "vz", "surface", "face", "kind"}
        assert ev["surface"].startswith("step") and ev["face"] == "+z"
        assert ev["vz"] < 0  # pre-impact velocity points into the tread
    times = [ev["t"] for ev in out["events"]]
    assert times == sorted(times)
    assert out["params"]["e"] == SEED_E[ball]


def test_simulate_defaults_and_table(capsys):
    # Defaults: seed e, mu_t, vx0 and the ball's scene position.
    out = run_json(capsys, "--ball", "golf")
    assert out["params"]["x0"] == pytest.approx(-0.2)
    assert out["params"]["z0"] == pytest.approx(1.70)
    assert out["final"]["x"] == pytest.approx(FINAL_X["golf"], abs=1e-9)
    assert main(["simulate", "--scene", SCENE, "--ball", "golf"]) == 0
    text = capsys.readouterr().out
    assert "step5" in text and "impact" in text and "2.3048901184" in text


def test_sensitivities_final_x(golf_sens):
    s = golf_sens["sensitivities"]
    got = [s["final"]["x"][k] for k in ("e", "mu_t", "vx0")]
    np.testing.assert_allclose(got, GOLF_GRAD, atol=1e-7)
    assert set(s["final"]["z"]) == {"e", "mu_t", "vx0"}
    assert len(s["events"]) == len(golf_sens["events"]) == 6


def test_sensitivities_event_times_vs_finite_difference(golf_sens):
    scene = estim.load_scene(SCENE)
    spec = scene.ball("golf")
    h = 1e-6

    def times(e):
        p = estim.Params(e, 0.98, spec.radius, spec.position, (1.15, 0.0, 0.0))
        ev = estim.simulate(scene, p, 2.3).events
        return np.asarray(ev.t)[: int(ev.count)]

    plus, minus = times(0.7 + h), times(0.7 - h)
    assert len(plus) == len(minus) == 6
    fd = (plus - minus) / (2 * h)
    got = np.array([ev["t"]["e"] for ev in golf_sens["sensitivities"]["events"]])
    np.testing.assert_allclose(got, fd, rtol=1e-5, atol=1e-9)


def test_sensitivities_table(capsys, golf_sens):
    assert main(["simulate", "--scene", SCENE, "--ball", "golf", "--sensitivities"]) == 0
    text = capsys.readouterr().out
    assert "sensitivities" in text and "0.19213914" in text


@pytest.mark.parametrize(
    "args, words",
    [
        (["--ball", "tennis"], ["tennis", "bocce", "golf", "pingpong"]),
        (["--ball", "golf", "--e", "1.5"], ["--e", "[0, 1]"]),
        (["--ball", "golf", "--mu-t", "-0.1"], ["--mu-t", "[0, 1]"]),
        (["--ball", "golf", "--e", "nan"], ["--e", "finite"]),
        (["--ball", "golf", "--vx0", "inf"], ["--vx0", "finite"]),
        (["--ball", "golf", "--t-end", "0"], ["--t-end", "> 0"]),
        (["--ball", "golf", "--z0", "1.0"], ["inside", "step1"]),
    ],
)
def test_bad_inputs(capsys, args, words):
    err = run_error(capsys, "simulate", "--scene", SCENE, *args)
    for word in words:
        assert word in err


SCENES = ROOT / "data" / "scenes"


@pytest.mark.parametrize(("scene", "ball", "args", "registry_values"), [
    ("drop.xml", "pingpong", ["--e", "0.8", "--vy0", "0.4", "--t-end", "0.7"], {}),
    ("stairs_air.xml", "bocce", ["--e", "0.8", "--t-end", "1.0"], {}),
    ("stairs_air.xml", "pingpong", ["--e", "0.8", "--t-end", "0.6", "--drag-coefficient", "0.6",
                                    "--spin-y", "-40", "--spin-z", "5", "--vz0", "0.5"],
     {"drag_coefficient": 0.6, "spin": (0.0, -40.0, 5.0), "vz0": 0.5}),
])
def test_simulate_every_bundled_scene(capsys, scene, ball, args, registry_values):
    """`estim simulate` on the scenes with air (it used to exit 2 asking for masses the
    scene gives) and on the drop: exit 0, and the final state of estim.simulate with the
    same parameters (the ball's mass from the scene; drag and spin where given)."""
    path = str(SCENES / scene)
    capsys.readouterr()
    assert main(["simulate", "--scene", path, "--ball", ball, *args, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    sc = estim.load_scene(path)
    vz0 = registry_values.get("vz0", 0.0)
    vy0 = 0.4 if "--vy0" in args else 0.0
    extra = {k: v for k, v in registry_values.items() if k in ("drag_coefficient", "spin")}
    p = estim.Params.for_ball(sc, ball, e=0.8, mu_t=0.98, velocity=(1.15, vy0, vz0), **extra)
    t_end = float(args[args.index("--t-end") + 1])
    final = estim.simulate(sc, p, t_end).final
    got = [out["final"][k] for k in ("x", "y", "z")] + [out["final"][k] for k in ("vx", "vy", "vz")]
    np.testing.assert_array_equal(got, np.concatenate([np.asarray(final.position), np.asarray(final.velocity)]))
    assert out["n_impacts"] >= 1
    if sc.air is not None:
        assert out["params"]["drag_coefficient"] == registry_values.get("drag_coefficient", 0.47)
        assert [out["params"][f"spin_{a}"] for a in "xyz"] == list(registry_values.get("spin", (0.0, 0.0, 0.0)))
    else:
        assert "drag_coefficient" not in out["params"]  # the air's parameters only where there is air
    text_args = ["simulate", "--scene", path, "--ball", ball, *args]
    assert main(text_args) == 0
    text = capsys.readouterr().out
    assert f"{float(final.position[0]):.10f}" in text
    assert ("drag_coefficient = " in text) == (sc.air is not None)


def test_simulate_refuses_air_parameters_in_a_vacuum(capsys):
    err = run_error(capsys, "simulate", "--scene", SCENE, "--ball", "golf", "--spin-y", "30")
    assert "--spin-y" in err and "scene with air" in err
    err = run_error(capsys, "simulate", "--scene", SCENE, "--ball", "golf", "--drag-coefficient", "-1")
    assert "--drag-coefficient must be > 0" in err


def test_missing_and_malformed_scene(capsys, tmp_path):
    err = run_error(capsys, "simulate", "--scene", str(tmp_path / "nope.xml"), "--ball", "golf")
    assert "nope.xml" in err
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody><geom type=")
    err = run_error(capsys, "simulate", "--scene", str(bad), "--ball", "golf")
    assert "bad.xml" in err


def test_console_entry_subprocess():
    proc = subprocess.run(
        [sys.executable, "-m", "estim", "simulate", "--scene", SCENE, "--ball", "pingpong",
         "--e", "0.85", "--json"],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["n_impacts"] == 4
    assert out["final"]["x"] == pytest.approx(FINAL_X["pingpong"], abs=1e-9)


def test_demo(capsys, tmp_path):
    out_dir = tmp_path / "new" / "out"
    assert main(["demo", "--out", str(out_dir), "--scene", SCENE]) == 0
    text = capsys.readouterr().out
    assert "golf" in text and "bounces" in text
    summary = json.loads((out_dir / "summary.json").read_text())
    rows = {r["ball"]: r for r in summary["balls"]}
    assert set(rows) == set(IMPACTS)
    for ball, row in rows.items():
        assert row["bounces"] == IMPACTS[ball]
        assert row["final_x"] == pytest.approx(FINAL_X[ball], abs=1e-9)
        assert row["e"] == SEED_E[ball]
    png = (out_dir / "heights.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_bench_speed_cpus_errors(capsys):
    """``--cpus`` restricts the process before JAX starts; here (in-process) JAX has started,
    so it is refused with a message, as is a count out of range, and nothing is timed."""
    import os

    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("needs os.sched_setaffinity (Linux)")
    import jax

    jax.devices()  # JAX's backend has started in this process (whatever ran before)
    before = os.sched_getaffinity(0)
    assert "before JAX starts its backend" in run_error(capsys, "bench", "speed", "--cpus", "1")
    too_many = str(len(before) + 1)
    assert "--cpus must lie in [1, " in run_error(capsys, "bench", "speed", "--cpus", too_many)
    assert "--cpus" in run_error(capsys, "bench", "speed", "--cpus", "0")  # argparse: not positive
    assert os.sched_getaffinity(0) == before


def test_restrict_cpus_fresh_process():
    """In a fresh process ``restrict_cpus(1)`` leaves one CPU to the process and to what it
    starts (the bench's first-call subprocess), and JAX then runs there."""
    import os

    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("needs os.sched_setaffinity (Linux)")
    code = (
        "import os, subprocess, sys, json\n"
        "from estim.app._bench import restrict_cpus\n"
        "restrict_cpus(1)\n"
        "import jax.numpy as jnp\n"
        "child = subprocess.run([sys.executable, '-c', 'import os; print(len(os.sched_getaffinity(0)))'],\n"
        "                       capture_output=True, text=True, check=True).stdout\n"
        "print(json.dumps([len(os.sched_getaffinity(0)), int(child), float(jnp.ones(3).sum())]))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == [1, 1, 3.0]


@pytest.mark.slow
def test_bench_speed_json(capsys):
    assert main(["bench", "speed", "--json", "--batch", "100", "--repeats", "3"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("forward_us", "gradient_us", "gradient_all_us", "first_call_s", "batch_final_us", "batch_events_us",
                "batch_all_us", "batch_balls_per_s", "batch_all_balls_per_s", "targets", "machine"):
        assert key in out
    assert set(out["targets"]) == {"forward_us", "gradient_us", "first_call_s", "batch_balls_per_s"}
    assert out["batch_balls_per_s"] == pytest.approx(100 / (out["batch_final_us"] * 1e-6))
    # Bytes per ball, counted from the parts (2 sample times, 64 event slots, 48 segments):
    # the final state is 7 numbers and a flag; the events 64 x (t, position, velocity
    # before and after) and 64 x (face, kind) + count + truncated; the dense solution
    # 48 x 26 numbers (a roll's pivot among them), 48 x (kind, support, reason, face) and 48
    # bounce counts, e, mu_t.
    final = 7 * 8 + 1 * 4
    events = 64 * 10 * 8 + (64 * 2 + 2) * 4
    samples = 2 * 6 * 8
    solution = (48 * 26 + 48 + 2) * 8 + 48 * 4 * 4
    assert out["batch_row_bytes"] == {"final": final, "events": final + events,
                                      "all": final + events + samples + solution}
    # the floor computes nothing, so it costs less than the forward call it bounds (up to
    # the noise of a shared machine: both are medians of a few calls of tens of us)
    assert 0 < out["forward_floor_us"] < 2 * out["forward_us"]
    parts = out["first_call_parts_s"]
    assert set(parts) == {"trace_s", "lower_s", "compile_s", "run_s"} and min(parts.values()) > 0
    assert out["machine"]["cpu_count"] >= 1 and out["machine"]["jax"]
    assert 1 <= out["machine"]["cpus_used"] <= out["machine"]["cpu_count"]
    # conftest imports estim before JAX starts its backend, so XLA took estim's threshold
    assert out["machine"]["small_loops_as_kernels"] is True
    assert out["machine"]["sync_dispatch"] is True  # likewise estim's dispatch (estim._config)
    np.testing.assert_allclose(list(out["gradient"].values()), GOLF_GRAD, atol=1e-7)
    # The air path beside a plain diffrax event loop: the same contacts as a tight reference,
    # both within 1e-9 m of it, and the same gradient (the loop's reverse mode, estim's
    # forward mode: two derivatives of one model that must agree).
    air = out["air"]
    assert air["events"] == air["loop_events"] == air["reference_events"] == [10, 6, 6]
    assert air["final_position_error"] < 1e-9 and air["loop_final_position_error"] < 1e-9
    np.testing.assert_allclose(air["gradient"], air["loop_gradient"], rtol=1e-6)
    assert air["shot_events"] == 1 and air["shot_final_position_error"] < 1e-9
    assert air["shot_forward_us"] > 0 and air["shot_forward_alternating_us"] > 0
    assert air["shot_jacobian_us"] > 0 and air["shot_jacobian_shape"] == [76, 3, 11]  # (0.42 s at 180 Hz)
    assert set(air["targets"]) == {"forward_ratio", "final_position_error", "gradient_ratio", "shot_forward_us",
                                   "shot_jacobian_us", "first_call_s"}


def test_simulate_json_events_carry_the_normal_and_the_velocity_after(capsys):
    """On the staircase with exact edges, a golf ball dropped r/2 beyond step1's top-left
    edge meets the edge's fillet: the event names the edge, its normal points from the edge
    to the centre (60 degrees round from the top, closed form), and the velocity after is
    the reset map of the velocity before about that normal."""
    scene = str(Path(SCENE).with_name("stairs_exact.xml"))
    e, mu = 0.5, 0.5
    assert main(["simulate", "--scene", scene, "--ball", "golf", "--x0", "-0.325", "--z0", "1.6", "--vx0", "0",
                 "--e", str(e), "--mu-t", str(mu), "--t-end", "0.5", "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)["events"][0]
    assert (ev["surface"], ev["face"]) == ("step1", "-x+z")
    n = np.array([-0.5, 0.0, np.sqrt(3.0) / 2])
    np.testing.assert_allclose(ev["normal"], n, rtol=0, atol=1e-12)
    v = np.array([ev["vx"], ev["vy"], ev["vz"]])
    after = mu * (v - (v @ n) * n) - e * (v @ n) * n
    np.testing.assert_allclose([ev["after"][k] for k in ("vx", "vy", "vz")], after, rtol=0, atol=1e-12)


def test_simulate_json_events_carry_the_spin_before_and_after(capsys):
    """A table-tennis ball with backspin and sidespin bounces on the table and hits the net
    (the friction law, in air): each event carries the spin before and after it. The spin
    before the first event is the release spin, and before each later one the spin after
    the one before (constant in flight); each impact keeps the angular momentum about the
    contact point, ``alpha r w + n x v`` per unit m r (the impulse acts at that point); on
    the table the slip ``v_t - r w x n`` keeps its direction. On the closed-form path (the
    seed's staircase) events carry no spin."""
    table = str(SCENES / "table_tennis.xml")
    spin = np.array([-100.0, 0.0, 20.0])
    out = subprocess.run([sys.executable, "-m", "estim", "simulate", "--scene", table, "--ball", "pingpong",
                          "--vx0", "0.9", "--vy0", "4", "--vz0", "1", "--spin-x", str(spin[0]), "--spin-y", "0",
                          "--spin-z", str(spin[2]), "--t-end", "0.8", "--json"],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    events = json.loads(out.stdout)["events"]
    assert [(ev["surface"], ev["kind"]) for ev in events[:2]] == [("table", "impact"), ("net", "impact")]
    ball = estim.Params.for_ball(estim.load_scene(table), "pingpong", e=0.88, mu_t=0.0)
    alpha, r = float(ball.inertia), float(ball.radius)
    before = spin
    for ev in events:
        w = np.array([ev[k] for k in ("wx", "wy", "wz")])
        w_after = np.array([ev["after"][k] for k in ("wx", "wy", "wz")])
        v = np.array([ev[k] for k in ("vx", "vy", "vz")])
        v_after = np.array([ev["after"][k] for k in ("vx", "vy", "vz")])
        n = np.array(ev["normal"])
        np.testing.assert_allclose(w, before, rtol=0, atol=1e-9)
        np.testing.assert_allclose(alpha * r * w_after + np.cross(n, v_after), alpha * r * w + np.cross(n, v),
                                   rtol=0, atol=1e-12)
        before = w_after
    first = events[0]
    n = np.array(first["normal"])
    slip = [np.array([ev[k] for k in ("vx", "vy", "vz")]) - r * np.cross([ev[k] for k in ("wx", "wy", "wz")], n)
            for ev in (first, first["after"])]
    slip = [s - (s @ n) * n for s in slip]
    # (Shrunk along itself, to zero where the ball grips, as here.)
    assert np.linalg.norm(slip[1]) < np.linalg.norm(slip[0])
    assert slip[1] @ slip[0] >= -1e-12 and np.linalg.norm(np.cross(slip[1], slip[0])) < 1e-9 * np.linalg.norm(slip[0])
    assert main(["simulate", "--ball", "golf", "--json"]) == 0
    seed = json.loads(capsys.readouterr().out)["events"]
    assert seed and not any("wx" in ev or "wx" in ev["after"] for ev in seed)


def test_effects_under_the_friction_law_points_to_fit_effects(capsys):
    """``estim effects`` compares against the seed law's closed-form vacuum, which a scene
    under the friction law has not: refused, with the command that sizes its effects."""
    assert main(["effects", "--scene", str(SCENES / "table_tennis.xml")]) == 2
    err = capsys.readouterr().err
    assert "FrictionLaw" in err and "estim fit TRACK --effects" in err
