"""Effect sizes: how much each force of the air would change a scene's trajectories.

For a scene and its balls, ``effect_sizes`` simulates the motion in a vacuum (the exact
closed form) and under each available effect of ``estim.model._air`` alone, and reports the
difference: final position, the first and second bounce times, the largest distance
between the two trajectories over ``[0, t_end]``, and the bounce counts. The effects:

- ``still air``: quadratic and linear drag together (air at rest), against the vacuum;
- ``quadratic drag``: eq. (1) of ``estim.model._air`` alone (density, ``Params.drag_coefficient``);
- ``linear drag``: eq. (2) alone (Stokes drag, viscosity);
- ``Magnus``: eq. (3) alone (drag switched off), for a stated spin;
- ``wind``: a stated wind, against still air (so this row isolates the wind);
- ``scene air``: the scene's own ``<option density viscosity wind>`` with the given
  parameters (their spin included), against the vacuum; only when the scene has air.

Every air run goes through one compiled ODE program: the scenes differ only in the values
of their ``Air`` (and the runs in drag coefficient and spin), never in structure.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ..model._air import Air
from ..model._params import Params
from ..model._scene import Scene
from ._balls import flat_params
from ._ode import ATOL, RTOL
from ._simulate import simulate
from ._trajectory import IMPACT

__all__ = ["AIR_DENSITY", "AIR_VISCOSITY", "EffectReport", "effect_sizes"]

# Dry air at 20 C and 1 atm.
AIR_DENSITY = 1.204  # kg/m^3
AIR_VISCOSITY = 1.81e-5  # Pa s
# Default spin (rad/s, backspin, about 8 revolutions per second) and wind (m/s along +x).
SPIN = 50.0
WIND = 3.0
SAMPLES = 1001

_COLUMNS = ("final_mm", "final_dx_mm", "bounce1_ms", "bounce2_ms", "max_deviation_mm")


@dataclasses.dataclass
class EffectReport:
    """What :func:`effect_sizes` returns.

    Attributes:
        names: the balls, in the order of the batch.
        t_end: the simulated time (s).
        settings: density, viscosity, spin and wind used, and each ball's radius, mass and
            drag coefficient.
        rows: one dict per effect and ball: ``effect``, ``ball``, ``baseline`` (what the
            effect is compared with: ``"vacuum"`` or ``"still air"``), ``air`` (the
            density, viscosity and wind of the run), and the changes caused by the effect:
            ``final_mm`` (distance between the final positions, mm), ``final_dx_mm``
            (change of the final x, mm), ``bounce1_ms`` and ``bounce2_ms`` (change of the
            first and second bounce times, ms; ``None`` where either run has no such
            bounce), ``max_deviation_mm`` (largest distance between the two trajectories
            at the sample times, mm), ``bounces_baseline`` and ``bounces`` (impacts in
            ``[0, t_end]``).
        ts: the sample times (s).
        positions: ``run -> (balls, times, 3)`` sampled centre positions (m) of every run
            (``"vacuum"`` and each effect), for plots.
    """

    names: list[str]
    t_end: float
    settings: dict
    rows: list[dict]
    ts: np.ndarray
    positions: dict[str, np.ndarray]

    def row(self, effect: str, ball: str) -> dict:
        """The row of ``effect`` for ``ball``."""
        for r in self.rows:
            if r["effect"] == effect and r["ball"] == ball:
                return r
        raise KeyError(f"no row for effect {effect!r} and ball {ball!r}")

    @property
    def effects(self) -> list[str]:
        return list(dict.fromkeys(r["effect"] for r in self.rows))

    def to_json(self) -> dict:
        """A JSON-ready dict: ``t_end``, ``settings``, ``balls`` and ``effects`` (one entry
        per effect with its ``baseline``, ``air`` and a dict of ball -> changes)."""
        effects = []
        for name in self.effects:
            rows = [r for r in self.rows if r["effect"] == name]
            effects.append({
                "effect": name,
                "baseline": rows[0]["baseline"],
                "air": rows[0]["air"],
                "balls": {r["ball"]: {k: r[k] for k in (*_COLUMNS, "bounces_baseline", "bounces")}
                          for r in rows},
            })
        return {"t_end": self.t_end, "settings": self.settings, "balls": list(self.names),
                "effects": effects}

    def format_table(self, markdown: bool = False) -> str:
        """The rows as a fixed-width text table, or a Markdown table."""
        header = ["effect", "ball", "final (mm)", "final dx (mm)", "bounce 1 (ms)",
                  "bounce 2 (ms)", "max dev. (mm)", "bounces"]

        def num(x, fmt):
            return "-" if x is None else format(x, fmt)

        body = []
        for r in self.rows:
            body.append([
                r["effect"], r["ball"], num(r["final_mm"], ".3g"), num(r["final_dx_mm"], "+.3g"),
                num(r["bounce1_ms"], "+.3g"), num(r["bounce2_ms"], "+.3g"),
                num(r["max_deviation_mm"], ".3g"), f"{r['bounces_baseline']} -> {r['bounces']}",
            ])
        if markdown:
            lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * 2 + ["---:"] * 5 + ["---"]) + "|"]
            lines += ["| " + " | ".join(row) + " |" for row in body]
            return "\n".join(lines)
        widths = [max(len(h), *(len(row[i]) for row in body)) for i, h in enumerate(header)]
        def line(cells):
            return "  ".join(c.ljust(w) if i < 2 else c.rjust(w)
                             for i, (c, w) in enumerate(zip(cells, widths, strict=True)))

        lines = [line(header)] + [line(row) for row in body]
        return "\n".join(lines)


def _vector(value, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape not in ((), (3,)) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be a finite number or 3-vector, got {value!r}")
    return v


def _spin_vectors(spin, velocity: np.ndarray) -> np.ndarray:
    """Per-ball angular velocity (n, 3): a 3-vector as given; a number s is backspin of
    rate s (topspin for s < 0) about the horizontal axis across each ball's horizontal
    release direction u (omega = s u x z, which lifts a ball moving along u), -y for a
    ball released without horizontal speed."""
    s = _vector(spin, "spin")
    if s.shape == (3,):
        return np.broadcast_to(s, velocity.shape).copy()
    horizontal = velocity.copy()
    horizontal[:, 2] = 0.0
    norm = np.linalg.norm(horizontal, axis=1, keepdims=True)
    u = np.where(norm > 0, horizontal / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0, 0.0]))
    return float(s) * np.cross(u, np.array([0.0, 0.0, 1.0]))


def _impacts(traj, k: int):
    """Impact times (list per ball) of the first k balls."""
    t = np.asarray(traj.events.t)
    kind = np.asarray(traj.events.kind)
    count = np.asarray(traj.events.count)
    return [t[i, : count[i]][kind[i, : count[i]] == IMPACT] for i in range(k)]


def _change(base, run, i: int, impacts_base, impacts_run) -> dict:
    p0, p1 = np.asarray(base.final.position[i]), np.asarray(run.final.position[i])
    dev = np.linalg.norm(np.asarray(run.position[i]) - np.asarray(base.position[i]), axis=-1)
    out = {
        "final_mm": float(np.linalg.norm(p1 - p0) * 1e3),
        "final_dx_mm": float((p1[0] - p0[0]) * 1e3),
    }
    tb, tr = impacts_base[i], impacts_run[i]
    for j, key in ((0, "bounce1_ms"), (1, "bounce2_ms")):
        out[key] = float((tr[j] - tb[j]) * 1e3) if len(tb) > j and len(tr) > j else None
    out["max_deviation_mm"] = float(np.max(dev) * 1e3)
    out["bounces_baseline"] = int(len(tb))
    out["bounces"] = int(len(tr))
    return out


def effect_sizes(
    scene: Scene,
    params: Params,
    t_end: float,
    *,
    names: Sequence[str] | None = None,
    density: float = AIR_DENSITY,
    viscosity: float = AIR_VISCOSITY,
    spin=SPIN,
    wind=WIND,
    samples: int = SAMPLES,
    rtol: float = RTOL,
    atol: float = ATOL,
) -> EffectReport:
    """How much each force of the air changes the motion of a scene's balls.

    Simulates the balls in a vacuum (closed form) and with each effect alone (the ODE
    path; see the module docstring of ``estim.forward._effect_report`` for the list), and reports
    the differences per effect and ball. One batched :func:`estim.simulate` call per
    effect; all air runs share one compiled program.

    Args:
        scene: the scene; its own air, if any, is reported as the effect ``scene air``
            and otherwise ignored (the other effects use ``density``, ``viscosity``).
        params: the balls, with a batch of one dimension and masses
            (``Params.for_ball``); their ``spin`` is used only for ``scene air``.
        t_end: simulated time (s), > 0.
        names: a name per ball (default ``ball 0``, ``ball 1``, ...).
        density: air density (kg/m^3) of the drag, Magnus and wind runs (default: dry
            air at 20 C); 0 switches those effects off (they are then reported as 0).
        viscosity: dynamic viscosity (Pa s) of the linear-drag and wind runs.
        spin: spin of the Magnus run: a rate (rad/s) of backspin (topspin if negative)
            about the horizontal axis across each ball's release direction, or an angular
            velocity 3-vector.
        wind: wind of the wind run: a speed (m/s) along +x, or a 3-vector.
        samples: sample times over ``[0, t_end]`` for the largest deviation.
        rtol: relative tolerance of the ODE path.
        atol: absolute tolerance of the ODE path (m, m/s).

    Returns:
        An :class:`EffectReport`.
    """

    if not isinstance(params, Params):
        raise TypeError(f"params must be an estim.Params, got {type(params).__name__}")
    if len(params.batch_shape) != 1:
        raise ValueError(f"params must have one batch dimension (one row per ball), got batch shape {params.batch_shape}")
    if params.mass is None:
        raise ValueError("the forces of the air need each ball's mass: build the parameters "
                         "with Params.for_ball(scene, ...) or pass Params(..., mass=...)")
    for name, value in (("density", density), ("viscosity", viscosity)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    if not (math.isfinite(float(t_end)) and float(t_end) > 0):
        raise ValueError(f"t_end must be a finite time > 0 (seconds), got {t_end!r}")
    if int(samples) < 2:
        raise ValueError(f"samples must be >= 2, got {samples!r}")
    params = flat_params(params)  # every field per ball: all runs share one compiled program
    (n,) = params.batch_shape
    names = [f"ball {i}" for i in range(n)] if names is None else [str(x) for x in names]
    if len(names) != n:
        raise ValueError(f"{len(names)} names for {n} balls")
    w = _vector(wind, "wind")
    wind_vec = np.array([float(w), 0.0, 0.0]) if w.shape == () else w
    omega = _spin_vectors(spin, np.asarray(params.velocity))

    t_end = float(t_end)
    ts = jnp.linspace(0.0, t_end, int(samples))
    no_spin = dataclasses.replace(params, spin=jnp.zeros((n, 3)))
    vacuum = simulate(scene.with_air(None), no_spin, t_end, ts=ts)

    def air_run(air: Air, prm: Params):
        # Built without Scene.with_air's check, which refuses an air that exerts no force:
        # here that is a legitimate run (density 0 asked for), the vacuum on the ODE path.
        return simulate(dataclasses.replace(scene, air=air), prm, t_end, ts=ts, rtol=rtol, atol=atol)

    runs = [
        ("still air", Air(density, viscosity), no_spin, "vacuum"),
        ("quadratic drag", Air(density, 0.0), no_spin, "vacuum"),
        ("linear drag", Air(0.0, viscosity), no_spin, "vacuum"),
        ("Magnus", Air(density, 0.0),
         dataclasses.replace(no_spin, drag_coefficient=jnp.zeros(n), spin=jnp.asarray(omega)), "vacuum"),
        ("wind", Air(density, viscosity, wind_vec), no_spin, "still air"),
    ]
    if scene.air is not None:
        runs.append(("scene air", scene.air, params, "vacuum"))

    trajs = {"vacuum": vacuum}
    for effect, air, prm, _ in runs:
        trajs[effect] = air_run(air, prm)
    impacts = {key: _impacts(traj, n) for key, traj in trajs.items()}

    rows = []
    for effect, air, _, baseline in runs:
        air_json = {"density": float(air.density), "viscosity": float(air.viscosity),
                    "wind": np.asarray(air.wind).tolist()}
        for i, ball in enumerate(names):
            row = {"effect": effect, "ball": ball, "baseline": baseline, "air": air_json}
            row.update(_change(trajs[baseline], trajs[effect], i, impacts[baseline], impacts[effect]))
            rows.append(row)

    settings = {
        "density": float(density), "viscosity": float(viscosity),
        "spin": omega.tolist(), "wind": wind_vec.tolist(), "rtol": rtol, "atol": atol,
        "samples": int(samples),
        "balls": {ball: {"radius": float(params.radius[i]), "mass": float(params.mass[i]),
                         "drag_coefficient": float(params.drag_coefficient[i])}
                  for i, ball in enumerate(names)},
    }
    positions = {key: np.asarray(traj.position) for key, traj in trajs.items()}
    return EffectReport(names=names, t_end=t_end, settings=settings, rows=rows,
                        ts=np.asarray(ts), positions=positions)
