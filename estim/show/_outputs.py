"""A fit's files: fit.json and its plots (of one data set, or of several clips fitted together)."""

from __future__ import annotations

import os

import numpy as np

from .._json import dump
from ..fitting._fit import FitResult
from ..fitting._pooled import PooledResult
from ..tracks._image import ImageTracks
from ._forest import plot_forest
from ._image_plots import plot_image_fit, plot_path
from ._plots import plot_fit, plot_from_above, plot_loss_history, plot_residuals


def write_outputs(result: FitResult, data, out_dir, extra: dict | None = None) -> dict:
    """fit.json and the plots into ``out_dir``. For tracks in metres (``data``: ``ball ->
    (t, position)``): fit.png, residuals.png, loss.png, and above.png, the view from above,
    for tracks with y. For a fit in pixels (``data``: the :class:`ImageTracks`):
    pixels.png (what each camera saw, the fitted path over it), path.png (the path in 3-D)
    and loss.png."""
    os.makedirs(out_dir, exist_ok=True)
    payload = result.to_json()
    payload.update(extra or {})
    with open(os.path.join(out_dir, "fit.json"), "w") as f:
        dump(payload, f, indent=2)
    plot_loss_history(result, os.path.join(out_dir, "loss.png"))
    if isinstance(data, ImageTracks):
        plot_image_fit(data, result, os.path.join(out_dir, "pixels.png"))
        plot_path(data, result, os.path.join(out_dir, "path.png"))
        return payload
    plot_fit(data, result, os.path.join(out_dir, "fit.png"))
    plot_residuals(data, result, os.path.join(out_dir, "residuals.png"))
    if any(np.isfinite(np.asarray(data[b][1], dtype=np.float64)[:, 1]).any() for b in result.balls):
        plot_from_above(data, result, os.path.join(out_dir, "above.png"))
    return payload


def write_pooled_outputs(result: PooledResult, data: dict, out_dir, extra: dict | None = None) -> dict:
    """fit.json and the forest plot (forest.png) of a fit of several clips into
    ``out_dir``, and for clips in metres (``data``: ``label -> (t, position)``) their
    tracks with the joint fit (fit.png); for clips in pixels (``data``: ``file label ->
    ImageTracks``) each unit's pixels with its joint fit over them (``pixels-LABEL.png``,
    as a single fit's pixels.png; a ``/`` in the label as ``-``)."""
    os.makedirs(out_dir, exist_ok=True)
    payload = result.to_json()
    payload.update(extra or {})
    with open(os.path.join(out_dir, "fit.json"), "w") as f:
        dump(payload, f, indent=2)
    plot_forest(result, os.path.join(out_dir, "forest.png"))
    if not all(isinstance(d, ImageTracks) for d in data.values()):
        plot_fit(data, result.clips, os.path.join(out_dir, "fit.png"))
        return payload
    for unit in result.units:
        tracks = data[unit.label.rpartition("/")[0] if unit.label not in data else unit.label]
        plot_image_fit(tracks, FitResult({unit.ball: result.clips.balls[unit.label]}),
                       os.path.join(out_dir, f"pixels-{unit.label.replace('/', '-')}.png"))
    return payload
