"""The ``estim`` command line: ``simulate``, ``fit``, ``replay``, ``effects``, ``bench speed``,
``bench fit``, ``bench clips``, ``bench accuracy``, ``demo``."""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import math
import os
import re
import sys
import time

import jax

from .._config import enable_compilation_cache
from .._json import dumps
from ..fitting import _registry as registry
from ..fitting._image import default_image_free
from ..fitting._job import (
    EXPORTS,
    fit_csv,
    fit_export,
    fit_files,
    fit_image_csv,
    fit_image_files,
    fit_pixels,
)
from ..fitting._simulation_report import SENSITIVITY_NAMES, sensitivities, simulation_report
from ..forward._balls import check_outside
from ..forward._effect_report import AIR_DENSITY, AIR_VISCOSITY, effect_sizes
from ..forward._simulate import simulate
from ..forward.laws import law_of
from ..model._scene import load_scene
from ..tracks._camera import read_camera
from ..tracks._csv import MAX_ABS_POSITION, MAX_ABS_TIME
from ..tracks._image import read_image_tracks_csv
from ._bench import (
    format_accuracy,
    format_clips_bench,
    format_fit_bench,
    format_speed,
    run_accuracy,
    run_clips_bench,
    run_fit_bench,
    run_speed,
    write_accuracy,
)
from ._demo import (
    DEMO_TRACKS,
    SEED,
    default_scene_path,
    format_summary,
    run_demo,
    seed_params,
    write_replays,
)

__all__ = ["main"]

THETA = SENSITIVITY_NAMES
# `estim simulate`'s help for the parameters whose defaults are the seed experiment's (the
# others' help comes from the registry, estim.fitting._registry).
SIMULATE_HELP = {
    "e": "coefficient of restitution in [0, 1] (default: the seed value of the ball: bocce 0.55, "
         "golf 0.70, pingpong 0.85)",
    "mu_t": f"tangential coefficient in [0, 1] (default {SEED['mu_t']})",
    **{f"{a}0": f"release {a} (m; default: the ball's position in the scene)" for a in "xyz"},
    **{f"v{a}0": f"release velocity {a} (m/s; default {SEED['velocity'][i]})" for i, a in enumerate("xyz")},
}


class UsageError(Exception):
    """A bad argument found after parsing (exit code 2)."""


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


