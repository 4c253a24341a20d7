"""estim: differentiable parameter estimation of hybrid (event-driven) dynamical systems.

Balls bounce in a scene read from MJCF; ``simulate`` solves their motion exactly, with
event-time sensitivities, in float64 (importing estim switches JAX's x64 mode on).
"""

import os as _os
import sys as _sys

# MuJoCo chooses its OpenGL backend once, when it is first imported (estim._scene imports
# it): without a display, offscreen rendering (estim.render_replay) needs EGL, so make it
# the default here, before any import of mujoco. An explicit MUJOCO_GL is left alone.
if _sys.platform.startswith("linux") and not (_os.environ.get("DISPLAY") or _os.environ.get("WAYLAND_DISPLAY")):
    _os.environ.setdefault("MUJOCO_GL", "egl")

from . import _config  # noqa: E402, F401  (switches on float64 first)
from ._config import enable_compilation_cache as enable_compilation_cache
from ._effect_report import EffectReport as EffectReport
from ._effect_report import effect_sizes as effect_sizes
from ._effects import Air as Air
from ._effects import acceleration as acceleration
from ._effects import air_acceleration as air_acceleration
from ._fit import BallFit as BallFit
from ._fit import FitResult as FitResult
from ._fit import fit as fit
from ._job import fit_pixels as fit_pixels
from ._ode import OdeSolution as OdeSolution
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
from ._trajectory import AbstractSolution as AbstractSolution
from ._trajectory import ClosedFormSolution as ClosedFormSolution
from ._trajectory import Events as Events
from ._trajectory import State as State
from ._trajectory import Trajectory as Trajectory

__version__ = "0.1.0"

# Plotting and rendering load matplotlib, Pillow and an OpenGL context: imported on first
# use, so that `import estim` stays quick and never picks a matplotlib backend.
_LAZY = {
    "plot_fit": "._plots", "plot_residuals": "._plots", "plot_loss_history": "._plots",
    "plot_heights": "._plots", "plot_energy": "._plots",
    "ReplayMotion": "._replay", "ReplayInfo": "._replay", "SideCamera": "._replay",
    "RenderError": "._replay", "EncoderNotFoundError": "._replay",
    "frame_times": "._replay", "replay_motion": "._replay", "side_camera": "._replay",
    "render_frames": "._replay", "render_replay": "._replay",
    "write_gif": "._replay", "write_mp4": "._replay", "write_video": "._replay",
    "SideView": "._sideview", "render_sideview": "._sideview",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'estim' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
