"""Driving a scene of one's own: an MJCF file written here, with no car and no sidecar
(primitives on a plane, a hump of two ramps), driven along a waypoint loop. The car climbs the ramps as
their geometry says, and every LiDAR return agrees with MuJoCo's own ``mj_ray`` through the scene."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from rangemcl.datasets.kitti import load_sequence
from rangemcl.errors import InputError
from rangemcl.sensors import load_spec
from simbed.record import record
from simbed.sim.world import World

PITCH = math.radians(4.0)
HALF = (6.0, 6.0, 0.5)  # half length, width, thickness of each ramp (room for a lane each way)
RIDGE_X, LANE_Y = 0.0, -20.0


def ramp(name: str, side: int) -> str:
    """A pitched box whose top face's upper end lies at the ridge (x = 0, height h); side -1 rises
    towards +x, side +1 falls."""
    L, W, T = HALF
    h = 0.7
    # the top face's upper corner c + R (-side L, 0, T) sits at (0, h): solve for the centre c
    cx = RIDGE_X + side * (L * math.cos(PITCH) - T * math.sin(PITCH)) * 1.0
    cz = h - L * math.sin(PITCH) - T * math.cos(PITCH)
    pitch_deg = side * math.degrees(PITCH)  # MJCF euler about y: positive tips +x down
    return (
        f'<geom name="{name}" type="box" size="{L} {W} {T}" pos="{cx:.6f} {LANE_Y} {cz:.6f}" '
        f'euler="0 {pitch_deg:.6f} 0"/>'
    )


def hump_height(x: np.ndarray) -> np.ndarray:
    """The hump's analytic top (0 where the floor is higher)."""
    return np.maximum(0.7 - math.tan(PITCH) * np.abs(x - RIDGE_X), 0.0)


SCENE = f"""<mujoco model="my_campus">
  <worldbody>
    <light pos="0 0 50" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="60 60 0.1" rgba="0.5 0.5 0.5 1"/>
    {ramp("ramp_up", -1)}
    {ramp("ramp_down", 1)}
    <geom name="hall" type="box" size="10 6 5" pos="0 0 5"/>
    <geom name="shed" type="box" size="3 3 2" pos="-40 -35 2"/>
    <geom name="trunk" type="cylinder" size="0.25 2" pos="15 -12 2"/>
    <geom name="crown" type="sphere" size="1.8" pos="15 -12 5"/>
    <geom name="pole" type="capsule" size="0.1 2.5" pos="-15 -26 2.5"/>
    <geom name="wall" type="box" size="20 0.2 1.5" pos="0 28 1.5"/>
  </worldbody>
</mujoco>
"""

LOOP = "# a loop around the hall, over the hump\n-28 -20\n28 -20\n28 20 6\n-28 20\n"


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    root = tmp_path_factory.mktemp("own_scene")
    (root / "campus.xml").write_text(SCENE)
    (root / "loop.txt").write_text(LOOP)
    spec = load_spec("vlp-16").to_dict()
    spec.update(name="vlp-16-exact", range_noise_m=0.0, dropout_prob=0.0, beam_origin_radius_m=0.0)
    spec["beam_vertical_offset_m"] = [0.0] * len(spec["elevation_deg"])
    import yaml

    (root / "exact.yaml").write_text(yaml.safe_dump(spec))
    out = root / "run"
    summary = record(
        str(root / "campus.xml"),
        str(root / "loop.txt"),
        str(root / "exact.yaml"),
        out,
        frames=110,
        seed=4,
        skew=False,
        progress=False,
        loop=True,
    )
    return root, out, summary


def test_a_bare_scene_is_driven_along_its_waypoint_loop(drive):
    _, out, summary = drive
    assert summary.frames == 110 and not summary.stuck_at
    seq = load_sequence(out)
    xy = seq.poses[:, :2, 3]
    assert summary.distance_driven_m > 50
    # the car keeps to its lane: the first leg of the loop is y = -20 (corners rounded after x = 20)
    first_leg = xy[:, 0] < 18
    assert np.abs(xy[first_leg, 1] - LANE_Y).max() < 0.5
    assert seq.meta["route_loop"] is True


