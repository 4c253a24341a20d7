"""Which law a scene's contacts follow."""

from __future__ import annotations

from ...model._scene import Scene
from ._base import AbstractContactLaw
from ._factor import FactorLaw

# One instance: building an eqx.Module costs microseconds, and an eager simulate asks
# for the law at every call.
_FACTOR_LAW = FactorLaw()


def law_of(scene: Scene) -> AbstractContactLaw:
    """The contact law of ``scene``: ``scene.law``, or the seed's :class:`FactorLaw` where
    the scene names none (``Scene.law`` is ``None`` by default: the scene is defined before
    the laws, in ``estim.model``)."""
    law = scene.law
    if law is None:
        return _FACTOR_LAW
    if not isinstance(law, AbstractContactLaw):
        raise TypeError(f"Scene.law must be an estim contact law (AbstractContactLaw), got {type(law).__name__}")
    return law
