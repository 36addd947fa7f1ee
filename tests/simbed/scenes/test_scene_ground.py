"""Ground height from a scene's own static geometry: checked against the analytic heights of a
hand-written scene with a ramp, a tree, a building, a parking deck and a hole."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from rangemcl.raycast import RayCaster
from simbed.scenes.scene_ground import SceneGround
from simbed.sim.geometry import split_static_dynamic

RAMP_DEG = 8.0
SCENE = f"""
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="40 40 0.1"/>
    <!-- a ramp: a thin box pitched by RAMP_DEG about y, its top surface rising along +x -->
    <geom name="ramp" type="box" size="6 3 0.2" pos="10 0 0.6" euler="0 {-RAMP_DEG} 0"/>
    <!-- a tree: trunk and crown, its crown 3 m above the ground -->
    <geom name="trunk" type="cylinder" size="0.2 2" pos="-10 0 2"/>
    <geom name="crown" type="sphere" size="1.5" pos="-10 0 4.6"/>
    <!-- a building 8 m high -->
    <geom name="house" type="box" size="3 3 4" pos="0 15 4"/>
    <!-- a deck on pillars: 4 m of free space under it -->
    <geom name="deck" type="box" size="4 4 0.2" pos="0 -15 4.2"/>
    <body name="door" pos="20 20 1"><joint type="slide" axis="1 0 0"/><geom type="box" size="1 0.1 1"/></body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def ground():
    model = mujoco.MjModel.from_xml_string(SCENE)
    parts = split_static_dynamic(model, mujoco.MjData(model))
    caster = RayCaster(threads=1)
    v, f, _ = parts.static
    handle = caster.add_mesh(v, f, name="static")
    for bm in parts.dynamic:
        caster.add_mesh(bm.vertices, bm.faces, name=bm.name, movable=True)
    return SceneGround.from_triangles(caster, handle, v), model


def ramp_top(x: np.ndarray) -> np.ndarray:
    """The ramp's top surface: its centre line pitched by RAMP_DEG about the box centre (10, 0, 0.6)."""
    a = math.radians(RAMP_DEG)
    # top face: points c + R (u, 0, 0.2); its height at world x is 0.6 + tan(a) (x - 10) + 0.2 / cos(a)
    return 0.6 + math.tan(a) * (x - 10.0) + 0.2 / math.cos(a)


def test_open_ground_is_the_floor(ground):
    g, _ = ground
    rng = np.random.default_rng(0)
    x = rng.uniform(-35, 35, 200)
    y = rng.uniform(25, 35, 200)
    assert np.allclose(g.height(x, y), 0.0, atol=1e-4)


def test_the_ramp_top_where_it_is_above_the_floor(ground):
    g, _ = ground
    x = np.linspace(6.0, 15.5, 40)
    h = g.height(x, np.zeros_like(x))
    expect = ramp_top(x)
    up = expect > 0.05  # where the ramp's top is above the floor
    assert np.allclose(h[up], expect[up], atol=2e-3)


def test_under_a_tree_and_a_deck_the_ground_beneath_on_a_house_its_roof(ground):
    g, _ = ground
    assert g.height(-10.0 + 1.0, 0.0) == pytest.approx(0.0, abs=1e-4)  # under the crown
    assert g.height(0.5, -15.5) == pytest.approx(0.0, abs=1e-4)  # under the deck
    assert g.height(0.5, 15.5) == pytest.approx(8.0, abs=1e-4)  # the house's roof


def test_moving_bodies_are_not_ground_and_outside_is_nan(ground):
    g, _ = ground
    assert g.height(20.0, 20.0) == pytest.approx(0.0, abs=1e-4)  # under the door: the floor
    assert np.isnan(g.height(60.0, 0.0))
    h = g.height(np.array([[0.0, 60.0], [30.0, -30.0]]), np.zeros((2, 2)))
    assert h.shape == (2, 2) and np.isnan(h[0, 1]) and h[1, 1] == pytest.approx(0.0, abs=1e-4)