class _Parser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` that reads a negative number in scientific notation as a
    value (``--vz0 -1e6``): argparse's own pattern knows ``-1`` and ``-1.5`` only, and takes
    ``-1e6`` for an option. (Subparsers are made of the same class.)"""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="estim",
        description="Exact, differentiable simulation of balls bouncing in an MJCF scene.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    sim = sub.add_parser("simulate", help="simulate one ball and list its contact events",
                         description="Simulate one ball of a scene; list its contact events "
                                     "and final state (optionally with sensitivities).")
    sim.add_argument("--scene", default=None,
                     help="MJCF scene file (default: the bundled data/scenes/stairs.xml)")
    sim.add_argument("--ball", required=True, help="name of a ball (body) in the scene")
    # One option per component of the registry that lives in Params (not t0, the release
    # time on a data clock); None: the seed's value, else the registry's default.
    for entry in registry.REGISTRY:
        for name in entry.components if entry.field is not None else ():
            sim.add_argument(_flag(name), type=_finite, default=None, dest=name,
                             help=SIMULATE_HELP.get(name) or _registry_help(entry, name))
    sim.add_argument("--t-end", type=_finite, default=SEED["t_end"],
                     help=f"final time (s), > 0 (default {SEED['t_end']})")
    sim.add_argument("--sensitivities", action="store_true",
                     help="also give d(final x, final z, event times)/d(e, mu_t, vx0)")
    sim.add_argument("--json", action="store_true", help="print one JSON object")
    sim.set_defaults(func=_cmd_simulate)

    fit = sub.add_parser("fit", help="fit e, mu_t and vx0 per ball from tracked positions",
                         description="Fit e, mu_t and the release speed vx0 (and the release "
                                     "point) of every ball in a tracks file, with standard "
                                     "errors. Exit code 0 on success, 1 when a fit did not "
                                     "converge (results still written), 2 on bad input.")
    fit.add_argument("tracks", nargs="+",
                     help="tracks CSV (t,ball,x,z[,y] in s and m), or with --pixels an 'a;b;' pixel "
                          "track; several files (clips of the same ball) are fitted together with "
                          "--shared")
    fit.add_argument("--scene", default=None,
                     help="MJCF scene file (default: data/scenes/stairs.xml)")
    fit.add_argument("--out", default=None, help="output directory for fit.json and plots")
    fit.add_argument("--json", action="store_true", help="print the fit.json object to stdout")
    fit.add_argument("--loss", default="cauchy", choices=("cauchy", "huber", "l2"),
                     help="robust loss (default cauchy)")
    fit.add_argument("--camera", action="append", default=None, metavar="CAM",
                     help="a calibrated camera (OpenCV FileStorage YAML/JSON, or the short form rvec, "
                          "tvec, f, w, h); the tracks file is then an image-track CSV t,ball,u,v[,camera] "
                          "in pixels, fitted in pixels; repeat for several cameras (the camera column "
                          "names them by file stem or number)")
    fit.add_argument("--format", default="csv", choices=("csv",) + tuple(EXPORTS),
                     help="the tracks file: estim's CSV (default), or a video tracker's export: Tracker's "
                          "'Export Data' text, Kinovea's trajectory CSV or Gnuplot text (with --units)")
    fit.add_argument("--units", choices=("m", "px"), default=None,
                     help="with --format tracker|kinovea: the export's units, metres (calibrated) or pixels "
                          "(then with --camera, --origin and --y-up or --y-down)")
    fit.add_argument("--origin", type=_finite, nargs=2, default=None, metavar=("U0", "V0"),
                     help="an export in pixels: the OpenCV pixel (u right, v down) of the export's origin")
    updown = fit.add_mutually_exclusive_group()
    updown.add_argument("--y-up", dest="y_up", action="store_const", const=True, default=None,
                        help="an export in pixels: its y grows upward in the image (Tracker's axes)")
    updown.add_argument("--y-down", dest="y_up", action="store_const", const=False,
                        help="an export in pixels: its y grows downward (Kinovea's image space)")
    fit.add_argument("--angle", type=_finite, default=None, metavar="DEG",
                     help="an export in pixels: the angle of its x axis, counter-clockwise (default 0)")
    fit.add_argument("--time-unit", choices=("s", "ms"), default=None,
                     help="with --format kinovea: the unit of its time column, where the header does not say")
    fit.add_argument("--pixels", action="store_true",
                     help="the file is an 'a;b;' pixel track (rows grow downward)")
    fit.add_argument("--frame-interval", type=_finite, default=None,
                     help="seconds per frame (required with --pixels)")
    fit.add_argument("--metres-per-pixel", type=_finite, default=None,
                     help="pixel scale; default: estimated from gravity")
    fit.add_argument("--ball", default=None, help="the ball of a pixel track (with --pixels)")
    fit.add_argument("--from-bounce", type=int, default=0,
                     help="with --pixels: fit only the data after this bounce (default 0: from "
                          "the release); leaves out the fastest flights, where drag matters most")
    fit.add_argument("--also", nargs="+", default=[], metavar="PARAM",
                     choices=registry.NAMES + tuple(p.name for p in registry.REGISTRY if p.components != (p.name,)),
                     help="more parameters to fit besides e, mu_t, vx0 and the release point "
                          "(names of the parameter registry): vz0, t0 (time offset), y0, vy0, and "
                          "in a scene with air drag_coefficient and spin_x, spin_y, spin_z (rad/s); "
                          "a vector's name stands for its components (velocity, position, spin)")
    fit.add_argument("--prior", action="append", default=None, metavar="NAME=MEAN,SD",
                     help="what is known of a fitted parameter before the data: its mean and "
                          "standard deviation (e.g. e=0.88,0.05; a vector's name for each component), "
                          "or NAME=none to drop the scene's prior on it; repeatable. The scene's priors "
                          "(<numeric name=\"estim:prior:NAME\">) apply unless dropped")
    fit.add_argument("--effects", action="store_true",
                     help="also say how far each effect of the model (drag, Magnus, wind, the spin at "
                          "the bounce, the bounce's friction) moves the fitted ball over the track, in "
                          "noise levels: what this track can and cannot tell apart")
    fit.add_argument("--shared", nargs="+", default=None, metavar="PARAM",
                     choices=registry.NAMES + tuple(p.name for p in registry.REGISTRY if p.components != (p.name,)),
                     help="with several files: the parameters shared by every clip of a ball (e.g. "
                          "e drag_coefficient), estimated once from all clips; the release state "
                          "(and a pixel clip's scale, or an image clip's cameras' clock offsets) stays "
                          "per clip; with --camera, several image-track files of the cameras")
    fit.add_argument("--devices", type=_positive_int, default=None,
                     help="with --shared: split the clips over this many of the devices JAX sees "
                          "(default: all)")
    fit.add_argument("--distributed", action="store_true",
                     help="with --shared: start jax.distributed first (one process per host, "
                          "launched as docs/pages/fitting.md says) and split the clips over every "
                          "device of every host")
    fit.set_defaults(func=_cmd_fit)

    bench = sub.add_parser("bench", help="benchmarks", description="Benchmarks.")
    bsub = bench.add_subparsers(dest="bench", metavar="BENCH", required=True)
    speed = bsub.add_parser("speed", help="forward / gradient / first-call / batch timings",
                            description="Time the seed scene in this process (first call in "
                                        "a fresh subprocess) against the targets.")
    speed.add_argument("--json", action="store_true", help="print one JSON object")
    speed.add_argument("--batch", type=_positive_int, default=10_000,
                       help="balls in the batch timing (default 10000)")
    speed.add_argument("--repeats", type=_positive_int, default=200,
                       help="timed calls per figure (median; default 200)")
    speed.add_argument("--scene", default=None, help="scene file (default: the seed scene)")
    speed.add_argument("--cpus", type=_positive_int, default=None,
                       help="run on this many CPUs (Linux: the process's CPU affinity, set before "
                            "JAX starts, as `taskset` does): shows what XLA's thread pool costs a "
                            "small call (docs/pages/speed.md)")
    speed.add_argument("--no-air", dest="air", action="store_false",
                       help="leave out the air path against a plain diffrax event loop (about a minute of "
                            "compiling; docs/pages/speed.md)")
    speed.set_defaults(func=_cmd_bench_speed)
    fitb = bsub.add_parser("fit", help="estim fit on the bundled tracks: cold, cached, steady",
                           description="Time `estim fit` on the bundled tracks from process "
                                       "start to written fit.json (no cache, warm cache) and "
                                       "the compiled fit in-process.")
    fitb.add_argument("--json", action="store_true", help="print one JSON object")
    fitb.add_argument("--repeats", type=_positive_int, default=5, help="steady-state repeats")
    fitb.set_defaults(func=_cmd_bench_fit)
    clipsb = bsub.add_parser("clips", help="many clips fitted together: cold and compiled, per clip",
                             description="Fit N staircase clips (3 balls each, e shared per ball) "
                                         "and N pixel drops (e shared) together: estim fit from "
                                         "process start without a compilation cache, the "
                                         "compiled fit in-process, and one clip's single fit "
                                         "beside it.")
    clipsb.add_argument("--clips", type=_positive_int, default=100, help="clips per set (default 100)")
    clipsb.add_argument("--json", action="store_true", help="print one JSON object")
    clipsb.set_defaults(func=_cmd_bench_clips)
    accb = bsub.add_parser("accuracy", help="work-precision table and plot of the ODE path",
                           description="Work-precision study: on the seed scene without air, the "
                                       "closed form against the ODE path forced with diffrax Tsit5, "
                                       "Dopri5 and Dopri8 at rtol 1e-3 ... 1e-12 (atol = rtol/10); "
                                       "in still air (stairs_air.xml), the same against Dopri8 at "
                                       "rtol 1e-13. Prints the tables; with --out also writes "
                                       "accuracy_table.md, accuracy.png and accuracy.json there "
                                       "(the docs page is written by docs/scripts/accuracy.py).")
    accb.add_argument("--out", default=None,
                      help="output directory for accuracy_table.md, accuracy.png and "
                           "accuracy.json (default: write no files)")
    accb.add_argument("--repeats", type=_positive_int, default=None,
                      help="timing rounds per setting, median reported (default 7; 3 with --quick)")
    accb.add_argument("--quick", action="store_true",
                      help="one solver (Tsit5), two tolerances (1e-4, 1e-9), reference Tsit5 at 1e-12")
    accb.add_argument("--json", action="store_true", help="print the results as one JSON object")
    accb.set_defaults(func=_cmd_bench_accuracy)

    eff = sub.add_parser("effects", help="how much drag, Magnus and wind change each ball's motion",
                         description="Effect sizes: simulate the scene's balls (released at their "
                                     "positions in the scene) in a vacuum and with each effect of "
                                     "the air alone (still air, quadratic drag, linear drag, Magnus, "
                                     "wind; and the scene's own air if it has one), and report the "
                                     "change of final position, bounce times, largest deviation and "
                                     "bounce counts per ball.")
    eff.add_argument("--scene", default=None,
                     help="MJCF scene file (default: data/scenes/stairs.xml)")
    eff.add_argument("--ball", action="append", default=None,
                     help="a ball of the scene (repeat for several; default: all)")
    eff.add_argument("--e", type=_finite, default=None,
                     help="coefficient of restitution in [0, 1] for every ball (default: the seed "
                          "value: bocce 0.55, golf 0.70, pingpong 0.85)")
    eff.add_argument("--mu-t", type=_finite, default=SEED["mu_t"],
                     help=f"tangential coefficient in [0, 1] (default {SEED['mu_t']})")
    eff.add_argument("--vx0", type=_finite, default=SEED["velocity"][0],
                     help=f"release velocity along x (m/s; default {SEED['velocity'][0]})")
    eff.add_argument("--t-end", type=_finite, default=SEED["t_end"],
                     help=f"final time (s), > 0 (default {SEED['t_end']})")
    eff.add_argument("--density", type=_finite, default=None,
                     help="air density (kg/m^3) of the drag, Magnus and wind runs (default: the "
                          "scene's, else 1.204, dry air at 20 C)")
    eff.add_argument("--viscosity", type=_finite, default=None,
                     help="air viscosity (Pa s) of the linear-drag and wind runs (default: the "
                          "scene's, else 1.81e-5)")
    eff.add_argument("--spin", type=_finite, default=50.0,
                     help="backspin (rad/s; negative: topspin) of the Magnus run (default 50)")
    eff.add_argument("--wind", type=_finite, default=3.0,
                     help="wind speed along +x (m/s) of the wind run (default 3)")
    eff.add_argument("--json", action="store_true", help="print one JSON object")
    eff.set_defaults(func=_cmd_effects)

    demo = sub.add_parser("demo", help="the main job on the bundled data: fit, table, plots",
                          description="Fit the bundled tracks (data/tracks/stairs_demo.csv): "
                                      "table, fit.json, plots and replays (replay.gif, "
                                      "sideview.gif) into --out; also simulate the seed scene "
                                      "(summary.json, heights.png, energy.png).")
    demo.add_argument("--out", required=True, help="output directory (created if missing)")
    demo.add_argument("--scene", default=None, help="scene file (default: the seed scene)")
    demo.set_defaults(func=_cmd_demo)

    rep = sub.add_parser("replay", help="render the fitted model against the tracks (GIF/MP4)",
                         description="Replay a fit: MuJoCo renders the fitted balls offscreen, "
                                     "with the measured samples as translucent halos of the same "
                                     "colour, from a side camera; a caption gives the time and the "
                                     "fitted parameters. --view side draws the same with matplotlib "
                                     "(no OpenGL needed). Exit code 0 on success, 1 when MuJoCo "
                                     "cannot render here, 2 on bad input.")
    rep.add_argument("tracks", help="tracks CSV (t,ball,x,z[,y] in s and m), or with --camera the image-track "
                                    "CSV (t,ball,u,v[,camera]) that the fit read")
    rep.add_argument("fit", help="fit.json written by `estim fit`")
    rep.add_argument("--scene", default=None,
                     help="MJCF scene file (default: data/scenes/stairs.xml)")
    rep.add_argument("--out", default="replay.gif",
                     help="output file, .gif or .mp4 (MP4 needs ffmpeg on PATH; default replay.gif)")
    rep.add_argument("--fps", type=_finite, default=25.0,
                     help="frames per second (default 25; a GIF shows at most 50)")
    rep.add_argument("--width", type=_positive_int, default=640, help="picture width in pixels (default 640)")
    rep.add_argument("--height", type=_positive_int, default=360, help="picture height in pixels (default 360)")
    rep.add_argument("--trail", type=_finite, default=0.3,
                     help="seconds of recent measured samples shown as dots (default 0.3; 0: none)")
    rep.add_argument("--view", choices=("mujoco", "side"), default="mujoco",
                     help="mujoco: 3-D offscreen rendering (default); side: matplotlib x-z view")
    rep.add_argument("--camera", action="append", default=None, metavar="CAM",
                     help="the cameras of a fit in pixels (as given to `estim fit`); MuJoCo renders from the "
                          "first one's viewpoint, the tracked pixels placed on their rays at the fitted depth")
    rep.set_defaults(func=_cmd_replay)
    return parser


def _flag(name: str) -> str:
    """The command-line option of a registry component: ``mu_t`` -> ``--mu-t``."""
    return "--" + name.replace("_", "-")


def _registry_help(entry, name: str) -> str:
    """Help for a registry component: its documentation, unit and default."""
    try:
        default = f"{entry.default(None)[entry.components.index(name)]:g}"
    except (AttributeError, TypeError):  # a default that the ball gives
        default = "the ball's in the scene"
    where = f"; acts only {entry.acts_where}" if entry.acts_where else ""
    unit = f"{entry.unit}; " if entry.unit else ""
    part = f", {'xyz'[entry.components.index(name)]} component" if len(entry.components) == 3 else ""
    return f"{entry.doc}{part} ({unit}default {default}{where})"


def progress(stream=None):
    start = time.perf_counter()

    def say(msg: str) -> None:
        print(f"[{time.perf_counter() - start:6.1f} s] {msg}", file=stream or sys.stderr, flush=True)

    return say


def main(argv: list[str] | None = None) -> int:
    # The modules are loaded: their objects live as long as the process. Frozen for the
    # command, the garbage collector's full passes no longer walk them while a fit's
    # program is traced (millions of short-lived objects): the camera shot of `estim bench
    # fit` traced and lowered in 2.07 s instead of 2.32 s. (Unfrozen after: a process
    # that calls main again, a test, collects them as before.)
    gc.freeze()
    try:
        return _command(argv)
    finally:
        gc.unfreeze()


