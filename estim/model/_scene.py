"""Scenes: static contact geometry, gravity and ball specifications read from MJCF.

A scene is what the balls bounce on. estim reads it from the MuJoCo model that also renders
it, so the picture and the physics share one file:

- every ``box`` geom becomes a solid axis-aligned box (rotations by multiples of 90 degrees
  are accepted, any other rotation is an error naming the geom),
- every ``plane`` geom becomes a solid half-space behind an axis-aligned plane,
- every ``sphere`` geom on a body with a free joint becomes a ball (radius, mass, and its
  body position as the default release point),
- ``<option gravity>`` sets gravity, which must point along -z,
- ``<option density viscosity wind>`` asks for air: quadratic drag and the Magnus force
  (density), viscous drag (viscosity), moving air (wind). Force laws in ``estim.model._air``.
  A scene without them has gravity only and is solved in closed form.

Geoms that MuJoCo itself never collides (``contype="0" conaffinity="0"``) are decoration and
are skipped, as in MuJoCo. Any other geom (meshes, capsules, static spheres, ...) is an error
naming the geom: estim never silently ignores geometry a ball could hit.

Contact geometry
----------------
A ball of radius r touches a box when its centre reaches the box grown by r,

    P = { q : || max(|q - c| - h, 0) ||_2 <= r }                            (1)

(c the centre, h the half sizes, the max taken per axis): the set of centres at distance
at most r from the box, its Minkowski sum with the ball. Its boundary is made of 26 pieces,
one per direction m in {-1, 0, 1}^3 \\ {0} (primary faces first):

- the 6 *faces* (one nonzero m_i): the box's faces moved out by r, the plane
  ``m . (q - c) = h_i + r`` over the face's rectangle. On the top face this is the seed's
  rule: the centre is over the tread and z - r reaches its top;
- the 12 *edges* (two nonzero m_i): the quarter cylinder of radius r around the box edge
  ``{q : m_i (q_i - c_i) = h_i where m_i != 0}``, along the edge's length;
- the 8 *corners* (three nonzero m_i): the eighth of the sphere of radius r around the
  vertex ``c + m h``.

On piece m the outward normal is the unit vector from the nearest box point to the centre,
``(m_i (q_i - c_i) - h_i) m_i`` over the nonzero axes, normalised: exactly what MuJoCo's
sphere-box distance (``mj_geomDistance``) returns. Each piece is where it is: the points of
P's boundary with ``m_i (q_i - c_i) >= h_i`` on the nonzero axes and ``|q_i - c_i| <= h_i``
on the others (its Voronoi region). Contact times on the curved pieces are roots of
quartics (``estim.forward._contact``).

A scene can declare instead the *seed's geometry* (``geometry="seed"``): a box is its six
faces only, with no edges or corners, as in the seed notebook (a tread is its top, under
the ball's centre). A ball there passes through a box's edges and corners (the seed's golf
ball passes 4.3 mm into the corner of tread 2 at t = 1.014 s); the seed scene
``data/scenes/stairs.xml`` declares it so that the seed's numbers hold. In MJCF::

    <custom><text name="estim:geometry" data="seed"/></custom>

(``data="exact"``, the default, is the sphere-box geometry above).

A scene declares its *contact law* the same way (``estim.forward.laws``; ``Scene.law``)::

    <custom><text name="estim:law" data="friction"/></custom>

``"factor"`` (the seed's law: restitution e, tangential factor mu_t) is the law of a scene
that declares none; ``"friction"`` is Coulomb friction at the contact point, with spin
(restitution e, friction coefficient mu; ``estim.forward.laws.FrictionLaw``).

A scene may declare what is known of a fit's parameters before any data: a Gaussian
*prior* per parameter (its registry name, ``estim.fitting._registry``), its mean and
standard deviation. The table-tennis scene declares the restitution and friction of a
table-tennis ball on a table, from the literature::

    <custom><numeric name="estim:prior:e" data="0.9 0.05"/></custom>

A fit takes the scene's priors unless told otherwise (``estim.fit(..., prior=...)``,
``estim fit --prior``); a scene that declares none adds nothing to any fit.

A scene may say which of its solids are of different *surfaces* (a table and the floor
under it: a ball keeps less of its speed on one than on the other), as groups of geom
names separated by ``;``, each group one surface; the solids it does not name are one
surface together::

    <custom><text name="estim:surfaces" data="table; floor; net"/></custom>

estim's contact laws hold one restitution for every surface; a fit whose path bounces on
two surfaces of a scene that declares them says so (``estim.fitting._missing_physics``).
A scene that declares none is one surface.

A piece that lies inside a plane's half-space for every radius (the bottom of a tread
standing on the ground, and its bottom edges and corners) can never be reached and is
dropped when the scene is built; this is exact, not an approximation.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._air import Air

__all__ = ["Ball", "Scene", "load_scene", "GEOMETRIES"]

# Contact geometries a scene may declare (module docstring); the first is the default.
GEOMETRIES = ("exact", "seed")
# The MJCF <custom><text> name under which a scene declares its geometry.
GEOMETRY_TEXT = "estim:geometry"
# Contact laws a scene may declare by name (``estim.forward.laws.law_of`` maps each to its
# class), and the <custom><text> name under which it does.
LAWS = ("factor", "friction")
LAW_TEXT = "estim:law"
# The MJCF <custom><numeric> name prefix under which a scene declares a fit parameter's prior.
PRIOR_NUMERIC = "estim:prior:"
# The MJCF <custom><text> name under which a scene declares its surfaces (module docstring).
SURFACES_TEXT = "estim:surfaces"
# How far a solid set aside (``Scene.set_aside``) is moved (m): out of reach of any ball a
# simulation can follow (a second's flight covers tens of metres; a fall from rest reaches
# 1e6 m after 450 s), and still small enough for float64 to keep a path's millimetres.
OUT_OF_REACH = 1.0e6


class Ball(NamedTuple):
    """A ball as the scene describes it: name, radius (m), mass (kg), release point (m), and
    moment of inertia as the ratio ``I / (m r^2)`` (MuJoCo's inertia of the ball's body: 2/5
    for a solid sphere, 2/3 for ``shellinertia="true"``)."""

    name: str
    radius: float
    mass: float
    position: tuple[float, float, float]
    inertia: float = 0.4


# The 26 piece directions of a grown box (module docstring), faces first: the order breaks
# ties between pieces that a ball reaches at the same instant (a ball landing exactly on a
# tread edge lands on the tread, whose normal is the edge's there).
_DIRECTIONS = np.array(
    sorted(
        (m for m in itertools.product((-1, 0, 1), repeat=3) if any(m)),
        key=lambda m: (sum(map(abs, m)), m),
    ),
    dtype=np.float64,
)


class Scene(eqx.Module):
    """Contact geometry and gravity, plus the balls the scene defines.

    Array fields are pytree leaves, so derivatives with respect to the geometry (box
    centres and half sizes, plane offsets) flow through :func:`estim.simulate`. The face
    table (which direction of which solid) is static.

    Attributes:
        box_centre: ``(n_boxes, 3)`` box centres (m).
        box_half: ``(n_boxes, 3)`` box half sizes (m).
        plane_normal: ``(n_planes, 3)`` unit outward normals (axis-aligned).
        plane_offset: ``(n_planes,)`` the solid is ``normal . x <= offset``.
        gravity: magnitude g (m/s^2) of gravity, which points along -z.
        names: one name per solid, boxes first, then planes.
        face_solid: static index of the solid each contact face belongs to.
        face_direction: static ``(n_faces, 3)`` direction m of each face (for a plane: its
            normal).
        balls: the balls the scene defines.
        air: the air the balls fly through (:class:`estim.Air`), or ``None`` for a vacuum:
            then only gravity acts and :func:`estim.simulate` is exact, in closed form.
        geometry: static: ``"exact"`` (a box is a box: faces, edges and corners) or
            ``"seed"`` (a box is its six faces; module docstring).
        law: static: the contact law of every contact: an
            ``estim.forward.laws.AbstractContactLaw``, a name of :data:`LAWS` (as the
            MJCF file declares it: the laws are defined after the scene, in
            ``estim.forward``), or ``None`` for the seed's factor law
            (``estim.forward.laws.FactorLaw``: e and mu_t).
        priors: static: what is known of the fit's parameters before any data, as the MJCF
            file declares it: ``(name, mean, standard deviation)`` per parameter (module
            docstring; ``estim.fitting._registry.prior_arrays`` reads them).
        surfaces: static: the groups of solids the MJCF file declares surfaces of their
            own, by name (module docstring); the solids no group names are one surface.
    """

    box_centre: Float[Array, "boxes 3"]
    box_half: Float[Array, "boxes 3"]
    plane_normal: Float[Array, "planes 3"]
    plane_offset: Float[Array, " planes"]
    gravity: Float[Array, ""]
    names: tuple[str, ...] = eqx.field(static=True)
    face_solid: tuple[int, ...] = eqx.field(static=True)
    face_direction: tuple[tuple[float, float, float], ...] = eqx.field(static=True)
    balls: tuple[Ball, ...] = eqx.field(static=True, default=())
    air: Air | None = None
    law: object = eqx.field(static=True, default=None)
    geometry: str = eqx.field(static=True, default="exact")
    priors: tuple[tuple[str, float, float], ...] = eqx.field(static=True, default=())
    surfaces: tuple[tuple[str, ...], ...] = eqx.field(static=True, default=())

    @property
    def n_boxes(self) -> int:
        return self.box_centre.shape[0]

    @property
    def n_faces(self) -> int:
        return len(self.face_solid)

    def ball(self, name: str) -> Ball:
        """The ball called ``name``; a ``KeyError`` lists the balls the scene has."""
        for b in self.balls:
            if b.name == name:
                return b
        raise KeyError(
            f"unknown ball {name!r}: this scene has {[b.name for b in self.balls]}"
        )

    def with_air(self, air: Air | None) -> Scene:
        """The same scene with another air (``None``: a vacuum, gravity only)."""
        return dataclasses.replace(self, air=_checked_air(air))

    def with_law(self, law) -> Scene:
        """The same scene with another contact law (``None``: the seed's factor law)."""
        return dataclasses.replace(self, law=law)

    def with_priors(self, priors) -> Scene:
        """The same scene with other priors: ``(name, mean, standard deviation)`` each."""
        return dataclasses.replace(self, priors=tuple((str(n), float(m), float(s)) for n, m, s in priors))

    def with_surfaces(self, groups) -> Scene:
        """The same scene with other surfaces: groups of solid names, each group one surface
        (the solids no group names are one surface together). A ``ValueError`` names a solid
        the scene lacks or one named twice."""
        groups = tuple(tuple(str(n) for n in g) for g in groups)
        named = [n for g in groups for n in g]
        unknown = sorted(set(named) - set(self.names))
        if unknown:
            raise ValueError(f"surfaces: unknown solid(s) {unknown}: this scene has {list(self.names)}")
        twice = sorted({n for n in named if named.count(n) > 1})
        if twice or not all(groups):
            raise ValueError(f"surfaces: each solid belongs to one surface, and each surface has a solid; "
                             f"got {[list(g) for g in groups]}")
        return dataclasses.replace(self, surfaces=groups)

    def surface(self, solid: str) -> int:
        """The surface of the solid ``solid``: the index of its group in :attr:`surfaces`
        plus one, 0 for a solid no group names."""
        return next((k + 1 for k, g in enumerate(self.surfaces) if solid in g), 0)

    def with_geometry(self, geometry: str) -> Scene:
        """The same scene with another contact geometry, ``"exact"`` or ``"seed"``."""
        return Scene.from_arrays(
            self._boxes(), self._planes(), gravity=float(self.gravity), balls=self.balls,
            air=self.air, geometry=geometry,
        ).with_law(self.law).with_priors(self.priors).with_surfaces(self.surfaces)

    def set_aside(self, names) -> Scene:
        """The same scene with the solids ``names`` out of play: each box moved
        ``OUT_OF_REACH`` above the origin, each plane's half-space ``OUT_OF_REACH`` behind
        its face. The arrays keep their shapes, so a compiled program of the scene runs the
        result as it is (a fit in pixels sets aside what no start bounces on:
        ``estim.fitting._image``). A ``KeyError`` names a solid the scene lacks."""
        unknown = [n for n in names if n not in self.names]
        if unknown:
            raise KeyError(f"unknown solid(s) {unknown}: this scene has {list(self.names)}")
        aside = np.isin(np.asarray(self.names), list(names))
        box = aside[:self.n_boxes, None]
        centre = jnp.where(box, jnp.array([0.0, 0.0, OUT_OF_REACH]), self.box_centre)
        offset = jnp.where(aside[self.n_boxes:], -OUT_OF_REACH, self.plane_offset)
        return eqx.tree_at(lambda s: (s.box_centre, s.plane_offset), self, (centre, offset))

    def _boxes(self):
        return {n: (tuple(map(float, c)), tuple(map(float, h))) for n, c, h in
                zip(self.names, np.asarray(self.box_centre), np.asarray(self.box_half), strict=False)}

    def _planes(self):
        return {n: (tuple(map(float, v)), float(o)) for n, v, o in
                zip(self.names[self.n_boxes:], np.asarray(self.plane_normal), np.asarray(self.plane_offset), strict=True)}

    def face_label(self, face: int) -> tuple[str, str]:
        """``(solid name, face)`` of face index ``face``, e.g. ``("step2", "+z")``."""
        solid = self.names[self.face_solid[face]]
        m = self.face_direction[face]
        if self.face_solid[face] >= self.n_boxes:
            return solid, "plane"
        label = "".join(
            f"{'+' if m[i] > 0 else '-'}{'xyz'[i]}" for i in range(3) if m[i] != 0
        )
        return solid, label

    @staticmethod
    def from_arrays(
        boxes: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]],
        planes: dict[str, tuple[tuple[float, float, float], float]] | None = None,
        *,
        gravity: float = 9.81,
        balls: tuple[Ball, ...] = (),
        air: Air | None = None,
        geometry: str = "exact",
    ) -> Scene:
        """A scene from plain numbers.

        Args:
            boxes: ``name -> (centre, half_size)``.
            planes: ``name -> (outward unit normal, offset)``, solid where
                ``normal . x <= offset``; the normal must be a coordinate axis.
            gravity: magnitude g > 0 (m/s^2); gravity points along -z.
            balls: the balls the scene defines.
            air: the air (drag, wind, Magnus), or ``None`` for gravity only.
            geometry: ``"exact"`` (faces, edges and corners of every box) or ``"seed"``
                (faces only; module docstring).
        """
        planes = planes or {}
        if not boxes and not planes:
            raise ValueError("a scene needs at least one box or plane to bounce on")
        if not (math.isfinite(gravity) and gravity > 0):
            raise ValueError(f"gravity must be a finite positive magnitude, got {gravity!r}")
        centre = np.array([b[0] for b in boxes.values()], dtype=np.float64).reshape(-1, 3)
        half = np.array([b[1] for b in boxes.values()], dtype=np.float64).reshape(-1, 3)
        normal = np.array([p[0] for p in planes.values()], dtype=np.float64).reshape(-1, 3)
        offset = np.array([p[1] for p in planes.values()], dtype=np.float64).reshape(-1)
        names = tuple(boxes) + tuple(planes)
        for name, c, h in zip(boxes, centre, half, strict=True):
            if not (np.all(np.isfinite(c)) and np.all(np.isfinite(h)) and np.all(h > 0)):
                raise ValueError(f"box {name!r}: centre {c} and half sizes {h} must be finite, sizes > 0")
        for name, n in zip(planes, normal, strict=True):
            if not (np.count_nonzero(n) == 1 and abs(np.abs(n).sum() - 1) < 1e-12):
                raise ValueError(f"plane {name!r}: normal {n} must be a coordinate axis")
        if geometry not in GEOMETRIES:
            raise ValueError(f"unknown contact geometry {geometry!r}: expected one of {GEOMETRIES}")
        face_solid, face_direction = _faces(centre, half, normal, offset, geometry)
        return Scene(
            box_centre=jnp.asarray(centre),
            box_half=jnp.asarray(half),
            plane_normal=jnp.asarray(normal),
            plane_offset=jnp.asarray(offset),
            gravity=jnp.asarray(float(gravity)),
            names=names,
            face_solid=face_solid,
            face_direction=face_direction,
            balls=tuple(balls),
            air=_checked_air(air),
            geometry=geometry,
        )


