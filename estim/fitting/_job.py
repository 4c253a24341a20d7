"""The fit jobs behind ``estim fit`` and ``estim demo``: read a file, fit it."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..model._scene import Scene, load_scene
from ..tracks._camera import read_camera
from ..tracks._csv import Tracks, TracksError, read_tracks_csv
from ..tracks._exports import read_kinovea, read_tracker
from ..tracks._image import read_image_tracks_csv
from ..tracks._pixels import estimate_pixel_scale, estimate_surface_row, read_pixel_track
from . import _registry as registry
from ._fit import LATE_START, fit
from ._hits import hits, longest_stretch
from ._image import fit_image
from ._initial import initial_guess, split_flights
from ._pooled import Clip, fit_clips, fit_image_clips


def fit_csv(tracks_path, scene: Scene | str, *, say=None, **options):
    """Fit a tracks CSV (``estim fit TRACKS``): returns (result, data) with data ``ball ->
    (t, position)``, what was fitted (:func:`fit_tracks`)."""
    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    result, data = fit_tracks(scene, read_tracks_csv(tracks_path, scene=scene), say=say, **options)
    result.source = os.fspath(tracks_path)
    return result, data


def fit_tracks(scene: Scene, tracks: Tracks, *, say=None, **options):
    """Fit tracks in metres as ``estim fit`` does: returns (result, data) with data ``ball
    -> (t, position)``, what was fitted. A track that something the scene does not have
    hits (a racket, a hand: ``estim.fitting._hits``) is fitted on its longest stretch
    between hits, released at that stretch's first sample (``t0``, unless ``fixed`` holds
    it), with a note that says where it was cut and how many samples were left out; a
    track on a video's clock is released at its first sample (:func:`_late_clock`).
    ``options`` are :func:`estim.fit`'s, which itself does neither."""
    data, notes = {}, {}
    fixed = {b: dict(v) for b, v in (options.pop("fixed", None) or {}).items()}
    for b in tracks.balls:
        t, pos = tracks.t[b], tracks.position[b]
        spec = scene.ball(b)
        found = hits(t, pos, scene, spec.radius, spec.position[1])
        if found:
            start, stop = longest_stretch(t.size, found)
            where = ", ".join(f"{jump:.1f} m/s at t = {tc:.3f} s" for _, tc, jump in found)
            notes[b] = (f"the velocity jumps far from every solid of the scene ({where}): something the scene "
                        f"does not have hit the ball (a racket, a hand); only t = {t[start]:.3f} to "
                        f"{t[stop - 1]:.3f} s is fitted, the longest stretch between hits "
                        f"({t.size - (stop - start)} of {t.size} samples left out)")
            if say:
                say(f"{b}: {notes[b]}")
            if start > 0:
                fixed.setdefault(b, {}).setdefault("t0", float(t[start]))
            t, pos = t[start:stop], pos[start:stop]
        late = _late_clock(b, t[np.isfinite(pos).any(axis=1)], fixed, say)
        if late:
            notes[b] = f"{notes[b]}; {late}" if b in notes else late
        data[b] = (t, pos)
    result = fit(scene, data, progress=say, fixed=fixed or None, **options)
    for b, note in notes.items():
        result.balls[b].notes.insert(0, note)
    return result, data


def fit_image_files(paths, camera_paths, scene: Scene | str, *, shared, say=None, **options):
    """Fit several image-track CSVs together, ``shared`` across the clips of each ball, every
    file seen by the cameras of ``camera_paths`` (:func:`estim.fitting._pooled.fit_image_clips`):
    ``estim fit A B ... --camera CAM --shared e``. Labels are the file names without
    extension (the full path where two files share a name). Returns the
    :class:`PooledResult` and the tracks read, ``label -> ImageTracks``."""
    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    cameras = _cameras(camera_paths)
    clips = {label: read_image_tracks_csv(path, cameras, balls=[b.name for b in scene.balls])
             for path, label in zip(paths, _labels(paths), strict=True)}
    return fit_image_clips(scene, clips, shared=shared, progress=say, **options), clips


