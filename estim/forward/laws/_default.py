"""Which law a scene's contacts follow."""

from __future__ import annotations

from ...model._scene import LAWS, Scene
from ._base import AbstractContactLaw
from ._factor import FactorLaw
from ._friction import FrictionLaw

# One instance per law, by the name a scene declares (``estim.model._scene.LAWS``): building
# an eqx.Module costs microseconds, and an eager simulate asks for the law at every call.
BY_NAME: dict[str, AbstractContactLaw] = {"factor": FactorLaw(), "friction": FrictionLaw()}
assert tuple(BY_NAME) == LAWS, "estim.model._scene.LAWS names the laws of BY_NAME"


def law_of(scene: Scene) -> AbstractContactLaw:
    """The contact law of ``scene``: ``scene.law``, the law of that name if it is a name
    (``estim.model._scene.LAWS``), or the seed's :class:`FactorLaw` where the scene names
    none (``Scene.law`` is ``None`` by default: the scene is defined before the laws, in
    ``estim.model``)."""
    law = scene.law
    if law is None:
        return BY_NAME["factor"]
    if isinstance(law, str):
        if law not in BY_NAME:
            raise ValueError(f"unknown contact law {law!r}; expected one of {LAWS}")
        return BY_NAME[law]
    if not isinstance(law, AbstractContactLaw):
        raise TypeError(f"Scene.law must be an estim contact law (AbstractContactLaw), got {type(law).__name__}")
    return law


def laws_reading(field: str) -> tuple[str, ...]:
    """The names of the laws (``estim.model._scene.LAWS``) that read the :class:`estim.Params`
    field ``field`` (``AbstractContactLaw.reads``), in the order of ``LAWS``."""
    return tuple(name for name, law in BY_NAME.items() if field in law.reads())
