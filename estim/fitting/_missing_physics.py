"""Physics the scene lacks, coefficients a fit held: would they explain residuals that stay
above the noise floor?

A scene without ``<option density viscosity>`` is a vacuum: flights are parabolas and a
fit's residuals can reach the noise floor only if the real ball felt no air. For a light
ball they often cannot (a 2.7 g ping-pong ball falling 2 m is slowed by a third of g). When
a fit in such a scene stays above its noise floor, :func:`missing_physics` says, with
numbers, how far the effects the scene leaves out would move this ball over this track:

- ``air drag``: still air (quadratic drag, eq. (1) of ``estim.model._air``, with the ball's
  ``drag_coefficient``, plus Stokes drag, eq. (2)) against the vacuum;
- ``a spinning ball (Magnus, S rad/s backspin)``, only for a stated spin: the same still
  air with the ball spinning (eq. (3)) against still air without spin, so that the entry
  isolates what the spin adds.

The size of an effect is the largest distance between the two simulated trajectories over
``[0, t_span]`` (mm), and in noise levels that distance over the track's noise level. It
is the size of the effect, not what would remain after refitting: a drag-free fit absorbs
part of it into e and the release state (biasing them), so ``explains`` (at least
:data:`EXPLAINS` noise levels) says the effect is large enough to matter, not that it is
the only cause.

In a scene with air, the effects are there but their coefficients may not be the ball's: a
fit holds the drag coefficient and the lift factor at their values (the textbook ones by
default) unless asked to fit them, and real balls differ from the textbook: flight experiments
with table-tennis balls find both coefficients varying with the ball's speed and spin rate
("Lift crisis of a spinning table tennis ball", C_D and C_L measured over 3e4 < Re < 9e4).
When such a fit stays above its noise floor, :func:`held_coefficients` says how far each
coefficient the fit held would move the ball if it were :data:`SPREAD` larger (a probe of
plausible size, not a measured spread), and advises fitting it.

What a fit's model does contain, :func:`model_effects` sizes the same way, for every fit that
asks (``estim.fit(..., effects=True)``, ``estim fit --effects``): how far each effect in the
model moves the fitted ball over the whole track, the effect against the same ball without
it, in noise levels. An effect of many noise levels is one the track measures; one below a
noise level is one it cannot tell from its absence (its coefficient then rests on its
default or a prior). The effects, where the scene and the ball have them:

- ``quadratic drag``: the ball's drag coefficient against 0;
- ``linear drag``: the scene's viscosity against 0 (Stokes drag);
- ``Magnus``: the ball's lift factor against 0 (a spinning ball in air);
- ``wind``: the scene's wind against still air;
- ``spin at the bounce``: under a law that couples spin (the friction law), the ball's
  spin against none, both without Magnus, so that the entry isolates what the spin does
  to the bounces;
- ``friction at the bounce``: under such a law, its friction coefficient ``mu`` against 0
  (a frictionless bounce keeps the tangential velocity and the spin);
- ``compression at the bounce``: a ball with a compression (``estim.Params``, fitted on
  request) against the rigid ball, whose contacts are at its radius.

And one thing no simulation sizes: the contact laws hold one restitution for every
surface. A ball that bounces on a table and then on the floor keeps a different share of
its normal speed on each (MuJoCo's default floor contact keeps a small part where its
table contact keeps 0.83), and one e cannot follow both: the fit follows one surface's
bounces, sets the other's rows aside as outliers and reads an e between the two (a rally
shot run on to the floor, seen from the side: e 0.36 for 0.83, docs/pages/fitting.md).
Where a fit above its noise floor bounces on two surfaces the scene declares different
(``Scene.surfaces``), :func:`one_restitution` says so.

Cost: one closed-form vacuum run and one ODE run (still air; a second run of the same
compiled program for the spinning ball when a spin is given). The ODE program compiles
once per process (seconds) and then runs in milliseconds.

Closed form used by the tests: a ball dropped from rest under quadratic drag alone falls
as ``z(t) = z0 - ln(cosh(t sqrt(g k))) / k`` with ``k = rho C_D A / (2 m)``, A = pi r^2
(e.g. Taylor, *Classical Mechanics*, sec. 2.4), so that its lag behind the parabola is
``g t^2 / 2 - ln(cosh(t sqrt(g k))) / k ~ k g^2 t^4 / 12`` for ``t sqrt(g k) << 1``.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from .._config import same_programs
from ..forward._effect_report import AIR_DENSITY, AIR_VISCOSITY
from ..forward._simulate import simulate
from ..forward._trajectory import IMPACT
from ..forward.laws import law_of
from ..model._air import Air
from ..model._params import Params
from ..model._scene import Scene

__all__ = ["EXPLAINS", "HELD", "SAMPLES", "SPREAD", "format_effects", "format_note", "held_coefficients",
           "missing_physics", "model_effects", "one_restitution"]

# An effect that moves the ball by at least this many noise levels could explain residuals
# above the noise floor (the fit's floor allows 1.3 noise levels of rms).
EXPLAINS = 3.0
# Sample times over [0, t_span] for the largest deviation.
SAMPLES = 401
# The air coefficients a fit may hold fixed (Params fields, named as in the parameter
# registry), and how far from its held value each is probed (a quarter; module docstring).
HELD = ("drag_coefficient", "lift_factor")
SPREAD = 0.25


def _number(x: float) -> str:
    """A number as a scene file would write it: 3 significant digits, short exponent
    (1.204 -> "1.2", 1.81e-5 -> "1.81e-5")."""
    mantissa, _, exponent = format(float(x), ".3g").partition("e")
    return mantissa if not exponent else f"{mantissa}e{int(exponent)}"


def _short(x: float) -> str:
    """A size for a sentence: whole numbers from 10 up, 2 significant digits below."""
    return f"{x:.0f}" if abs(x) >= 10 else f"{x:.2g}"


def _backspin(rate: float, velocity: np.ndarray) -> np.ndarray:
    """Angular velocity of backspin ``rate`` (rad/s; topspin if negative) about the
    horizontal axis across the horizontal release direction u: omega = rate u x z, which
    lifts a ball moving along u (+x for a ball released without horizontal speed); the
    convention of ``estim effects --spin``."""
    u = np.array([velocity[0], velocity[1], 0.0])
    norm = np.linalg.norm(u)
    u = u / norm if norm > 0 else np.array([1.0, 0.0, 0.0])
    return rate * np.cross(u, np.array([0.0, 0.0, 1.0]))


def missing_physics(
    scene: Scene,
    params: Params,
    t_span: float,
    noise_m: float,
    ball_label: str,
    *,
    density: float = AIR_DENSITY,
    viscosity: float = AIR_VISCOSITY,
    spin: float | None = None,
    samples: int = SAMPLES,
) -> list[dict]:
    """How far the air a vacuum scene leaves out would move this ball over this track.

    Args:
        scene: the scene of the fit. A scene with air already has these effects: the
            answer is then ``[]``.
        params: one ball, unbatched (batch shape ``()``), as fitted; its mass is needed
            (taken from the scene's ball ``ball_label`` when ``params.mass`` is ``None``).
            Its drag coefficient (0.47 by default) sets the quadratic drag; its spin is
            ignored (spin has no effect without air; see ``spin``).
        t_span: the time the track covers after the release (s), > 0.
        noise_m: the track's noise level (m), > 0.
        ball_label: the ball's name, for the entries and the notes.
        density: air density rho (kg/m^3) of the still-air run and the advice; default
            dry air at 20 C (``AIR_DENSITY``).
        viscosity: dynamic viscosity eta (Pa s) of the Stokes drag; default
            ``AIR_VISCOSITY``; 0 leaves quadratic drag alone.
        spin: a backspin rate (rad/s; topspin if negative) for a Magnus entry, about the
            horizontal axis across the release direction; ``None`` (default): no Magnus
            entry and a single air run.
        samples: sample times over ``[0, t_span]`` for the largest deviation.

    Returns:
        One dict per effect, air drag first: ``effect`` (``"air drag"`` or
        ``"a spinning ball (Magnus, 50 rad/s backspin)"``), ``ball`` (``ball_label``),
        ``mass_kg``, ``t_span_s``, ``noise_mm``, ``max_deviation_mm`` (largest distance
        between the trajectories with and without the effect over the track's first
        flight: up to the first impact in the vacuum, or ``t_span``),
        ``noise_levels`` (that distance over ``noise_m``), ``explains``
        (``noise_levels >= EXPLAINS``), ``air`` (the density and viscosity of the run) and
        ``advice`` (what to add to the scene and which parameter to fit). ``[]`` for a
        scene with air.
    """
    if scene.air is not None:
        return []
    if not isinstance(params, Params):
        raise TypeError(f"params must be an estim.Params, got {type(params).__name__}")
    if params.batch_shape != ():
        raise ValueError(f"params must be one ball (batch shape ()), got batch shape {params.batch_shape}")
    for name, value, positive in (("t_span", t_span, True), ("noise_m", noise_m, True),
                                  ("density", density, False), ("viscosity", viscosity, False)):
        v = float(value)
        if not (math.isfinite(v) and (v > 0 if positive else v >= 0)):
            raise ValueError(f"{name} must be finite and {'> 0' if positive else '>= 0'}, got {value!r}")
    if density == 0 and viscosity == 0:
        raise ValueError("density and viscosity are both 0: that air exerts no force")
    if spin is not None and not math.isfinite(float(spin)):
        raise ValueError(f"spin must be a finite rate (rad/s) or None, got {spin!r}")
    mass = params.mass if params.mass is not None else scene.ball(ball_label).mass
    t_span, noise_m = float(t_span), float(noise_m)

    ball = dataclasses.replace(params, mass=jnp.asarray(mass, jnp.float64), spin=jnp.zeros(3))
    ts = jnp.linspace(0.0, t_span, int(samples))
    run = simulate(scene, ball, t_span, ts=ts)  # closed form
    vacuum = np.asarray(run.position)  # (times, 3)
    flight = _first_flight(run, ts, t_span)

    air_scene = scene.with_air(Air(density, viscosity))
    # The spinning ball is a second call of the same compiled program (one ball, the same
    # air; only the value of its spin differs): no second compilation.
    balls = [ball] if spin is None else [ball, dataclasses.replace(
        ball, spin=jnp.asarray(_backspin(float(spin), np.asarray(ball.velocity))))]
    in_air = [np.asarray(simulate(air_scene, b, t_span, ts=ts).position) for b in balls]

    settings = {"density": float(density), "viscosity": float(viscosity)}
    option = f'<option density="{_number(density)}" viscosity="{_number(viscosity)}"/>'

    def entry(effect: str, a: np.ndarray, b: np.ndarray, advice: str) -> dict:
        return _entry(effect, ball_label, mass, t_span, noise_m, settings, a, b, flight, advice)

    out = [entry("air drag", in_air[0], vacuum,
                 f"add {option} to the scene and fit drag_coefficient (--also drag_coefficient)")]
    if spin is not None:
        out.append(entry(f"a spinning ball (Magnus, {_short(float(spin))} rad/s backspin)", in_air[1], in_air[0],
                         f"add {option} to the scene and fit the spin (--also spin)"))
    return out


def one_restitution(scene: Scene, contacts, ball_label: str, e: float, outliers: int) -> list[dict]:
    """The entry of a fitted path that bounces on two or more surfaces the scene declares
    different (``Scene.surfaces``; module docstring), ``[]`` for a path on one.

    Args:
        scene: the scene of the fit.
        contacts: the fitted path's impacts within the data, ``(solid, face)`` in time order
            (``BallFit.contacts``).
        ball_label: the ball's name.
        e: the restitution the fit read.
        outliers: the rows the fit set aside.

    Returns:
        One dict with ``effect``, ``ball``, ``surfaces`` (the first solid met on each
        surface, in the order met), ``explains`` (True: one e for surfaces that differ
        leaves residuals above the noise) and ``advice``.
    """
    met: list[str] = []
    for solid, _ in contacts:
        if all(scene.surface(solid) != scene.surface(m) for m in met):
            met.append(solid)
    if len(met) < 2:
        return []
    names = " and then on ".join(repr(m) for m in met)
    aside = f"here {outliers} row(s) set aside as outliers, " if outliers else ""
    return [{"effect": f"one restitution for the surfaces {', '.join(met)}", "ball": ball_label, "surfaces": met,
             "explains": True,
             "advice": (f"the fitted path bounces on {names}, surfaces the scene declares different, with the one "
                        f"restitution every surface has in estim's laws (e = {e:.3g}): where the ball keeps less of "
                        f"its speed on one, the fit follows one surface's bounces and gives up the other's ({aside}"
                        f"e between the two); fit the rows before the ball reaches {met[1]!r}")}]


def _first_flight(run, ts, t_span: float) -> np.ndarray:
    """The sample times up to the first impact of ``run`` (one ball): after it two runs drift
    apart in phase (a bounce earlier or later), and their distance would measure that drift,
    not the force."""
    kind, count = np.asarray(run.events.kind), int(run.events.count)
    impacts = np.asarray(run.events.t)[:count][kind[:count] == IMPACT]
    return np.asarray(ts) <= (impacts[0] if impacts.size else t_span)


def _entry(effect: str, ball_label: str, mass: float, t_span: float, noise_m: float, settings: dict,
           a: np.ndarray, b: np.ndarray, flight: np.ndarray, advice: str) -> dict:
    deviation = float(np.max(np.linalg.norm(a - b, axis=-1)[flight]))
    levels = deviation / noise_m
    return {"effect": effect, "ball": ball_label, "mass_kg": float(mass), "t_span_s": t_span,
            "noise_mm": noise_m * 1e3, "max_deviation_mm": deviation * 1e3, "noise_levels": levels,
            "explains": bool(levels >= EXPLAINS), "air": settings, "advice": advice}


def held_coefficients(
    scene: Scene,
    params: Params,
    t_span: float,
    noise_m: float,
    ball_label: str,
    held: tuple[str, ...] = HELD,
    *,
    samples: int = SAMPLES,
) -> list[dict]:
    """How far each air coefficient a fit held fixed would move this ball over this track,
    were it :data:`SPREAD` larger than the value held.

    Args:
        scene: the scene of the fit; without air the coefficients do nothing and the answer
            is ``[]`` (see :func:`missing_physics`).
        params: one ball, unbatched, as fitted, with its mass.
        t_span, noise_m, ball_label, samples: as :func:`missing_physics`.
        held: the coefficients the fit held (a subset of :data:`HELD`); the lift factor is
            left out for a ball without spin, where it does nothing.

    Returns:
        One dict per coefficient, with the keys of :func:`missing_physics`'s entries;
        ``effect`` reads e.g. ``"a drag_coefficient 25% above the 0.4 held"`` and ``advice``
        ``"fit it (--also drag_coefficient)"``.
    """
    if scene.air is None:
        return []
    unknown = sorted(set(held) - set(HELD))
    if unknown:
        raise ValueError(f"held coefficients must be among {HELD}, got {unknown}")
    if params.batch_shape != () or params.mass is None:
        raise ValueError("params must be one ball (batch shape ()) with its mass")
    held = tuple(n for n in held if n != "lift_factor" or np.any(np.asarray(params.spin) != 0))
    if not held:
        return []
    t_span, noise_m = float(t_span), float(noise_m)
    ts = jnp.linspace(0.0, t_span, int(samples))
    # The probes are further calls of the fitted ball's compiled program (only values differ).
    run = simulate(scene, params, t_span, ts=ts)
    flight = _first_flight(run, ts, t_span)
    settings = {"density": float(scene.air.density), "viscosity": float(scene.air.viscosity)}
    out = []
    for name in held:
        value = float(getattr(params, name))
        probe = dataclasses.replace(params, **{name: jnp.asarray(value * (1.0 + SPREAD))})
        moved = np.asarray(simulate(scene, probe, t_span, ts=ts).position)
        out.append(_entry(f"a {name} {SPREAD:.0%} above the {_short(value)} held", ball_label, float(params.mass),
                          t_span, noise_m, settings, moved, np.asarray(run.position), flight,
                          f"fit it (--also {name})"))
    return out


def format_note(entry: dict, mass_kg: float) -> str:
    """The one-line note of an entry of :func:`missing_physics`, e.g. ``air drag would move
    this 2.7 g ball by 41 mm in its first flight, 41 noise levels: add <option density="1.2"
    viscosity="1.81e-5"/> to the scene and fit drag_coefficient (--also drag_coefficient)``.
    """
    return (f"{entry['effect']} would move this {_number(mass_kg * 1e3)} g ball by "
            f"{_short(entry['max_deviation_mm'])} mm in its first flight, "
            f"{_short(entry['noise_levels'])} noise levels: {entry['advice']}")


def _verdict(levels: float) -> str:
    """What a track can say of an effect of this many noise levels."""
    return "measured" if levels >= EXPLAINS else ("marginal" if levels >= 1.0 else "below the noise")


def model_effects(
    scene: Scene,
    params: Params,
    t_span: float,
    noise_m: float,
    *,
    samples: int = SAMPLES,
) -> list[dict]:
    """How far each effect that the model contains moves this ball over this track (module
    docstring): the fitted ball against the same ball without the effect.

    Args:
        scene: the scene of the fit.
        params: one ball, unbatched, as fitted, with its mass.
        t_span: the time the track covers after the release (s), > 0.
        noise_m: the track's noise level (m), > 0.
        samples: sample times over ``[0, t_span]`` for the largest deviation.

    Returns:
        One dict per effect the scene and the ball have (``[]`` in a vacuum under the seed's
        law, for a rigid ball): ``effect``, ``switched_off`` (what the run without it changes, e.g.
        ``"drag_coefficient = 0"``), ``max_deviation_mm`` (the largest distance between the
        two runs over the whole track, bounces included), ``noise_levels`` (that distance
        over ``noise_m``) and ``verdict``: ``"measured"`` (at least :data:`EXPLAINS` noise
        levels), ``"marginal"`` (1 to 3) or ``"below the noise"`` (the track cannot tell the
        effect from its absence).
    """
    if params.batch_shape != () or params.mass is None:
        raise ValueError("params must be one ball (batch shape ()) with its mass")
    t_span, noise_m = float(t_span), float(noise_m)
    if not (math.isfinite(t_span) and t_span > 0 and math.isfinite(noise_m) and noise_m > 0):
        raise ValueError(f"t_span and noise_m must be finite and > 0, got {t_span!r} and {noise_m!r}")
    air, law = scene.air, law_of(scene)
    spinning = bool(np.any(np.asarray(params.spin) != 0))
    zero = jnp.zeros(())
    # (effect, what is switched off, the run without it, the run it is compared with);
    # None: the fitted ball in its scene. Every run is one ball in a scene of the same
    # structure (only values differ): one compiled program.
    runs = []
    if air is not None:
        if float(air.density) > 0 and float(params.drag_coefficient) > 0:
            runs.append(("quadratic drag", "drag_coefficient = 0",
                         (scene, dataclasses.replace(params, drag_coefficient=zero)), None))
        if float(air.viscosity) > 0:
            runs.append(("linear drag", "viscosity = 0",
                         (dataclasses.replace(scene, air=Air(air.density, 0.0, air.wind)), params), None))
        if float(air.density) > 0 and spinning and float(params.lift_factor) > 0:
            runs.append(("Magnus", "lift_factor = 0", (scene, dataclasses.replace(params, lift_factor=zero)), None))
        if bool(np.any(np.asarray(air.wind) != 0)):
            runs.append(("wind", "wind = 0", (dataclasses.replace(scene, air=Air(air.density, air.viscosity)), params),
                         None))
    if law.couples_spin:
        if spinning:
            lifeless = dataclasses.replace(params, lift_factor=zero)
            runs.append(("spin at the bounce", "spin = 0 (and lift_factor = 0 in both runs)",
                         (scene, dataclasses.replace(lifeless, spin=jnp.zeros(3))), (scene, lifeless)))
        if float(params.mu) > 0:
            runs.append(("friction at the bounce", "mu = 0", (scene, dataclasses.replace(params, mu=zero)), None))
    if float(params.compression) != 0:
        runs.append(("compression at the bounce", "compression = 0",
                     (scene, dataclasses.replace(params, compression=zero)), None))
    if not runs:
        return []
    ts = jnp.linspace(0.0, t_span, int(samples))

    def position(run):
        return np.asarray(simulate(*run, t_span, ts=ts).position)

    out = []
    with same_programs():  # (runs compared on one program each: an effect that does nothing is 0)
        fitted = position((scene, params))
        for effect, off, without, reference in runs:
            deviation = float(np.max(np.linalg.norm(
                position(without) - (fitted if reference is None else position(reference)), axis=-1)))
            levels = deviation / noise_m
            out.append({"effect": effect, "switched_off": off, "max_deviation_mm": deviation * 1e3,
                        "noise_levels": levels, "verdict": _verdict(levels)})
    return out


def format_effects(effects: list[dict]) -> str:
    """The effects of :func:`model_effects` on one line, e.g. ``effects, in noise levels
    over the track: quadratic drag 41, Magnus 12, friction at the bounce 0.4 (below the
    noise: this track cannot tell it from its absence)``."""
    def one(m):
        tail = {"marginal": " (marginal)",
                "below the noise": " (below the noise: this track cannot tell it from its absence)"}.get(m["verdict"], "")
        return f"{m['effect']} {_short(m['noise_levels'])}{tail}"

    return "effects, in noise levels over the track: " + ", ".join(one(m) for m in effects)