def _command(argv: list[str] | None) -> int:
    enable_compilation_cache()
    parser = build_parser()
    args = parser.parse_args(argv)  # argparse's own errors exit with status 2
    try:
        return args.func(args)
    except (UsageError, ValueError, KeyError, FileNotFoundError, IsADirectoryError) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        if isinstance(exc, FileNotFoundError) and not str(exc).strip():
            msg = "file not found"
        print(f"estim {args.command}: error: {msg}", file=sys.stderr)
        return 2


# --------------------------------------------------------------------------- simulate


def _simulation_values(args, scene, spec) -> dict[str, float]:
    """Every registry component of ``estim simulate``'s ball: the options given, else the
    seed experiment's e (per ball), mu_t and velocity, else the registry's defaults (the
    ball's position in the scene, no spin, ...)."""
    seed = {"mu_t": SEED["mu_t"], **dict(zip(("vx0", "vy0", "vz0"), SEED["velocity"], strict=True))}
    if args.ball in SEED["e"]:
        seed["e"] = SEED["e"][args.ball]
    given = {n: getattr(args, n) for n in registry.NAMES if getattr(args, n, None) is not None}
    for name, v in given.items():
        entry = registry.component(name)
        why = entry.transform.refuse(v)
        if why:
            raise UsageError(f"{_flag(name)} {why}, got {v}")
        if scene is not None and not entry.acts(scene):
            raise UsageError(f"{_flag(name)}: {name} acts only {registry.where_it_acts(name)}, and this scene does "
                             "not have it")
    if spec is None:
        return {}
    if "e" not in given and "e" not in seed:
        raise UsageError(f"--e is required for ball {args.ball!r} (no seed value)")
    return {**registry.defaults(spec), **seed, **given}