def _labels(paths) -> list[str]:
    """Each file's label: its name without extension, or its path where two share a name."""
    paths = [os.fspath(p) for p in paths]
    if len(set(paths)) != len(paths):
        raise ValueError(f"a file is given twice: {sorted({p for p in paths if paths.count(p) > 1})}")
    stems = [os.path.splitext(os.path.basename(p))[0] for p in paths]
    return stems if len(set(stems)) == len(stems) else paths


def _cameras(camera_paths) -> list:
    """The cameras of ``camera_paths``, each named by its file's stem (unique)."""
    cameras = [read_camera(p) for p in camera_paths]
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ValueError(f"two camera files share the name {sorted({n for n in names if names.count(n) > 1})} "
                         "(a camera is named by its file's stem): rename one")
    return cameras


def fit_image_csv(tracks_path, camera_paths, scene: Scene | str, *, say=None, **options):
    """Fit an image-track CSV (``t,ball,u,v[,camera]``) seen by the cameras of
    ``camera_paths`` (camera files, in the order the ``camera`` column numbers them):
    ``estim fit TRACKS --camera CAM ...``. Returns ``(result, tracks)``: the
    :class:`FitResult` of :func:`estim.fitting._image.fit_image` and the
    :class:`~estim.tracks._image.ImageTracks` read."""
    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    tracks = read_image_tracks_csv(tracks_path, _cameras(camera_paths), balls=[b.name for b in scene.balls])
    return fit_image(scene, tracks, progress=say, **options), tracks


def _late_clock(ball: str, t, fixed: dict, say) -> str | None:
    """A track whose clock starts more than ``LATE_START`` after t = 0 (a video's): its
    release held at its first sample (in ``fixed``, unless that holds one already), and
    the note that says so; None otherwise. Released at t = 0, the model would fly unseen
    for seconds and its release state would be all but free."""
    first = float(np.min(t))
    if "t0" in fixed.get(ball, {}) or first <= LATE_START:
        return None
    fixed.setdefault(ball, {})["t0"] = first
    note = (f"the track's clock starts at t = {first:.3f} s, more than {LATE_START:g} s after t = 0: the release "
            "is taken at its first sample (to fit the release time instead: --also t0)")
    if say:
        say(f"{ball}: {note}")
    return note


EXPORTS = {"tracker": read_tracker, "kinovea": read_kinovea}


def fit_export(path, kind: str, scene: Scene | str, *, units: str, camera_path=None, say=None, reader=None,
               **options):
    """Fit a video tracker's export (``kind``: ``"tracker"`` or ``"kinovea"``;
    ``estim.tracks._exports``): in metres as a tracks file (:func:`fit_tracks`), in pixels
    (``units="px"``) through the camera of ``camera_path`` (:func:`estim.fitting._image.fit_image`). ``reader``
    holds the reader's keywords (``ball``, ``origin``, ``y_up``, ``angle_deg``,
    ``time_unit``). Returns ``(result, data)``: data ``ball -> (t, position)`` for metres,
    the :class:`~estim.tracks._image.ImageTracks` for pixels."""
    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    if kind not in EXPORTS:
        raise ValueError(f"unknown export {kind!r}; estim reads {sorted(EXPORTS)}")
    camera = None if camera_path is None else read_camera(camera_path)
    tracks = EXPORTS[kind](path, units=units, camera=camera, **(reader or {}))
    if isinstance(tracks, Tracks):
        result, data = fit_tracks(scene, tracks, say=say, **options)
    else:
        data = tracks
        result = fit_image(scene, tracks, progress=say, **options)
    result.source = os.fspath(path)
    return result, data


