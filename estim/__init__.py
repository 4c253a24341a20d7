"""estim: differentiable parameter estimation of hybrid (event-driven) dynamical systems.

Balls bounce in a scene read from MJCF; ``simulate`` solves their motion exactly, with
event-time sensitivities, in float64 (importing estim switches JAX's x64 mode on).
"""

import os as _os
import sys as _sys

# MuJoCo chooses its OpenGL backend once, when it is first imported (estim.model._scene imports
# it): without a display, offscreen rendering (estim.render_replay) needs EGL, so make it
# the default here, before any import of mujoco. An explicit MUJOCO_GL is left alone.
if _sys.platform.startswith("linux") and not (_os.environ.get("DISPLAY") or _os.environ.get("WAYLAND_DISPLAY")):
    _os.environ.setdefault("MUJOCO_GL", "egl")

from . import _config  # noqa: E402, F401  (switches on float64 first)
from ._config import enable_compilation_cache as enable_compilation_cache
from ._config import optimised_programs as optimised_programs
from .fitting._fit import BallFit as BallFit
from .fitting._fit import FitResult as FitResult
from .fitting._fit import fit as fit
from .fitting._image import fit_image as fit_image
from .fitting._job import fit_files as fit_files
from .fitting._job import fit_pixels as fit_pixels
from .fitting._job import read_pixel_clip as read_pixel_clip
from .fitting._pooled import Clip as Clip
from .fitting._pooled import PooledResult as PooledResult
from .fitting._pooled import SharedFit as SharedFit
from .fitting._pooled import fit_clips as fit_clips
from .fitting._pooled import fit_image_clips as fit_image_clips
from .forward._contact import contact_normals as contact_normals
from .forward._effect_report import EffectReport as EffectReport
from .forward._effect_report import effect_sizes as effect_sizes
from .forward._ode import OdeSolution as OdeSolution
from .forward._sensitivity import EventSensitivity as EventSensitivity
from .forward._sensitivity import event_sensitivities as event_sensitivities
from .forward._simulate import simulate as simulate
from .forward._trajectory import AbstractSolution as AbstractSolution
from .forward._trajectory import ClosedFormSolution as ClosedFormSolution
from .forward._trajectory import Events as Events
from .forward._trajectory import State as State
from .forward._trajectory import Trajectory as Trajectory
from .forward.laws import AbstractContactLaw as AbstractContactLaw
from .forward.laws import AbstractSeriesLaw as AbstractSeriesLaw
from .forward.laws import AbstractSummableLaw as AbstractSummableLaw
from .forward.laws import FactorLaw as FactorLaw
from .forward.laws import FrictionLaw as FrictionLaw
from .model._air import Air as Air
from .model._air import acceleration as acceleration
from .model._air import air_acceleration as air_acceleration
from .model._params import Params as Params
from .model._scene import Ball as Ball
from .model._scene import Scene as Scene
from .model._scene import load_scene as load_scene
from .tracks._camera import Camera as Camera
from .tracks._camera import CameraError as CameraError
from .tracks._camera import read_camera as read_camera
from .tracks._csv import Tracks as Tracks
from .tracks._csv import TracksError as TracksError
from .tracks._csv import read_tracks_csv as read_tracks_csv
from .tracks._csv import write_tracks_csv as write_tracks_csv
from .tracks._exports import read_kinovea as read_kinovea
from .tracks._exports import read_tracker as read_tracker
from .tracks._image import ImageTracks as ImageTracks
from .tracks._image import read_image_tracks_csv as read_image_tracks_csv
from .tracks._pixels import PixelTrack as PixelTrack
from .tracks._pixels import estimate_pixel_scale as estimate_pixel_scale
from .tracks._pixels import estimate_surface_row as estimate_surface_row
from .tracks._pixels import read_pixel_track as read_pixel_track
from .tracks._pixels import restitution_from_flight_times as restitution_from_flight_times
from .tracks._reconstruct import reconstruct as reconstruct
from .tracks._synthetic import synthesize_tracks as synthesize_tracks

__version__ = "0.1.0"

# Plotting and rendering load matplotlib, Pillow and an OpenGL context: imported on first
# use, so that `import estim` stays quick and never picks a matplotlib backend.
_LAZY = {
    "plot_fit": ".show._plots", "plot_from_above": ".show._plots", "plot_residuals": ".show._plots",
    "plot_loss_history": ".show._plots", "plot_heights": ".show._plots", "plot_energy": ".show._plots",
    "ReplayMotion": ".show._replay", "ReplayInfo": ".show._replay", "SideCamera": ".show._replay",
    "RenderError": ".show._replay", "EncoderNotFoundError": ".show._replay",
    "frame_times": ".show._replay", "replay_motion": ".show._replay", "side_camera": ".show._replay",
    "render_frames": ".show._replay", "render_replay": ".show._replay",
    "write_gif": ".show._replay", "write_mp4": ".show._replay", "write_video": ".show._replay",
    "SideView": ".show._sideview", "render_sideview": ".show._sideview",
    "write_outputs": ".show._outputs", "write_pooled_outputs": ".show._outputs",
    "plot_forest": ".show._forest", "plot_image_fit": ".show._image_plots", "plot_path": ".show._image_plots",
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