def _cmd_simulate(args) -> int:
    _simulation_values(args, None, None)  # the ranges of the options given, before any file is read
    if not args.t_end > 0:
        raise UsageError(f"--t-end must be > 0 (seconds), got {args.t_end}")

    scene_path = args.scene or default_scene_path()
    scene = load_scene(scene_path)
    spec = scene.ball(args.ball)
    values = _simulation_values(args, scene, spec)
    # The limits of the track reader (estim.tracks._csv): beyond them the numbers are not
    # metres and seconds of a tabletop experiment, whatever the simulator could do with them.
    for name in registry.component("x0").components:
        if abs(values[name]) > MAX_ABS_POSITION:
            raise UsageError(f"{_flag(name)} = {values[name]:g} is not a position in metres (|{name}| > "
                             f"{MAX_ABS_POSITION:g}); millimetres? estim never rescales")
    if args.t_end > MAX_ABS_TIME:
        raise UsageError(f"--t-end = {args.t_end:g} is not a time in seconds (> {MAX_ABS_TIME:g}); "
                         "milliseconds? estim never rescales")
    air = scene.air is not None
    # The mass only where the air needs it: without it the pytree (and so the compiled
    # program) is that of a plain simulation.
    params = registry.to_params(values, radius=spec.radius, mass=spec.mass if air else None, inertia=spec.inertia,
                                scene=scene)
    check_outside(scene, params, names=[args.ball])
    traj = simulate(scene, params, args.t_end)

    out = {"scene": scene_path, "ball": spec.name, "radius": float(params.radius),
           **simulation_report(scene, traj, values, args.t_end)}
    if args.sensitivities:
        out["sensitivities"] = sensitivities(scene, params, values, args.t_end, THETA)

    if args.json:
        print(dumps(out))
    else:
        print(_format_simulation(out))
    return 0


