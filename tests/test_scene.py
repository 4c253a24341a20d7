"""Scenes from MJCF (estim.load_scene), Scene.from_arrays, and input validation of
Params and simulate. Nothing here compiles ``simulate``: every error is raised before."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import STAIRS_XML

import estim


def write(tmp_path, body: str, *, option: str = "", assets: str = "", name: str = "scene.xml"):
    path = tmp_path / name
    path.write_text(
        f"""<mujoco model="t">
  {option}
  <asset>{assets}</asset>
  <worldbody>
{body}
  </worldbody>
</mujoco>
"""
    )
    return path


GROUND = '<geom name="floor" type="plane" size="5 5 0.1"/>'
BALL = '<body name="ball" pos="0 0 1"><freejoint/><geom name="ball" type="sphere" size="0.05" mass="0.1"/></body>'


# ---------------------------------------------------------------------------------------
# The seed scene
# ---------------------------------------------------------------------------------------


def test_load_stairs(stairs):
    assert stairs.names == ("step1", "step2", "step3", "step4", "step5", "ground")
    assert stairs.n_boxes == 5
    np.testing.assert_allclose(float(stairs.gravity), 9.81, rtol=0, atol=1e-15)
    k = np.arange(5)
    top = 1.40 - 0.2 * k
    np.testing.assert_allclose(
        np.asarray(stairs.box_centre), np.stack([0.6 * k, 0 * k, top / 2], 1), atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(stairs.box_half), np.stack([0.3 + 0 * k, 0.6 + 0 * k, top / 2], 1), atol=1e-12
    )
    np.testing.assert_allclose(np.asarray(stairs.plane_normal), [[0.0, 0.0, 1.0]], atol=0)
    np.testing.assert_allclose(np.asarray(stairs.plane_offset), [0.0], atol=0)
    balls = {b.name: b for b in stairs.balls}
    assert set(balls) == {"bocce", "golf", "pingpong"}
    for name, r, m, pos in (
        ("bocce", 0.08, 0.92, (-0.20, -0.30, 1.73)),
        ("golf", 0.05, 0.046, (-0.20, 0.00, 1.70)),
        ("pingpong", 0.04, 0.005, (-0.20, 0.30, 1.69)),
    ):
        b = stairs.ball(name)
        assert b == balls[name]
        assert b.radius == pytest.approx(r, abs=1e-12)
        assert b.mass == pytest.approx(m, abs=1e-12)
        np.testing.assert_allclose(b.position, pos, atol=1e-12)
    with pytest.raises(KeyError, match="tennis"):
        stairs.ball("tennis")


def test_face_table(stairs, stairs_exact):
    """Exact geometry: every box's 6 faces, 12 edges and 8 corners, flat faces first, less
    those the ground covers; the seed's geometry (stairs.xml): the faces only."""
    labels = [stairs_exact.face_label(f) for f in range(stairs_exact.n_faces)]
    assert len(set(labels)) == len(labels)
    for k in range(1, 6):
        assert (f"step{k}", "+z") in labels
        assert (f"step{k}", "+x") in labels and (f"step{k}", "+x+z") in labels
        # Every tread stands on the ground: its bottom pieces can never be reached.
        assert not any(s == f"step{k}" and "-z" in lab for s, lab in labels)
        # 26 directions minus the 9 with m_z = -1.
        assert sum(s == f"step{k}" for s, _ in labels) == 17
    flat = [len(lab) == 2 or lab == "plane" for _, lab in labels]
    assert flat == sorted(flat, reverse=True)  # flat faces first
    assert labels[sum(flat) - 1] == ("ground", "plane")
    assert stairs_exact.n_faces == 5 * 17 + 1
    assert stairs_exact.geometry == "exact" and stairs.geometry == "seed"
    seed = [stairs.face_label(f) for f in range(stairs.n_faces)]
    assert seed == [x for x, f in zip(labels, flat, strict=True) if f]  # 5 faces per tread, the ground
    assert stairs.n_faces == 5 * 5 + 1


def test_declared_geometry(tmp_path):
    """A scene declares its geometry in MJCF (<custom><text name="estim:geometry">); an
    unknown one is an error naming it; from_arrays and with_geometry take it too."""
    body = f"""    {GROUND}
    <geom name="block" type="box" pos="1 0 0.25" size="0.5 0.25 0.25"/>
    {BALL}"""
    exact = estim.load_scene(write(tmp_path, body))
    assert exact.geometry == "exact" and exact.n_faces == 17 + 1
    custom = '<custom><text name="estim:geometry" data="seed"/></custom>'
    seed = estim.load_scene(write(tmp_path, body, option=custom))
    assert seed.geometry == "seed" and seed.n_faces == 5 + 1
    assert exact.with_geometry("seed").n_faces == seed.n_faces
    bad = '<custom><text name="estim:geometry" data="bevel"/></custom>'
    with pytest.raises(ValueError, match="data='bevel'> declares an unknown contact geometry"):
        estim.load_scene(write(tmp_path, body, option=bad))
    with pytest.raises(ValueError, match="unknown contact geometry"):
        estim.Scene.from_arrays({"b": ((0, 0, 0), (1, 1, 1))}, geometry="round")