def fit_pixels(path, scene: Scene | str, *, ball: str, frame_interval: float,
               metres_per_pixel: float | None = None, from_bounce: int = 0,
               pad_to: int | None = None, say=None, **options):
    """Fit a pixel track from a video tracker (``a;b;`` lines): ``estim fit --pixels``.

    The pixel coordinates ``(a, b)`` of the ball centre (``a`` horizontal, ``b`` the image
    row, growing downward) become metres with a scale ``s`` (m/px) and the row
    ``b_s`` of the surface: ``x = s (a - a_0)``, ``z = s (b_s - b) + z_top``, at
    ``t = frame * frame_interval`` (s), ``z_top`` the top of the scene's highest box or
    upward plane. Without ``metres_per_pixel`` the scale comes from gravity: each flight is
    a parabola ``b(t) = b_0 + v t + (g / 2 s) t^2`` in the image, so its curvature ``c``
    (px/s^2) gives ``s = g / (2 c)`` (:func:`estimate_pixel_scale`; it scales with
    ``frame_interval**2``). In a scene with air the scale comes from the flights observed
    from bounce to bounce only, each fitted with a drag term (``drag=True,
    complete_only=True``): drag bends the fall from the hand most, and that flight alone
    read the real drops' scale 13% high. ``b_s`` lies one ball radius below the row where consecutive
    flight parabolas meet (the ball centre at contact; :func:`estimate_surface_row`).
    Frames before the release (the ball still in the hand) are skipped, the release time
    ``t0`` is held at the first fitted sample, and :func:`fit` estimates the scene's law's
    coefficients (``e`` and ``mu_t``, or under the friction law ``e`` and ``mu``), ``vx0``
    and the release state ``x0``, ``z0``, ``vz0`` (by default, ``registry.side_view_free``;
    ``free=`` changes them: a drop filmed from the side starts with an unknown vertical
    speed) in metres and seconds. Convert residuals back to pixels by dividing by the returned scale
    (``result.balls[ball].rms_m / s``).

    Args:
        path: the pixel track (one ``a;b;`` line per frame, no header, no time column).
        scene: a :class:`Scene`, or the path of an MJCF file.
        ball: the ball of the scene that the track follows (its radius places the surface).
        frame_interval: seconds per frame (e.g. 0.01 for 100 fps).
        metres_per_pixel: the scale (m/px) if known; ``None`` estimates it from gravity.
        from_bounce: ``k > 0`` fits only the data after the k-th bounce (from two frames after
            it; the state just after it is fitted), leaving out the fastest flights, where
            air drag matters most. Raises ``ValueError`` if fewer than k bounces are resolved.
        pad_to: pad the samples with masked rows to this many, so that tracks of different
            lengths share one compiled fit (``None``: no padding).
        say: called with progress messages (``None``: silent).
        **options: passed on to :func:`fit` (``free``, ``loss``, ``restarts``, ...).

    Returns:
        ``(result, data, metres_per_pixel, surface_row)``: the :class:`FitResult` (in metres
        and seconds, ``source`` the track's path), the fitted data ``{ball: (t, position)}``
        in metres (padding rows are NaN), the scale used (m/px) and the image row of the
        surface (px).

    Raises:
        ValueError: a track with no resolved flight or bounce to measure the scale or the
            surface from, fewer bounces than ``from_bounce``, or data that :func:`fit` rejects.

    Example:
        >>> res, data, s, row = estim.fit_pixels(  # doctest: +SKIP
        ...     "../shared/realdata/pingpong_drop_nicofighter45/table/tracked-9.txt",
        ...     "data/scenes/drop.xml", ball="pingpong", frame_interval=0.01, from_bounce=1)
        >>> res.balls["pingpong"].values["e"], res.balls["pingpong"].rms_m / s  # doctest: +SKIP
        (0.8247, 1.17)
    """
    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    clip = read_pixel_clip(path, scene, ball=ball, frame_interval=frame_interval,
                           metres_per_pixel=metres_per_pixel, from_bounce=from_bounce, say=say)
    t, pos = clip.t, clip.position
    if pad_to is not None and pad_to > len(t):
        extra = pad_to - len(t)
        t = np.concatenate([t, np.full(extra, t[-1])])
        pos = np.concatenate([pos, np.full((extra, 3), np.nan)])
    fixed = {ball: clip.fixed}
    free = options.pop("free", registry.side_view_free(scene))
    result = fit(scene, {ball: (t, pos)}, free=free, fixed=fixed, progress=say, anchors={ball: clip.anchor},
                 **options)
    result.source = os.fspath(path)
    return result, {ball: (t, pos)}, clip.metres_per_pixel, clip.surface_row