def _format_simulation(out: dict) -> str:
    p = out["params"]
    lines = [
        f"ball {out['ball']} (r = {out['radius']} m) in {out['scene']}",
        f"e = {p['e']}, mu_t = {p['mu_t']}, release ({p['x0']}, {p['y0']}, {p['z0']}) m, "
        f"velocity ({p['vx0']}, {p['vy0']}, {p['vz0']}) m/s, t_end = {p['t_end']} s",
    ]
    # The rest of the registry's parameters that the simulation used (in a scene with air:
    # the drag coefficient and the spin), one entry each; an opt-in effect (e_slope,
    # compression) only where it is switched on, not at zero.
    for entry in registry.REGISTRY:
        if entry.name in ("e", "mu_t", "position", "velocity") or entry.components[0] not in p:
            continue
        if entry.opt_in and all(p[c] == 0 for c in entry.components):
            continue
        numbers = ", ".join(f"{p[c]}" for c in entry.components)
        lines.append(f"{entry.name} = {numbers if len(entry.components) == 1 else '(' + numbers + ')'}"
                     + (f" {entry.unit}" if entry.unit else ""))
    lines += [
        "",
        f"{out['n_events']} events ({out['n_impacts']} impacts)"
        + (" [truncated: more events than listed]" if out["truncated"] else ""),
        f"{'#':>3} {'t (s)':>13} {'x (m)':>13} {'z (m)':>13} {'vx (m/s)':>13} {'vz (m/s)':>13}  "
        f"{'surface':<12} kind",
    ]
    for i, ev in enumerate(out["events"]):
        lines.append(
            f"{i + 1:>3} {ev['t']:>13.9f} {ev['x']:>13.9f} {ev['z']:>13.9f} {ev['vx']:>13.9f} "
            f"{ev['vz']:>13.9f}  {ev['surface'] + ' ' + ev['face']:<12} {ev['kind']}"
        )
    f = out["final"]
    lines += [
        "",
        f"final state at t = {f['t']} s:",
        f"  position ({f['x']:.10f}, {f['y']:.10f}, {f['z']:.10f}) m",
        f"  velocity ({f['vx']:.10f}, {f['vy']:.10f}, {f['vz']:.10f}) m/s",
    ]
    if "sensitivities" in out:
        s = out["sensitivities"]
        head = "".join(f"{'d/d' + k:>16}" for k in THETA)
        lines += ["", "sensitivities (one jacfwd):", f"{'':<12}{head}"]
        for name, row in (("final x", s["final"]["x"]), ("final z", s["final"]["z"])):
            lines.append(f"{name:<12}" + "".join(f"{row[k]:>16.8f}" for k in THETA))
        for i, ev in enumerate(s["events"]):
            lines.append(f"{f't event {i + 1}':<12}" + "".join(f"{ev['t'][k]:>16.8f}" for k in THETA))
    return "\n".join(lines)


# --------------------------------------------------------------------------- bench, demo


def _cmd_bench_speed(args) -> int:
    result = run_speed(batch=args.batch, repeats=args.repeats, scene_path=args.scene, cpus=args.cpus, air=args.air)
    if args.json:
        print(dumps(result))
    else:
        print(format_speed(result))
    return 0


def _cmd_bench_fit(args) -> int:
    result = run_fit_bench(repeats=args.repeats)
    print(dumps(result) if args.json else format_fit_bench(result))
    return 0


def _cmd_bench_clips(args) -> int:
    r = run_clips_bench(n=args.clips)
    print(dumps(r, indent=2) if args.json else format_clips_bench(r))
    return 0


def _cmd_bench_accuracy(args) -> int:
    out = args.out
    if out is not None and os.path.exists(out) and not os.path.isdir(out):
        raise UsageError(f"--out {out}: not a directory")
    repeats = args.repeats or (3 if args.quick else 7)
    result = run_accuracy(repeats=repeats, quick=args.quick, say=progress())
    if args.json:
        print(dumps(result))
    else:
        print(format_accuracy(result))
    if out is not None:
        print("wrote " + ", ".join(write_accuracy(result, out)), file=sys.stderr)
    return 0


# --------------------------------------------------------------------------- effects