def _checked_air(air: Air | None) -> Air | None:
    if air is None:
        return None
    if not isinstance(air, Air):
        raise TypeError(f"air must be an estim.Air or None, got {type(air).__name__}")
    rho, eta, wind = float(air.density), float(air.viscosity), np.asarray(air.wind)
    if not (math.isfinite(rho) and rho >= 0 and math.isfinite(eta) and eta >= 0):
        raise ValueError(f"air density {rho} and viscosity {eta} must be finite and >= 0")
    if wind.shape != (3,) or not np.all(np.isfinite(wind)):
        raise ValueError(f"wind must be a finite 3-vector (m/s), got {wind.tolist()}")
    if rho == 0 and eta == 0:
        raise ValueError(
            f"wind {wind.tolist()} without air density or viscosity exerts no force; "
            "set density (quadratic drag) and/or viscosity (linear drag), or remove it"
        )
    return air


def _faces(centre, half, normal, offset, geometry):
    """Static face table: the flat faces of every box, one face per plane, then (exact
    geometry) the edges and corners of every box; each box's pieces in the order of
    ``_DIRECTIONS``. Flat faces first, so that the contact search takes them as one slice.

    Piece m of box b is unreachable when, for every radius r >= 0, it lies inside the
    grown half-space ``n . x <= s + r`` of some plane. The piece's points are box points of
    the box face F_m plus at most r in any direction, so this holds iff
    ``max_{x in F_m} n . x <= s`` (the r terms cancel because |n . d| <= r for d in the
    ball of radius r).
    """
    face_solid, face_direction = [], []
    rank = np.abs(_DIRECTIONS).sum(axis=1)

    def pieces(directions):
        for b in range(centre.shape[0]):
            for m in directions:
                # F_m: the box points maximising m . x; its extreme value along a plane normal
                # n picks, per axis, the face coordinate where m_i != 0 and the best end otherwise.
                covered = False
                for n, s in zip(normal, offset, strict=True):
                    top = 0.0
                    for i in range(3):
                        if m[i] != 0:
                            top += n[i] * (centre[b, i] + m[i] * half[b, i])
                        else:
                            top += n[i] * centre[b, i] + abs(n[i]) * half[b, i]
                    if top <= s + 1e-12:
                        covered = True
                        break
                if not covered:
                    face_solid.append(b)
                    face_direction.append(tuple(float(v) for v in m))

    pieces(_DIRECTIONS[rank == 1])
    for p in range(normal.shape[0]):
        face_solid.append(centre.shape[0] + p)
        face_direction.append(tuple(float(v) for v in normal[p]))
    if geometry == "exact":
        pieces(_DIRECTIONS[rank >= 2])
    return tuple(face_solid), tuple(face_direction)