def test_declared_surfaces(tmp_path):
    """A scene declares which solids are surfaces of their own (<custom><text
    name="estim:surfaces">, groups separated by ';'); the solids no group names are one
    surface; a name the scene lacks, or one named twice, is an error naming it; the
    declaration survives another geometry."""
    body = f"""    {GROUND}
    <geom name="table" type="box" pos="1 0 0.25" size="0.5 0.25 0.25"/>
    <geom name="net" type="box" pos="1 0 0.6" size="0.01 0.25 0.1"/>
    <geom name="step" type="box" pos="-1 0 0.1" size="0.5 0.25 0.1"/>
    {BALL}"""
    plain = estim.load_scene(write(tmp_path, body))
    assert plain.surfaces == () and {plain.surface(n) for n in plain.names} == {0}
    declared = '<custom><text name="estim:surfaces" data="table net; floor"/></custom>'
    scene = estim.load_scene(write(tmp_path, body, option=declared))
    assert scene.surfaces == (("table", "net"), ("floor",))
    assert [scene.surface(n) for n in ("table", "net", "floor", "step")] == [1, 1, 2, 0]
    assert scene.with_geometry("seed").surfaces == scene.surfaces
    for data, words in (("table; roof", r"unknown solid\(s\) \['roof'\]"), ("table; table floor", "one surface"),
                        ("table;; floor", "each surface has a solid")):
        bad = f'<custom><text name="estim:surfaces" data="{data}"/></custom>'
        with pytest.raises(ValueError, match="<text name='estim:surfaces'>: surfaces: .*" + words):
            estim.load_scene(write(tmp_path, body, option=bad))


# ---------------------------------------------------------------------------------------
# MJCF errors name the geom
# ---------------------------------------------------------------------------------------


def test_inline_scene(tmp_path):
    body = f"""    {GROUND}
    <geom name="block" type="box" pos="1 0 0.25" size="0.5 0.25 0.25"/>
    <geom name="turned" type="box" pos="-1 0 0.5" size="0.1 0.2 0.5" euler="0 0 90"/>
    <geom name="decor" type="capsule" size="0.1 0.5" pos="0 3 1" contype="0" conaffinity="0"/>
    {BALL}"""
    scene = estim.load_scene(write(tmp_path, body, option='<option gravity="0 0 -3.7"/>'))
    assert scene.names == ("block", "turned", "floor")
    np.testing.assert_allclose(
        np.asarray(scene.box_half), [[0.5, 0.25, 0.25], [0.2, 0.1, 0.5]], atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(scene.box_centre), [[1, 0, 0.25], [-1, 0, 0.5]], atol=1e-12
    )
    assert float(scene.gravity) == pytest.approx(3.7, abs=1e-12)
    assert scene.balls == (estim.Ball("ball", 0.05, pytest.approx(0.1), (0.0, 0.0, 1.0), pytest.approx(0.4)),)


@pytest.mark.parametrize(
    ("geom", "assets", "name", "words"),
    [
        (
            '<geom name="tilted" type="box" size="0.3 0.3 0.3" pos="0 0 0.3" quat="0.9238795 0 0 0.3826834"/>',
            "",
            "tilted",
            "rotated",
        ),
        (
            '<geom name="rock" type="mesh" mesh="tet"/>',
            '<mesh name="tet" vertex="0 0 0  1 0 0  0 1 0  0 0 1"/>',
            "rock",
            "mesh",
        ),
        ('<geom name="pipe" type="capsule" size="0.1 0.5" pos="0 0 1"/>', "", "pipe", "capsule"),
        ('<geom name="boulder" type="sphere" size="0.3" pos="1 1 0.3"/>', "", "boulder", "sphere"),
        ('<geom name="slope" type="plane" size="5 5 0.1" euler="20 0 0"/>', "", "slope", "normal"),
    ],
)
def test_unsupported_geometry_is_named(tmp_path, geom, assets, name, words):
    path = write(tmp_path, f"    {GROUND}\n    {geom}\n    {BALL}", assets=assets)
    with pytest.raises(ValueError, match=name) as info:
        estim.load_scene(path)
    assert words in str(info.value)


def test_gravity_must_point_down(tmp_path):
    for g in ("0 0 9.81", "1 0 -9.81", "0 0 0"):
        path = write(tmp_path, f"    {GROUND}\n    {BALL}", option=f'<option gravity="{g}"/>')
        with pytest.raises(ValueError, match="gravity"):
            estim.load_scene(path)


def test_no_contact_surfaces(tmp_path):
    with pytest.raises(ValueError, match="no contact surfaces"):
        estim.load_scene(write(tmp_path, f"    {BALL}"))
    with pytest.raises(ValueError, match="at least one box or plane"):
        estim.Scene.from_arrays(boxes={}, planes={})


