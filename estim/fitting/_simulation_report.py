"""What ``estim simulate`` reports: one ball's events, final state and parameters as plain
numbers, and the derivatives of its final position and event times with respect to named
parameters of the registry (``estim.fitting._registry``), by one ``jax.jacfwd``."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..forward._contact import contact_normals
from ..forward._simulate import simulate
from ..forward._trajectory import IMPACT, Trajectory
from ..model._params import Params
from ..model._scene import Scene
from . import _registry as registry

__all__ = ["simulation_report", "sensitivities", "SENSITIVITY_NAMES"]

# The parameters `estim simulate --sensitivities` differentiates by default.
SENSITIVITY_NAMES = ("e", "mu_t", "vx0")


def simulation_report(scene: Scene, traj: Trajectory, values: Mapping[str, float], t_end: float) -> dict:
    """One ball's trajectory as JSON-ready numbers: every event (time, position, pre-impact
    velocity, the surface and face it touched, the contact ``normal`` from the solid
    towards the ball's centre, the velocity ``after`` it, ``impact`` or ``settle``; where the
    simulation carries spin, the spin before, ``wx wy wz`` in rad/s, and after), the final
    state, and the registry ``values`` it was simulated with (``params``; in a scene without
    air the air's parameters are left out)."""
    ev = traj.events
    count = int(ev.count)
    t, pos = np.asarray(ev.t)[:count], np.asarray(ev.position)[:count]
    vpre, face, kind = np.asarray(ev.velocity_pre)[:count], np.asarray(ev.face)[:count], np.asarray(ev.kind)[:count]
    vpost = np.asarray(ev.velocity_post)[:count]
    normal = np.asarray(contact_normals(scene, face, pos))
    spins = ev.spin_pre is not None
    if spins:
        wpre, wpost = np.asarray(ev.spin_pre)[:count], np.asarray(ev.spin_post)[:count]
    events = []
    for i in range(count):
        surface, label = scene.face_label(int(face[i]))
        after = {"vx": float(vpost[i, 0]), "vy": float(vpost[i, 1]), "vz": float(vpost[i, 2])}
        spin = {}
        if spins:
            spin = {"wx": float(wpre[i, 0]), "wy": float(wpre[i, 1]), "wz": float(wpre[i, 2])}
            after |= {"wx": float(wpost[i, 0]), "wy": float(wpost[i, 1]), "wz": float(wpost[i, 2])}
        events.append({
            "t": float(t[i]),
            "x": float(pos[i, 0]), "y": float(pos[i, 1]), "z": float(pos[i, 2]),
            "vx": float(vpre[i, 0]), "vy": float(vpre[i, 1]), "vz": float(vpre[i, 2]),
            **spin,
            "surface": surface, "face": label,
            "normal": [float(x) for x in normal[i]],
            "after": after,
            "kind": "impact" if int(kind[i]) == IMPACT else "settle",
        })
    fp, fv = np.asarray(traj.final.position), np.asarray(traj.final.velocity)
    return {
        "params": {
            **{n: values[n] for p in registry.REGISTRY if p.field is not None and p.acts(scene)
               for n in p.components},
            "t_end": float(t_end),
        },
        "n_impacts": sum(1 for x in events if x["kind"] == "impact"),
        "n_events": count,
        "truncated": bool(ev.truncated),
        "events": events,
        "final": {
            "t": float(traj.final.t),
            "x": float(fp[0]), "y": float(fp[1]), "z": float(fp[2]),
            "vx": float(fv[0]), "vy": float(fv[1]), "vz": float(fv[2]),
        },
    }


@eqx.filter_jit
def _jacobians(scene, params, names, theta, t_end):
    def f(theta):
        traj = simulate(scene, registry.with_values(params, dict(zip(names, theta, strict=True))), t_end)
        ev = traj.events
        valid = jnp.arange(ev.t.shape[-1]) < ev.count
        times = jnp.where(valid, ev.t, 0.0)  # padding (inf) masked out
        return (traj.final.position[0], traj.final.position[2], times), ev.count

    return jax.jacfwd(f, has_aux=True)(theta)


def sensitivities(scene: Scene, params: Params, values: Mapping[str, float], t_end: float,
                  names: Sequence[str] = SENSITIVITY_NAMES) -> dict:
    """Derivatives of one ball's final x and z and of each of its event times with respect
    to the registry components ``names``, at ``values`` (name -> value; exact: forward-mode
    autodiff through the event times, as ``estim.event_sensitivities`` checks). Returns
    ``{"wrt": names, "final": {"x": {...}, "z": {...}}, "events": [{"t": {...}}, ...]}``,
    each ``{...}`` a map name -> derivative. Jitted: repeated calls with the same shapes
    compile once."""
    names = tuple(names)
    theta = jnp.array([values[n] for n in names], dtype=jnp.float64)
    (dx, dz, dt), count = _jacobians(scene, params, names, theta, float(t_end))
    dx, dz, dt, count = np.asarray(dx), np.asarray(dz), np.asarray(dt), int(count)

    def named(row):
        return {k: float(v) for k, v in zip(names, row, strict=True)}

    return {"wrt": list(names), "final": {"x": named(dx), "z": named(dz)},
            "events": [{"t": named(dt[i])} for i in range(count)]}