def _cmd_effects(args) -> int:
    for name, value in (("--e", args.e), ("--mu-t", args.mu_t)):
        if value is not None and not 0.0 <= value <= 1.0:
            raise UsageError(f"{name} must lie in [0, 1], got {value}")
    if not args.t_end > 0:
        raise UsageError(f"--t-end must be > 0 (seconds), got {args.t_end}")
    for name, value in (("--density", args.density), ("--viscosity", args.viscosity)):
        if value is not None and value < 0:
            raise UsageError(f"{name} must be >= 0, got {value}")
    scene_path = args.scene or default_scene_path()
    scene = load_scene(scene_path)
    law = law_of(scene)
    if law.couples_spin:
        raise UsageError(f"{scene_path}: estim effects compares each effect against the closed-form vacuum "
                         f"run of the seed's factor law; this scene's {type(law).__name__} couples the "
                         "bounce to the spin and has no such baseline; for a track in this scene, "
                         "estim fit TRACK --effects sizes every effect of the model (drag, Magnus, the "
                         "spin at the bounce, the bounce's friction) in noise levels")
    if not scene.balls:
        raise UsageError(f"{scene_path}: the scene defines no balls (spheres on free bodies)")
    names = list(dict.fromkeys(args.ball)) if args.ball else [b.name for b in scene.balls]
    params = seed_params(scene, names, e=args.e, mu_t=args.mu_t, velocity=(args.vx0, 0.0, 0.0))
    air = scene.air
    density = args.density if args.density is not None else (float(air.density) if air is not None else AIR_DENSITY)
    viscosity = args.viscosity if args.viscosity is not None else (
        float(air.viscosity) if air is not None else AIR_VISCOSITY)
    report = effect_sizes(scene, params, args.t_end, names=names, density=density, viscosity=viscosity,
                          spin=args.spin, wind=args.wind)
    out = {"scene": scene_path, "params": {"e": [float(x) for x in params.e], "mu_t": args.mu_t,
                                           "vx0": args.vx0, "t_end": args.t_end}}
    out.update(report.to_json())
    if args.json:
        print(dumps(out))
    else:
        s = report.settings
        print(f"effect sizes in {scene_path}, {args.t_end} s, release at the scene's positions, "
              f"vx0 = {args.vx0} m/s, mu_t = {args.mu_t}")
        print(f"air: density {s['density']} kg/m^3, viscosity {s['viscosity']} Pa s; Magnus run: "
              f"{args.spin} rad/s backspin, no drag; wind run: {args.wind} m/s along +x vs still air")
        print("changes against the vacuum (closed form): final position distance, final x, first and "
              "second bounce times, largest deviation; bounces: baseline -> with the effect")
        print()
        print(report.format_table())
    return 0


def _cmd_demo(args) -> int:
    summary = run_demo(args.out, scene_path=args.scene)
    print(format_summary(summary))
    print("wrote " + ", ".join(summary["files"]))
    # `estim fit` on the bundled tracks, its arguments parsed as the command line would (every
    # option of `estim fit` gets its default).
    fit_args = build_parser().parse_args(["fit", str(DEMO_TRACKS), "--out", str(args.out)]
                                         + (["--scene", str(args.scene)] if args.scene else []))
    code = _cmd_fit(fit_args)
    print("wrote " + ", ".join(write_replays(args.out, scene_path=args.scene)))
    return code


# --------------------------------------------------------------------------- replay


def _cmd_replay(args) -> int:
    from ..show._replay import EncoderNotFoundError, RenderError, check_output  # lazy: MuJoCo

    for what, path in (("tracks", args.tracks), ("fit", args.fit), *(("camera", c) for c in args.camera or ())):
        if not os.path.isfile(path):
            raise FileNotFoundError(f"{what} file not found: {path}")
    if not args.fps > 0:
        raise UsageError(f"--fps must be > 0, got {args.fps}")
    if args.trail < 0:
        raise UsageError(f"--trail must be >= 0 (seconds), got {args.trail}")
    out_dir = os.path.dirname(os.path.abspath(args.out))
    if not os.path.isdir(out_dir):
        raise UsageError(f"--out {args.out}: the folder {out_dir} does not exist")
    try:
        check_output(args.out, args.fps)  # suffix, GIF frame rate, ffmpeg: before any work
    except EncoderNotFoundError as err:
        raise UsageError(str(err)) from None
    scene = args.scene or default_scene_path()
    options = dict(fps=args.fps, width=args.width, height=args.height, trail=args.trail)
    if args.camera:
        if args.view == "side":
            raise UsageError("--camera renders from the camera's viewpoint with MuJoCo; --view side is a matplotlib x-z view")
        from ..show._image_plots import replay_samples  # lazy: matplotlib

        cameras = [read_camera(p) for p in args.camera]
        tracks = read_image_tracks_csv(args.tracks, cameras)
        with open(args.fit) as f:
            fit = json.load(f)
        args.tracks, options["camera"] = replay_samples(tracks, fit), cameras[0]
    if args.view == "side":
        from ..show._sideview import render_sideview  # lazy: matplotlib

        info = render_sideview(scene, args.fit, args.tracks, args.out, **options)
    else:
        from ..show._replay import render_replay  # lazy: MuJoCo

        try:
            info = render_replay(scene, args.fit, args.tracks, args.out, **options)
        except RenderError as err:
            print(f"estim replay: error: {err}", file=sys.stderr)
            return 1
    print(f"wrote {info.path}: {info.n_frames} frames at {info.fps:g} fps, "
          f"t = {info.t_start:.3f} .. {info.t_end:.3f} s, balls {', '.join(info.balls)} "
          f"({info.renderer})")
    return 0


# --------------------------------------------------------------------------- fit