def test_missing_and_broken_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.xml"):
        estim.load_scene(tmp_path / "nowhere.xml")
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody><geom type='box'")
    with pytest.raises(ValueError, match="bad.xml"):
        estim.load_scene(bad)


def test_from_arrays_validation():
    with pytest.raises(ValueError, match="'flat'"):
        estim.Scene.from_arrays(boxes={"flat": ((0, 0, 0), (1, 1, 0))})
    with pytest.raises(ValueError, match="'tilt'"):
        estim.Scene.from_arrays(boxes={}, planes={"tilt": ((0.6, 0.0, 0.8), 0.0)})
    with pytest.raises(ValueError, match="gravity"):
        estim.Scene.from_arrays(boxes={"b": ((0, 0, 0), (1, 1, 1))}, gravity=-9.81)


def test_stairs_file_is_the_seed():
    assert STAIRS_XML.is_file()
    scene = estim.load_scene(str(STAIRS_XML))  # str and Path both accepted
    assert scene.names[0] == "step1"


# ---------------------------------------------------------------------------------------
# Params and simulate validation
# ---------------------------------------------------------------------------------------

GOOD = dict(e=0.7, mu_t=0.98, radius=0.05, position=(-0.2, 0.0, 1.7), velocity=(1.15, 0.0, 0.0))


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("e", math.nan, "Params.e"),
        ("e", 1.2, "Params.e"),
        ("e", -0.01, "Params.e"),
        ("mu_t", -0.1, "Params.mu_t"),
        ("mu_t", 1.0 + 1e-9, "Params.mu_t"),
        ("radius", 0.0, "Params.radius"),
        ("radius", -0.05, "Params.radius"),
        ("position", (0.0, math.inf, 1.0), "Params.position"),
        ("velocity", (math.nan, 0.0, 0.0), "Params.velocity"),
        ("position", (0.0, 1.0), "last axis of length 3"),
    ],
)
def test_params_validation(field, value, words):
    with pytest.raises(ValueError, match=words):
        estim.Params(**{**GOOD, field: value})


def test_params_bounds_are_inclusive():
    for e, mu in ((0.0, 0.0), (1.0, 1.0)):
        p = estim.Params(**{**GOOD, "e": e, "mu_t": mu})
        assert float(p.e) == e and float(p.mu_t) == mu
    p = estim.Params(np.full(4, 0.5), 0.9, 0.05, np.zeros((4, 3)) + [0, 0, 2], (1.0, 0.0, 0.0))
    assert p.batch_shape == (4,)


def test_params_for_ball(stairs):
    p = estim.Params.for_ball(stairs, "golf", e=0.7, mu_t=0.98, velocity=(1.15, 0, 0))
    assert float(p.radius) == 0.05
    np.testing.assert_allclose(np.asarray(p.position), (-0.2, 0.0, 1.70), atol=1e-12)


@pytest.mark.parametrize("t_end", [0.0, -1.0, math.inf, math.nan])
def test_simulate_rejects_bad_t_end(stairs, t_end):
    with pytest.raises(ValueError, match="t_end"):
        estim.simulate(stairs, estim.Params(**GOOD), t_end)


def test_simulate_rejects_bad_ts(stairs):
    with pytest.raises(ValueError, match="ts"):
        estim.simulate(stairs, estim.Params(**GOOD), 1.0, ts=[0.0, 2.0])
    with pytest.raises(ValueError, match="ts"):
        estim.simulate(stairs, estim.Params(**GOOD), 1.0, ts=[[0.0, 0.5]])


@pytest.mark.parametrize(
    ("position", "solid"),
    [
        ((0.6, 0.0, 1.0), "step2"),  # deep inside the tread
        ((0.0, 0.0, 1.42), "step1"),  # centre above the top, but closer than r = 0.05
        ((-0.32, 0.0, 1.42), "step1"),  # 0.028 m from the top-left edge (< r)
        ((5.0, 0.0, 0.01), "ground"),  # sunk into the ground plane
    ],
)
def test_simulate_rejects_ball_inside_a_solid(stairs, stairs_exact, position, solid):
    """A ball closer than r to a solid: on the exact staircase, and on the seed's (whose
    treads have no edges) unless it overlaps only an edge."""
    with pytest.raises(ValueError, match=f"inside '{solid}'"):
        estim.simulate(stairs_exact, estim.Params(**{**GOOD, "position": position}), 1.0)
    if position[0] != -0.32:
        with pytest.raises(ValueError, match=f"inside '{solid}'"):
            estim.simulate(stairs, estim.Params(**{**GOOD, "position": position}), 1.0)


def test_simulate_rejects_wrong_types(stairs):
    with pytest.raises(TypeError, match="Scene"):
        estim.simulate("data/scenes/stairs.xml", estim.Params(**GOOD), 1.0)
    with pytest.raises(TypeError, match="Params"):
        estim.simulate(stairs, dict(GOOD), 1.0)
