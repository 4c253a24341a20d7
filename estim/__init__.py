"""estim: differentiable parameter estimation of hybrid (event-driven) dynamical systems.

Balls bounce in a scene read from MJCF; ``simulate`` solves their motion exactly, with
event-time sensitivities, in float64 (importing estim switches JAX's x64 mode on).
"""

from . import _config  # noqa: F401  (switches on float64 first)
from ._params import Params as Params
from ._scene import Ball as Ball
from ._scene import Scene as Scene
from ._scene import load_scene as load_scene
from ._sensitivity import EventSensitivity as EventSensitivity
from ._sensitivity import event_sensitivities as event_sensitivities
from ._simulate import simulate as simulate
from ._trajectory import Events as Events
from ._trajectory import State as State
from ._trajectory import Trajectory as Trajectory

__version__ = "0.1.0"