def load_scene(path: str | os.PathLike) -> Scene:
    """Read a scene from an MJCF file (see the module docstring for what is read).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: MuJoCo cannot compile it, or it holds geometry estim cannot simulate
            exactly (the message names the geom).
    """
    import mujoco

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"scene file not found: {path}")
    try:
        model = mujoco.MjModel.from_xml_path(path)
    except Exception as err:  # mujoco raises ValueError with its own parser message
        raise ValueError(f"{path}: MuJoCo could not load this MJCF file: {err}") from None
    return scene_from_model(model, source=path)


def scene_from_model(model, *, source: str = "<model>") -> Scene:
    """Build a :class:`Scene` from a compiled ``mujoco.MjModel``."""
    import mujoco

    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    gx, gy, gz = (float(v) for v in model.opt.gravity)
    if gx != 0.0 or gy != 0.0 or not gz < 0.0:
        raise ValueError(
            f"{source}: gravity {model.opt.gravity.tolist()} must point along -z "
            "(estim's contact model assumes horizontal treads under vertical gravity)"
        )
    density, viscosity = float(model.opt.density), float(model.opt.viscosity)
    wind = [float(w) for w in model.opt.wind]
    air = None
    if density != 0 or viscosity != 0 or any(wind):
        if density == 0 and viscosity == 0:
            raise ValueError(
                f"{source}: <option wind={wind}> without density or viscosity exerts no "
                "force; set density (quadratic drag) and/or viscosity (linear drag)"
            )
        air = Air(density, viscosity, wind)
    free_bodies = {
        int(model.jnt_bodyid[j])
        for j in range(model.njnt)
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
    }
    boxes, planes, balls = {}, {}, []
    ball_geom = {}  # body -> the name of its sphere
    for g in range(model.ngeom):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}"
        body = int(model.geom_bodyid[g])
        kind = int(model.geom_type[g])
        if kind == mujoco.mjtGeom.mjGEOM_SPHERE and body in free_bodies:
            body_name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or name
            if body in ball_geom:
                raise ValueError(f"{source}: body {body_name!r} has two sphere geoms ({ball_geom[body]!r} "
                                 f"and {name!r}); a ball is one sphere on a free body")
            ball_geom[body] = name
            offset = np.asarray(model.geom_pos[g], dtype=float)
            if np.any(offset != 0):
                # The ball's centre is its body's origin (the release point, and the point
                # the replay moves); a sphere off that origin would be another point.
                raise ValueError(f"{source}: sphere {name!r} sits at {offset.tolist()} from the "
                                 f"origin of its body {body_name!r}; centre it on the body "
                                 "(move the offset to the body's pos)")
            pos = tuple(float(v) for v in data.xpos[body])
            radius, mass = float(model.geom_size[g, 0]), float(model.body_mass[body])
            inertia = float(np.mean(model.body_inertia[body])) / (mass * radius**2)
            if not 0.0 < inertia <= 1.0:
                raise ValueError(f"{source}: ball {body_name!r} has the moment of inertia "
                                 f"{inertia:.4g} m r^2, outside (0, 1] m r^2 (a sphere has 2/5, a "
                                 "shell 2/3): check its <inertial> or use shellinertia")
            balls.append(Ball(body_name, radius, mass, pos, inertia))
            continue
        if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
            continue  # visual only, exactly as in MuJoCo
        if body in free_bodies or model.body_dofnum[body] > 0:
            raise ValueError(f"{source}: geom {name!r} moves (it is on a body with joints); "
                             "contact surfaces must be static")
        rot = data.geom_xmat[g].reshape(3, 3)
        if kind == mujoco.mjtGeom.mjGEOM_BOX:
            perm = np.abs(rot)
            if not np.allclose(perm, np.round(perm), atol=1e-9):
                raise ValueError(
                    f"{source}: box {name!r} is rotated; estim supports axis-aligned boxes "
                    "(rotations by multiples of 90 degrees) only"
                )
            half = np.round(perm) @ model.geom_size[g]
            boxes[name] = (tuple(data.geom_xpos[g]), tuple(half))
        elif kind == mujoco.mjtGeom.mjGEOM_PLANE:
            n = rot[:, 2]
            if not np.allclose(np.abs(n), np.round(np.abs(n)), atol=1e-9):
                raise ValueError(
                    f"{source}: plane {name!r} has normal {n.round(6).tolist()}; estim "
                    "supports planes whose normal is a coordinate axis only"
                )
            n = np.round(n)
            planes[name] = (tuple(n), float(n @ data.geom_xpos[g]))
        else:
            kind_name = mujoco.mjtGeom(kind).name.removeprefix("mjGEOM_").lower()
            raise ValueError(
                f"{source}: geom {name!r} is a {kind_name}; estim's contact surfaces are "
                "boxes and planes, and its balls are spheres on free bodies"
            )
    if not boxes and not planes:
        raise ValueError(f"{source}: the scene has no contact surfaces (box or plane geoms)")
    law = _declared(model, source, LAW_TEXT, LAWS, "contact law")
    scene = Scene.from_arrays(boxes, planes, gravity=-gz, balls=tuple(balls), air=air,
                             geometry=_declared(model, source, GEOMETRY_TEXT, GEOMETRIES, "contact geometry"),
                             ).with_law(None if law == LAWS[0] else law).with_priors(_priors(model, source))
    try:
        return scene.with_surfaces(_surfaces(model))
    except ValueError as err:
        raise ValueError(f"{source}: <text name={SURFACES_TEXT!r}>: {err}") from None