@dataclass(frozen=True)
class PixelClip:
    """A pixel track in metres, ready to fit: samples from the release (or after a bounce),
    the release values held fixed (``t0`` at the first sample, ``y0`` the ball's y in the
    scene), the scale (m/px) and the image row of the surface (px)."""

    t: np.ndarray
    position: np.ndarray
    fixed: dict
    metres_per_pixel: float
    surface_row: float
    anchor: tuple[float, float, float]  # the surface under the first sample: pixel_scale scales about it


def read_pixel_clip(path, scene: Scene, *, ball: str, frame_interval: float,
                    metres_per_pixel: float | None = None, from_bounce: int = 0,
                    say=None) -> PixelClip:
    """A pixel track in the scene's metres, as :func:`fit_pixels` fits it (its docstring
    gives the conversion); also one clip of a fit of several (``estim fit A B ... --pixels``)."""
    spec = scene.ball(ball)
    track = read_pixel_track(path, frame_interval=frame_interval, ball=ball)
    if metres_per_pixel is None:
        # In air the flights are not parabolas, and the fall from the hand (the fastest,
        # and where the real drops' tracks are least like the model) biases the scale most:
        # there it comes from bounce-to-bounce flights with a drag term
        # (docs/pages/fitting.md, "All drops together").
        air = scene.air is not None
        scale = estimate_pixel_scale(track, frame_interval, drag=air, complete_only=air)
        metres_per_pixel = scale.metres_per_pixel
        if say:
            say(f"scale from gravity: {metres_per_pixel * 1e3:.4f} +- {scale.stderr * 1e3:.4f} mm/px")
    rows = estimate_surface_row(track, metres_per_pixel=metres_per_pixel, radius=spec.radius)
    surface_row = rows.surface_row
    # The surface of the scene: the highest upward face under the ball.
    tracks = track.to_metres(metres_per_pixel, surface_row)
    t, pos = tracks.t[ball], tracks.position[ball].copy()
    pos[:, 2] += _surface_height(scene)
    pos[:, 1] = np.nan
    # Frames before the release (the ball still in the hand) are not part of the motion:
    # start at the first resolved flight.
    flights, _ = split_flights(t, np.nan_to_num(pos[:, 0]), pos[:, 2], float(scene.gravity))
    release = int(np.searchsorted(t, flights[0].start)) if flights else 0
    if say and release:
        say(f"release at frame {release}: the {release} frames before it are not fitted")
    t, pos = t[release:], pos[release:]
    if from_bounce:
        bounces = initial_guess(t, np.nan_to_num(pos[:, 0]), pos[:, 2], float(scene.gravity)).bounces
        if len(bounces) < from_bounce:
            raise ValueError(f"{path}: only {len(bounces)} bounces resolved, cannot start after bounce {from_bounce}")
        k = int(np.searchsorted(t, bounces[from_bounce - 1] + 2 * frame_interval))
        t, pos = t[k:], pos[k:]
        if say:
            say(f"fitting from t = {t[0]:.3f} s, after bounce {from_bounce}")
    pos[:, 0] -= pos[0, 0] if np.isfinite(pos[0, 0]) else 0.0
    fixed = {"t0": float(t[0]), "y0": spec.position[1]}
    return PixelClip(t, pos, fixed, float(metres_per_pixel), float(surface_row), (0.0, 0.0, _surface_height(scene)))