def test_the_car_climbs_the_ramps_as_their_geometry_says(drive):
    _, out, _ = drive
    seq = load_sequence(out)
    mount_z = float(seq.meta["sensor"]["mount"]["xyz_m"][2])
    T = seq.poses
    # the sensor's height above the analytic ground under the rear axle (the car's origin), level ground
    # and ramps alike; the mount is ahead of the axle, so on a ramp the pitch lifts it by x_mount sin(pitch)
    x_mount = float(seq.meta["sensor"]["mount"]["xyz_m"][0])
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    axle = T[:, :2, 3] - x_mount * np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    on_leg = np.abs(axle[:, 1] - LANE_Y) < 1.0
    ground = hump_height(axle[:, 0])
    pitch = -np.arcsin(np.clip(T[:, 2, 0], -1, 1))
    expected = ground + mount_z * np.cos(pitch) + x_mount * np.sin(pitch)
    err = T[on_leg, 2, 3] - expected[on_leg]
    assert on_leg.sum() > 60 and (ground[on_leg] > 0.6).any()  # it went over the ridge
    assert np.abs(err - np.median(err)).max() < 0.08  # suspension sag is a constant offset
    assert abs(np.median(err)) < 0.1


def test_every_lidar_return_agrees_with_mj_ray(drive):
    root, out, _ = drive
    seq = load_sequence(out)
    world = World(root / "campus.xml", add_car=True)
    m, d = world.model, world.data
    group = np.array([1, 0, 0, 0, 0, 0], np.uint8)  # the scene's geoms; the car's are in groups 1 and 2
    gid = np.zeros(1, np.int32)
    for i in (20, 60, 100):
        pts = seq.scan(i)
        T = seq.poses[i]  # the sensor pose (calib.txt is identity for simbed recordings)
        rng = np.linalg.norm(pts, axis=1)
        dirs = (T[:3, :3] @ (pts / rng[:, None]).T).T
        origin = T[:3, 3]
        ref = np.array([mujoco.mj_ray(m, d, origin, u, group, 1, -1, gid) for u in dirs])
        diff = np.abs(ref - rng)
        assert (ref > 0).mean() > 0.99
        # exact on planes and boxes; tessellated cylinders and spheres within a few millimetres
        assert np.median(diff) < 1e-3 and np.quantile(diff, 0.99) < 0.02, (i, np.quantile(diff, [0.5, 0.99]))


def test_named_routes_need_a_road_network_and_bad_waypoints_stop_before_writing(drive, tmp_path):
    root, _, _ = drive
    with pytest.raises(InputError, match="needs a road network"):
        record(str(root / "campus.xml"), "mapping", "vlp-16", tmp_path / "a", frames=5, progress=False)
    (tmp_path / "bad.txt").write_text("-28 -20\n0 0\n")  # into the hall
    with pytest.raises(InputError, match=r"bad\.txt:1: waypoint 1"):
        record(
            str(root / "campus.xml"),
            str(tmp_path / "bad.txt"),
            "vlp-16",
            tmp_path / "b",
            frames=5,
            progress=False,
        )
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_actors_from_a_paths_file_are_seen_and_labelled(drive, tmp_path):
    root, _, _ = drive
    paths = tmp_path / "paths.yaml"
    paths.write_text(
        "actors:\n"
        "  - {kind: car, speed: 5.0, waypoints: [[-10, -15.0], [25, -15.0]], loop: false}\n"
        "  - {kind: pedestrian, speed: 1.2, waypoints: [[-20, -24], [-5, -24]], start_m: 3.0}\n"
    )
    out = tmp_path / "run"
    record(
        str(root / "campus.xml"),
        str(root / "loop.txt"),
        "vlp-16",
        out,
        frames=30,
        seed=5,
        progress=False,
        loop=True,
        actor_paths=paths,
    )
    seq = load_sequence(out)
    assert seq.meta["actors"] == 2 and seq.meta["actor_paths"] == str(paths)
    label = seq.point_meta(20)["label"]
    pts = seq.scan(20) @ seq.poses[20][:3, :3].T + seq.poses[20][:3, 3]
    moving = pts[label == 1]
    assert len(moving) > 30  # both actors are in view from the lane
    # the labelled points lie on the actors' paths (the car's body is 1.8 m wide, the pedestrian 0.5 m)
    near_car = np.abs(moving[:, 1] + 15.0) < 1.0
    near_walker = np.abs(moving[:, 1] + 24.0) < 0.4
    assert (near_car | near_walker).all() and near_car.any() and near_walker.any()
    # and no static point is labelled moving
    static = pts[label == 0]
    assert not (
        (np.abs(static[:, 1] + 15.0) < 0.8) & (static[:, 2] > 0.3) & (np.abs(static[:, 0]) > 12)
    ).any()