def _also(args, base, priors: bool = True) -> dict:
    """``free=`` for the fit when --also asks for more parameters (registry names; a
    vector's name stands for its components), else nothing (the fit's default), and
    ``prior=`` when --prior gives priors, ``effects=True`` with --effects. ``base``: the
    default to add them to, or a scene
    (its default, ``registry.default_free``, with what has a prior unless ``priors`` is
    false, as for clips fitted together; the lateral release state joins it where the
    tracks have y, as in ``estim.fit``)."""
    out = {"prior": _priors(args.prior)} if getattr(args, "prior", None) else {}
    if getattr(args, "effects", False):
        out["effects"] = True
    if not getattr(args, "also", None):
        return out
    if not isinstance(base, tuple):
        known = registry.priors(base, out.get("prior")) if priors else ()
        base = registry.default_free(base, lateral=False, known=tuple(known))
    return {**out, "free": tuple(base) + tuple(n for n in registry.expand(args.also) if n not in base)}


def _priors(items) -> dict:
    """``--prior NAME=MEAN,SD`` or ``NAME=none`` as ``estim.fit``'s ``prior``."""
    out = {}
    for item in items:
        name, sep, spec = item.partition("=")
        if not sep or not name:
            raise UsageError(f"--prior {item!r}: expected NAME=MEAN,SD or NAME=none")
        if spec.strip().lower() == "none":
            out[name] = None
            continue
        parts = spec.split(",")
        try:
            mean, sd = (_finite(p) for p in parts) if len(parts) == 2 else (None, None)
        except argparse.ArgumentTypeError as err:
            raise UsageError(f"--prior {item!r}: {err}") from None
        if mean is None:
            raise UsageError(f"--prior {item!r}: expected NAME=MEAN,SD (two numbers) or NAME=none")
        out[name] = (mean, sd)
    return out


def _check_pixel_options(args) -> None:
    if args.pixels:
        if args.frame_interval is None or args.frame_interval <= 0:
            raise UsageError("--pixels needs --frame-interval SECONDS (> 0): a pixel track has no time column")
        if args.metres_per_pixel is not None and args.metres_per_pixel <= 0:
            raise UsageError(f"--metres-per-pixel must be > 0, got {args.metres_per_pixel}")
        if not args.ball:
            raise UsageError("--pixels needs --ball NAME (the ball of the scene the track follows)")
    else:
        if args.from_bounce:
            raise UsageError("--from-bounce only applies with --pixels")
        for flag in ("frame_interval", "metres_per_pixel") + (("ball",) if args.format == "csv" else ()):
            if getattr(args, flag) is not None:
                raise UsageError(f"--{flag.replace('_', '-')} only applies with --pixels"
                                 + (" or --format tracker|kinovea" if flag == "ball" else ""))


def _distributed_settings() -> dict:
    """``jax.distributed.initialize``'s coordinator, process count and id from
    ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID`` where set (else
    JAX detects them itself on Slurm, Open MPI and Cloud TPU)."""
    names = {"coordinator_address": ("JAX_COORDINATOR_ADDRESS", str), "num_processes": ("JAX_NUM_PROCESSES", int),
             "process_id": ("JAX_PROCESS_ID", int)}
    out = {}
    for key, (env, kind) in names.items():
        if os.environ.get(env):
            try:
                out[key] = kind(os.environ[env])
            except ValueError:
                raise UsageError(f"{env}={os.environ[env]!r} is not a valid {kind.__name__}") from None
    return out


