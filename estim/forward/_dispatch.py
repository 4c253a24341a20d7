"""Which path solves a scene: one decision for ``simulate``, ``fit``, the sensitivities and
the benchmarks.

- ``ODE``: a scene with air (or an explicit ``solver=``) has no closed form; diffrax
  integrates its flights (``estim.forward._ode``). A contact law that couples spin
  (``estim.forward.laws.FrictionLaw``) takes it too: the ODE path carries the spin from
  contact to contact, the closed-form planner does not.
- ``NATIVE``: the closed form on the native CPU kernels, where they support the scene's
  contact law (``estim.forward._native.supports``) and are built, current, switched on
  and on a CPU backend (``estim.forward._native.active``).
- ``JAX``: the closed form on the JAX planner (``estim.forward._solver``), with the same
  results: everywhere else.
"""

from __future__ import annotations

import contextlib

from ..model._scene import Scene
from . import _native, _solver
from ._solver import Plan
from .laws import law_of

__all__ = ["NATIVE", "JAX", "ODE", "path", "closed_form_plan", "jax_planner"]

NATIVE, JAX, ODE = "native", "jax", "ode"


def path(scene: Scene, solver=None) -> str:
    """The path that solves ``scene``: ``ODE``, ``NATIVE`` or ``JAX`` (module docstring).
    ``solver``: a diffrax solver the caller asked for (forces the ODE path)."""
    if scene.air is not None or solver is not None or law_of(scene).couples_spin:
        return ODE
    return NATIVE if _native.runs(scene) else JAX


def closed_form_plan(scene: Scene, params, t_end, max_segments: int) -> Plan:
    """The closed-form plan of one ball (or, on the kernels, a batch) by the planner that
    :func:`path` chooses: the discrete structure and its segments, as values."""
    if path(scene) == NATIVE:
        return _native.plan(scene, params, t_end, max_segments)
    return _solver.plan(scene, params, t_end, max_segments)


@contextlib.contextmanager
def jax_planner():
    """Within the block, the closed form runs on the JAX planner, not the kernels (programs
    traced before keep the path they were traced with)."""
    was = _native.ENABLED
    _native.ENABLED = False
    try:
        yield
    finally:
        _native.ENABLED = was