def test_actors_beside_the_route_and_bad_paths_files(drive, tmp_path):
    root, _, _ = drive
    out = tmp_path / "beside"
    record(
        str(root / "campus.xml"),
        str(root / "loop.txt"),
        "vlp-16",
        out,
        frames=10,
        actors=4,
        seed=6,
        progress=False,
        loop=True,
    )
    meta = load_sequence(out).meta
    assert meta["actors"] + len(meta["actors_left_out"]) == 4 and meta["actors"] >= 3
    bad = tmp_path / "bad.yaml"
    for text, words in [
        ("actors:\n  - {kind: bus, waypoints: [[0, 0], [1, 1]]}\n", "kind 'bus'"),
        ("actors:\n  - {kind: car, waypoints: [[0, 0]]}\n", "at least two"),
        ("actors:\n  - {kind: car, speed: -1, waypoints: [[0, 0], [5, 0]]}\n", "speed"),
        ("actors:\n  - {kind: car, waypoints: [[0, 0], [5, 0]], colour: red}\n", "colour"),
        ("actors:\n  - {kind: car, waypoints: [[-15, 0], [15, 0]]}\n", "steps"),  # through the hall
        ("actors:\n  - {kind: car, waypoints: [[-15.5, -32], [-15.5, -20]]}\n", "static geometry"),  # pole
        ("cars: []\n", "'actors'"),
    ]:
        bad.write_text(text)
        with pytest.raises(InputError, match=words) as err:
            record(
                str(root / "campus.xml"),
                str(root / "loop.txt"),
                "vlp-16",
                tmp_path / "x",
                frames=5,
                progress=False,
                loop=True,
                actor_paths=bad,
            )
        assert "bad.yaml" in str(err.value) and "\n" not in str(err.value)
        assert not (tmp_path / "x").exists()


VARIANTS = """<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="30 30 0.1"/>
    <body name="variant_1_fence" pos="10 0 1"><geom type="box" size="0.1 3 1"/>
      <body name="gate" pos="0 4 0"><geom type="box" size="0.1 1 1"/></body></body>
    <body name="variant_2_crates" pos="-10 0 1"><geom type="box" size="1 1 1"/></body>
    <body name="parked_v2_van" pos="0 10 1"><geom type="box" size="2.5 1 1"/></body>
    <geom name="kiosk" type="box" size="1 1 1.5" pos="0 -10 1.5"/>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("variant", [0, 1, 2])
def test_variant_bodies_are_shown_only_in_their_variant(tmp_path, variant):
    scene = tmp_path / "variants.xml"
    scene.write_text(VARIANTS)
    world = World(scene, variant=variant)
    origins = np.array([[0.0, 0.0, 1.0]] * 5)
    dirs = np.array([[1.0, 0, 0], [10.0, 4.0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    hits = world.caster.cast(origins, dirs, 50.0)
    seen = hits.hit & (hits.ranges < 12)
    # fence and its gate (a child body), crates, van, kiosk (no variant: always there)
    assert seen.tolist() == [variant == 1, variant == 1, variant == 2, variant == 2, True]
    # what the LiDAR does not see, the car does not hit and nobody sees in a render either
    hidden = world.hidden_geoms
    assert (world.model.geom_contype[hidden] == 0).all() and (world.model.geom_rgba[hidden, 3] == 0).all()


def test_a_variant_the_scene_does_not_have_is_one_line(tmp_path):
    scene = tmp_path / "variants.xml"
    scene.write_text(VARIANTS)
    with pytest.raises(InputError, match=r"no variant 3 \(it has \[1, 2\]\)"):
        World(scene, variant=3)
    bare = tmp_path / "bare.xml"
    bare.write_text('<mujoco><worldbody><geom type="plane" size="5 5 0.1"/></worldbody></mujoco>')
    with pytest.raises(InputError, match="variant_"):
        World(bare, variant=1)


@pytest.mark.parametrize(
    ("scene", "routes", "variant"),
    [
        ("campus.xml", ("campus_mapping.txt", "campus_test.txt"), 1),
        ("village.xml", ("village_route.txt", "village_test.txt"), 0),
    ],
)
def test_the_example_scenes_drive_their_routes(tmp_path, scene, routes, variant):
    """scenes/examples: a scene written as MJCF and a mesh world made by import-scene; their routes
    pass the checks and the car drives them with actors beside it."""
    from simbed.sim.world import scenes_dir

    ex = scenes_dir() / "examples"
    for k, route in enumerate(routes):
        out = tmp_path / f"run{k}"
        s = record(
            str(ex / scene),
            str(ex / route),
            "vlp-16",
            out,
            frames=15,
            actors=4 * k,
            variant=variant * k,
            seed=k,
            progress=False,
            loop=True,
        )
        assert s.frames == 15 and s.distance_driven_m > 1.5  # 1.5 s from standstill
        seq = load_sequence(out)
        assert len(seq.scan(14)) > 5000
