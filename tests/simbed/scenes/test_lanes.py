"""Waypoint files as lanes in any scene: corners rounded within the car's steering, the
checks against the scene (ground, steps, static geometry in the car's box), one line naming the first
bad waypoint."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from rangemcl.errors import InputError
from rangemcl.raycast import RayCaster
from simbed.scenes.lanes import CAR_MIN_RADIUS_M, check_lane, lane_from_waypoints, read_waypoints
from simbed.scenes.scene_ground import SceneGround
from simbed.sim.geometry import split_static_dynamic

SCENE = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="40 40 0.1"/>
    <geom name="house" type="box" size="3 3 4" pos="0 15 4"/>
    <geom name="kerb" type="box" size="2 2 0.2" pos="-25 0 0.2"/>
    <geom name="platform" type="box" size="3 3 1" pos="25 -25 1"/>
    <geom name="pole" type="cylinder" size="0.15 1.5" pos="0 30 1.5"/>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def scene():
    model = mujoco.MjModel.from_xml_string(SCENE)
    parts = split_static_dynamic(model, mujoco.MjData(model))
    caster = RayCaster(threads=1)
    v, f, _ = parts.static
    handle = caster.add_mesh(v, f, name="static")
    ground = SceneGround.from_triangles(caster, handle, v)
    return caster, handle, ground.height


def write(tmp_path, text: str):
    p = tmp_path / "route.txt"
    p.write_text(text)
    return p


def test_a_square_loop_is_rounded_closed_and_clear(tmp_path, scene):
    p = write(tmp_path, "# a square around the house\n-20 -20\n20,-20\n20 20 4.0\n-20 20\n")
    lane = lane_from_waypoints(read_waypoints(p), loop=True)
    pts = lane.points
    step = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
    assert step.max() <= 0.5 + 1e-9 and step.min() > 1e-6  # closed, evenly sampled
    # corners rounded with the default 8 m arc: the lane passes the corner 8 (sqrt 2 - 1) m inside it
    d = np.linalg.norm(pts - np.array([20.0, 20.0]), axis=1).min()
    assert d == pytest.approx(8 * (math.sqrt(2) - 1), abs=0.05)
    # the third waypoint's speed from it on, the driver's choice elsewhere
    assert np.isnan(lane.speed[lane.leg == 0]).all() and (lane.speed[lane.leg == 2] == 4.0).all()
    caster, handle, ground = scene
    z = check_lane(lane, ground, caster, handle)
    assert np.allclose(z, 0.0, atol=1e-4)


@pytest.mark.parametrize(
    ("text", "loop", "words"),
    [
        ("-20 -20\n20 -20\n-20 -19\n", False, ["waypoint 2", "turn of", "radius"]),
        ("-20 30.5\n20 30.5\n", False, ["waypoint 1", "static geometry"]),  # past a pole, too close
        ("-20 15\n20 15\n", False, ["waypoint 1", "steps"]),  # into the house
        ("-35 0\n-10 0\n", False, ["waypoint 1", "steps"]),  # over the kerb
        ("0 -30\n60 -30\n", False, ["waypoint 1", "no ground"]),  # off the floor
        ("0 0\n0 0\n5 5\n", False, [":2:", "repeats"]),
        ("0 0\n1 2 3 4\n", False, [":2:", "two or three"]),
        ("0 0\n1 x\n", False, [":2:", "x y"]),
        ("0 0\n10 0 -1\n", False, [":2:", "speed"]),
        ("0 0\n", False, ["at least 2"]),
        ("0 0\n10 0\n", True, ["loop needs at least 3"]),
        ("0 0\n10 0\n10 10\n0 0\n", True, ["waypoint 4", "repeats the first"]),
    ],
)
def test_bad_routes_name_the_first_bad_waypoint(tmp_path, scene, text, loop, words):
    p = write(tmp_path, text)
    caster, handle, ground = scene
    with pytest.raises(InputError) as err:
        check_lane(lane_from_waypoints(read_waypoints(p), loop=loop), ground, caster, handle)
    msg = str(err.value)
    assert "\n" not in msg and str(p) in msg
    for w in words:
        assert w in msg, msg


def test_the_tightest_turn_allowed_is_the_cars(tmp_path):
    # a right angle between 2r-long legs allows an arc of radius r: just above the limit passes
    r = 1.25 * CAR_MIN_RADIUS_M
    p = write(tmp_path, f"0 0\n{2 * r:.3f} 0\n{2 * r:.3f} {2 * r:.3f}\n")
    lane = lane_from_waypoints(read_waypoints(p))
    assert len(lane.points) > 10
    p = write(tmp_path, f"0 0\n{1.6 * r:.3f} 0\n{1.6 * r:.3f} {1.6 * r:.3f}\n")
    with pytest.raises(InputError, match="waypoint 2"):
        lane_from_waypoints(read_waypoints(p))