def _surface_height(scene: Scene) -> float:
    """Top of the highest box, or the highest upward plane (the drop scene's table)."""
    tops = list(np.asarray(scene.box_centre[:, 2] + scene.box_half[:, 2]))
    for n, s in zip(np.asarray(scene.plane_normal), np.asarray(scene.plane_offset), strict=True):
        if n[2] > 0.5:
            tops.append(float(s))
    return float(max(tops))


def clips_from_files(paths, scene: Scene, *, pixels: bool = False, ball: str | None = None,
                     frame_interval: float | None = None, metres_per_pixel: float | None = None,
                     from_bounce: int = 0, say=None) -> tuple[list[Clip], dict[str, str]]:
    """The clips of several files: with ``pixels`` each file is one clip of ``ball``
    (:func:`read_pixel_clip`, its own scale and surface row), else each ball of each tracks
    CSV is one clip. Labels are the file names without extension (and ``/ball`` where a
    file has several balls); the full path where two files share a name.

    Returns the clips and those left out, ``label -> why``: a pixel track whose motion
    cannot be placed in metres (no flight to read the scale from, no bounce between two
    fitted flights to read the surface row from, fewer bounces than ``from_bounce``) is left
    out, named (``say``) and reported, so that one such clip does not stop the fit of the
    others. A file that does not parse is an error, as for one file."""
    paths = [os.fspath(p) for p in paths]
    names = _labels(paths)
    clips, left_out = [], {}
    for path, name in zip(paths, names, strict=True):
        if pixels:
            try:
                pc = read_pixel_clip(path, scene, ball=ball, frame_interval=frame_interval,
                                     metres_per_pixel=metres_per_pixel, from_bounce=from_bounce, say=say)
            except TracksError:
                raise
            except ValueError as err:
                left_out[name] = str(err).removeprefix(f"{path}: ")
                if say:
                    say(f"left out {name}: {left_out[name]}")
                continue
            clips.append(Clip(label=name, ball=ball, t=pc.t, position=pc.position, fixed=pc.fixed, source=path,
                              anchor=pc.anchor,
                              extra={"metres_per_pixel": pc.metres_per_pixel, "surface_row_px": pc.surface_row,
                                     "frame_interval_s": frame_interval}))
        else:
            tracks = read_tracks_csv(path, scene=scene)
            for b in tracks.balls:
                label = name if len(tracks.balls) == 1 else f"{name}/{b}"
                clips.append(Clip(label=label, ball=b, t=tracks.t[b], position=tracks.position[b], source=path))
    return clips, left_out


def fit_files(paths, scene: Scene | str, *, shared, pixels: bool = False, ball: str | None = None,
              frame_interval: float | None = None, metres_per_pixel: float | None = None,
              from_bounce: int = 0, say=None, **options):
    """Fit several files together, ``shared`` across the clips of each ball
    (:func:`estim.fitting._pooled.fit_clips`): ``estim fit A B ... --shared e``. Returns the
    :class:`PooledResult` and the data ``label -> (t, position)``.

    Raises:
        ValueError: a ball seen in only one clip (nothing to share), or what the readers and
            :func:`fit_clips` refuse.
    """
    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    clips, left_out = clips_from_files(paths, scene, pixels=pixels, ball=ball, frame_interval=frame_interval,
                                       metres_per_pixel=metres_per_pixel, from_bounce=from_bounce, say=say)
    why = "".join(f"; left out: {k}: {v}" for k, v in left_out.items())
    if not clips:
        raise ValueError("no clip could be fitted" + why)
    seen = [c.ball for c in clips]
    alone = sorted({b for b in seen if seen.count(b) == 1})
    if alone:
        raise ValueError(f"ball(s) {alone} appear in only one clip: shared parameters need a ball "
                         "in at least two clips" + why)
    free = options.pop("free", registry.side_view_free(scene) if pixels else None)
    result = fit_clips(scene, clips, shared=shared, free=free, progress=say, **options)
    result.left_out = left_out
    return result, {c.label: (c.t, c.position) for c in clips}