def _text(model, name: str) -> str | None:
    """The data of the MJCF ``<custom><text name=NAME>``, or ``None`` where there is none."""
    import mujoco

    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXT, name)
    if i < 0:
        return None
    start, size = int(model.text_adr[i]), int(model.text_size[i])
    return bytes(model.text_data[start:start + size]).split(b"\0", 1)[0].decode().strip()


def _surfaces(model) -> tuple[tuple[str, ...], ...]:
    """The surfaces an MJCF file declares (module docstring): groups of geom names."""
    text = _text(model, SURFACES_TEXT)
    return () if text is None else tuple(tuple(g.split()) for g in text.split(";"))


def _priors(model, source: str) -> tuple[tuple[str, float, float], ...]:
    """The priors an MJCF file declares: ``<numeric name="estim:prior:NAME" data="MEAN SD"/>``
    in ``<custom>`` (module docstring). Which names a fit knows is the fit's to check."""
    import mujoco

    out = []
    for i in range(model.nnumeric):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_NUMERIC, i) or ""
        if not name.startswith(PRIOR_NUMERIC):
            continue
        start, size = int(model.numeric_adr[i]), int(model.numeric_size[i])
        data = [float(v) for v in model.numeric_data[start:start + size]]
        if len(data) != 2 or not all(map(math.isfinite, data)) or not data[1] > 0:
            raise ValueError(f"{source}: <numeric name={name!r} data={data}> must hold two finite numbers, "
                             "the prior's mean and its standard deviation (> 0)")
        out.append((name.removeprefix(PRIOR_NUMERIC), data[0], data[1]))
    return tuple(out)


def _declared(model, source: str, text: str, choices: tuple[str, ...], what: str) -> str:
    """The choice an MJCF file declares in ``<custom><text name=TEXT data="..."/></custom>``,
    the first of ``choices`` if it declares none."""
    value = _text(model, text)
    if value is None:
        return choices[0]
    if value not in choices:
        raise ValueError(f"{source}: <text name={text!r} data={value!r}> declares an unknown "
                         f"{what}; expected one of {choices}")
    return value
