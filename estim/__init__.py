"""estim: differentiable parameter estimation of hybrid (event-driven) dynamical systems.

Balls bounce in a scene read from MJCF; ``simulate`` solves their motion exactly, with
event-time sensitivities, in float64 (importing estim switches JAX's x64 mode on).
"""

from . import _config  # noqa: F401  (switches on float64 first)
from ._config import enable_compilation_cache as enable_compilation_cache
from ._fit import BallFit as BallFit
from ._fit import FitResult as FitResult
from ._fit import fit as fit
from ._params import Params as Params
from ._scene import Ball as Ball
from ._scene import Scene as Scene
from ._scene import load_scene as load_scene
from ._sensitivity import EventSensitivity as EventSensitivity
from ._sensitivity import event_sensitivities as event_sensitivities
from ._simulate import simulate as simulate
from ._synthetic import synthesize_tracks as synthesize_tracks
from ._tracks import PixelTrack as PixelTrack
from ._tracks import Tracks as Tracks
from ._tracks import TracksError as TracksError
from ._tracks import estimate_pixel_scale as estimate_pixel_scale
from ._tracks import estimate_surface_row as estimate_surface_row
from ._tracks import read_pixel_track as read_pixel_track
from ._tracks import read_tracks_csv as read_tracks_csv
from ._tracks import restitution_from_flight_times as restitution_from_flight_times
from ._tracks import write_tracks_csv as write_tracks_csv
from ._trajectory import Events as Events
from ._trajectory import State as State
from ._trajectory import Trajectory as Trajectory

__version__ = "0.1.0"
