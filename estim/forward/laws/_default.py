"""Which law a scene's contacts follow."""

from __future__ import annotations

from ...model._scene import Scene
from ._base import AbstractContactLaw
from ._factor import FactorLaw


def law_of(scene: Scene) -> AbstractContactLaw:
    """The contact law of ``scene``: ``scene.law``, or the seed's :class:`FactorLaw` where
    the scene names none (``Scene.law`` is ``None`` by default: the scene is defined before
    the laws, in ``estim.model``)."""
    law = scene.law
    if law is None:
        return FactorLaw()
    if not isinstance(law, AbstractContactLaw):
        raise TypeError(f"Scene.law must be an estim contact law (AbstractContactLaw), got {type(law).__name__}")
    return law