@contextlib.contextmanager
def _stdout_to_stderr():
    """Standard output, at the file descriptor, sent to standard error: the library that
    joins JAX's processes (Gloo) prints its connections to the C++ standard output, and the
    result (``--json``) must be all that standard output holds."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _devices(args) -> list:
    """The devices of ``--devices N`` (the first N JAX sees), default all."""
    devices = jax.devices()
    if args.devices is not None:
        if args.devices > len(devices):
            raise UsageError(f"--devices {args.devices}: JAX sees only {len(devices)} device(s)")
        devices = devices[: args.devices]
    return devices


def _cmd_fit_image_clips(args, scene, say) -> int:
    """``estim fit A B ... --camera CAM --shared NAMES``: image-track files fitted together."""
    if args.format != "csv":
        raise UsageError(f"--format {args.format} with --shared: fit a tracker's export on its own")
    result, clips = fit_image_files(args.tracks, args.camera, scene, shared=tuple(args.shared), say=say,
                                    loss=args.loss, devices=_devices(args),
                                    **_also(args, default_image_free(scene, len(args.camera))))
    extra = {"cameras": [c.to_json() for c in next(iter(clips.values())).cameras]}
    if args.out:
        from ..show._outputs import write_pooled_outputs  # lazy: matplotlib

        write_pooled_outputs(result, clips, args.out, extra)
        say(f"wrote {os.path.join(args.out, 'fit.json')}, forest.png and each clip's pixels-LABEL.png")
    if args.json:
        print(dumps({**result.to_json(), **extra}, indent=2))
    else:
        print(result.format_table())
    return 0 if result.converged else 1


def _cmd_fit_clips(args, scene, say) -> int:
    """``estim fit A B ... --shared NAMES``: the clips fitted together."""
    devices = _devices(args)
    with _stdout_to_stderr() if jax.process_count() > 1 else contextlib.nullcontext():
        result, data = fit_files(
            args.tracks, scene, shared=tuple(args.shared), pixels=args.pixels, ball=args.ball,
            frame_interval=args.frame_interval, metres_per_pixel=args.metres_per_pixel,
            from_bounce=args.from_bounce, say=say, loss=args.loss, devices=devices,
            **_also(args, registry.side_view_free(scene) if args.pixels else scene, priors=False))
    payload = result.to_json()
    if jax.process_index() > 0:  # every process holds the result: process 0 reports it
        return 0 if result.converged else 1
    if args.out:
        from ..show._outputs import write_pooled_outputs  # lazy: matplotlib

        write_pooled_outputs(result, data, args.out)
        say(f"wrote {os.path.join(args.out, 'fit.json')}, forest.png and fit.png")
    if args.json:
        print(dumps(payload, indent=2))
    else:
        print(result.format_table())
    return 0 if result.converged else 1


def _finish_fit(args, result, data, extra, say) -> int:
    """fit.json and the plots (with --out), the table or the JSON; the exit code."""
    payload = result.to_json()
    payload.update(extra)
    if args.out:
        from ..show._outputs import write_outputs  # lazy: matplotlib

        write_outputs(result, data, args.out, extra)
        say(f"wrote {os.path.join(args.out, 'fit.json')} and plots")
    if args.json:
        print(dumps(payload, indent=2))
    else:
        print(result.format_table())
        if "metres_per_pixel" in extra:
            print(f"scale {extra['metres_per_pixel'] * 1e3:.4f} mm/px, surface row {extra['surface_row_px']:.1f} px")
    return 0 if result.converged else 1


def _cmd_fit_image(args, scene, say) -> int:
    """``estim fit TRACKS --camera CAM [--camera CAM2 ...]``: a fit in pixels."""
    result, tracks = fit_image_csv(args.tracks, args.camera, scene, say=say, loss=args.loss,
                                   **_also(args, default_image_free(scene, len(args.camera))))
    return _finish_fit(args, result, tracks, {"cameras": [c.to_json() for c in tracks.cameras]}, say)


def _cmd_fit_export(args, scene, say) -> int:
    """``estim fit EXPORT --format tracker|kinovea --units m|px ...``."""
    if args.pixels:
        raise UsageError("--pixels reads an 'a;b;' pixel track; a tracker's export in pixels takes --units px "
                         "and --camera")
    if args.units is None:
        raise UsageError(f"--format {args.format} needs --units m or px: the export does not say reliably")
    if args.time_unit is not None and args.format != "kinovea":
        raise UsageError("--time-unit only applies with --format kinovea")
    if args.camera and len(args.camera) > 1:
        raise UsageError("a tracker's export is one video: give one --camera")
    reader = {"ball": args.ball, "origin": args.origin, "y_up": args.y_up, "angle_deg": args.angle}
    if args.format == "kinovea":
        reader["time_unit"] = args.time_unit
    camera = args.camera[0] if args.camera else None
    free = default_image_free(scene, 1) if args.units == "px" else scene
    result, data = fit_export(args.tracks, args.format, scene, units=args.units, camera_path=camera, say=say,
                              reader=reader, loss=args.loss, **_also(args, free))
    extra = {"cameras": [c.to_json() for c in data.cameras]} if args.units == "px" else {}
    return _finish_fit(args, result, data, extra, say)


def _cmd_fit(args) -> int:
    if args.distributed and args.camera:
        raise UsageError("--distributed with --camera: image-track files fitted together run on one host "
                         "(its devices: --devices)")
    if args.distributed and args.shared is not None:
        # First: JAX refuses to join the processes once its backend is up, and loading
        # the scene already makes arrays.
        jax.distributed.initialize(**_distributed_settings())
    scene = load_scene(args.scene or default_scene_path())
    for path in args.tracks:
        if not os.path.isfile(path):
            raise FileNotFoundError(f"tracks file not found: {path}")
    _check_pixel_options(args)
    say = progress()
    if args.shared is not None:
        if args.prior and not args.camera:
            raise UsageError("--prior with --shared: a fit of several clips in metres takes no priors (the "
                             "scene's are dropped too: many clips fix what one cannot); fit one file to use a "
                             "prior (image clips, --camera, take them)")
        if args.effects:
            raise UsageError("--effects with --shared: the effect sizes are those of one track; fit one file "
                             "to see them")
        if args.camera:
            return _cmd_fit_image_clips(args, scene, say)
        return _cmd_fit_clips(args, scene, say)
    for flag in ("devices", "distributed"):
        if getattr(args, flag):
            raise UsageError(f"--{flag} only applies with --shared (a fit of several clips)")
    if len(args.tracks) > 1:
        raise UsageError(f"{len(args.tracks)} files: fitting several clips together needs --shared "
                         "NAMES (the parameters they share, e.g. --shared e); fit them one at a "
                         "time otherwise")
    args.tracks = args.tracks[0]
    extra = {}
    if args.format != "csv":
        return _cmd_fit_export(args, scene, say)
    for flag in ("units", "origin", "y_up", "angle", "time_unit"):
        if getattr(args, flag) is not None:
            raise UsageError(f"--{flag.replace('_', '-')} only applies with --format tracker|kinovea")
    if args.camera:
        if args.pixels:
            raise UsageError("--pixels (a side view at one scale) and --camera (calibrated cameras) exclude each other")
        return _cmd_fit_image(args, scene, say)
    if args.pixels:
        result, data, scale, row = fit_pixels(
            args.tracks, scene, ball=args.ball, frame_interval=args.frame_interval,
            metres_per_pixel=args.metres_per_pixel, from_bounce=args.from_bounce, say=say,
            loss=args.loss, **_also(args, registry.side_view_free(scene)))
        extra = {"metres_per_pixel": scale, "surface_row_px": row,
                 "frame_interval_s": args.frame_interval}
    else:
        result, data = fit_csv(args.tracks, scene, say=say, loss=args.loss, **_also(args, scene))
    return _finish_fit(args, result, data, extra, say)
