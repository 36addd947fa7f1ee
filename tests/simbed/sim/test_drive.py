"""The simulated LiDAR and drives against independent references: MuJoCo's own ray casts, actor poses,
the skew predicted by the sweep timing, reproducibility, and what a recording loads back as."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import mujoco
import numpy as np
import pytest

from rangemcl.datasets.kitti import load_sequence
from rangemcl.errors import InputError
from rangemcl.sensors import load_spec
from simbed.record import checkpoint_path, record, resumable
from simbed.scenes.routes import Route, make_route
from simbed.sim.actors import ACTOR_KINDS
from simbed.sim.drive import Drive
from simbed.sim.lidar import LABEL_ACTOR
from simbed.sim.world import World, scenes_dir

WALL_X = 40.0


@pytest.fixture(scope="module")
def wall_scene(tmp_path_factory) -> Path:
    """A flat plane, the car, and a wall across the road ahead at x = WALL_X."""
    d = tmp_path_factory.mktemp("wall")
    shutil.copy(scenes_dir() / "car.xml", d / "car.xml")
    xml = f"""<mujoco model="wall">
  <option timestep="0.002"/>
  <include file="car.xml"/>
  <worldbody>
    <geom name="ground" type="plane" size="200 200 0.1"/>
    <geom name="wall" type="box" pos="{WALL_X + 0.5} 0 5" size="0.5 30 5"/>
  </worldbody>
</mujoco>"""
    path = d / "wall.xml"
    path.write_text(xml)
    return path


def straight_route(length_m: float = 200.0) -> Route:
    x = np.arange(0.0, length_m, 0.5)
    return Route("straight", np.column_stack([x, np.zeros_like(x)]))


def test_lidar_ranges_equal_mj_ray_in_a_town():
    """Every sampled pixel's range equals MuJoCo's own mj_ray along the same ray (car standing still)."""
    rng = np.random.default_rng(0)
    world = World("town_small", n_actors=4, rng=rng)
    route = make_route("test", world.graph, world.town.lane_width_m, world.town.road_width_m)
    spec = load_spec("vlp-16")
    drive = Drive(world, route, spec, rng, skew=False, settle_s=0.5)
    frame = drive.next_frame()
    world.sync_caster()
    T = frame.T_world_sensor
    geo = drive.lidar.geometry
    h, w = geo.shape
    pick = rng.choice(h * w, 600, replace=False)
    rows, cols = np.unravel_index(pick, (h, w))
    origins = geo.origins[rows, cols] @ T[:3, :3].T + T[:3, 3]
    dirs = geo.directions[rows, cols] @ T[:3, :3].T
    ours = world.caster.cast(origins, dirs, spec.max_range_m).ranges
    mujoco.mj_forward(world.model, world.data)
    group = np.array([1, 0, 0, 1, 0, 0], np.uint8)  # static scene (0) and actors (3), not the car (1, 2)
    theirs = np.empty(len(pick))
    for k in range(len(pick)):
        d = mujoco.mj_ray(world.model, world.data, origins[k], dirs[k], group, 1, -1, np.zeros(1, np.int32))
        theirs[k] = np.inf if d < 0 or d > spec.max_range_m else d
    both = np.isfinite(ours) & np.isfinite(theirs)
    assert (np.isfinite(ours) == np.isfinite(theirs)).mean() > 0.99  # silhouettes of curved shapes may differ
    diff = np.abs(ours[both] - theirs[both])
    # flat geometry agrees to float precision; tree crowns, poles and wheels are tessellated (sagitta)
    assert np.median(diff) < 1e-3 and np.quantile(diff, 0.95) < 0.02
    # the sweep's own image holds the same ranges (noise-free check: within 4 sigma of the noise)
    measured = frame.sweep.ranges[rows, cols]
    ok = (measured > 0) & np.isfinite(ours)
    assert np.abs(measured[ok] - ours[ok]).max() < 4 * spec.range_noise_m + 0.02


def test_car_never_sees_itself():
    world = World("town_small")
    spec = load_spec("os1-64")
    route = make_route("test", world.graph, world.town.lane_width_m, world.town.road_width_m)
    frame = Drive(world, route, spec, np.random.default_rng(1), skew=False, settle_s=0.3).next_frame()
    base = frame.sweep.points @ spec.T_base_sensor[:3, :3].T + spec.T_base_sensor[:3, 3]  # base frame
    in_car = (base[:, 0] > -1.0) & (base[:, 0] < 3.8) & (np.abs(base[:, 1]) < 1.0) & (base[:, 2] > 0.25)
    assert not in_car.any()
    assert len(frame.sweep.points) > 20_000


def test_moving_actors_appear_where_mujoco_puts_them():
    rng = np.random.default_rng(3)
    world = World("town_small", n_actors=12, rng=rng)
    route = make_route("test", world.graph, world.town.lane_width_m, world.town.road_width_m)
    drive = Drive(world, route, load_spec("os1-64"), rng, skew=False, settle_s=0.2)
    seen = 0
    for _ in range(6):
        frame = drive.next_frame()
        pts = frame.sweep.points[frame.sweep.label == LABEL_ACTOR]
        if not len(pts):
            continue
        T = frame.T_world_sensor
        world_pts = pts @ T[:3, :3].T + T[:3, 3]
        # distance of each actor point to the nearest actor box, as MuJoCo placed the bodies at the end
        best = np.full(len(world_pts), np.inf)
        for a in world.actors:
            R = world.data.xmat[a.body_id].reshape(3, 3)
            local = (world_pts - world.data.xpos[a.body_id]) @ R
            half = np.array(ACTOR_KINDS[a.kind]["half"])
            outside = np.maximum(np.abs(local) - half, 0.0)
            best = np.minimum(best, np.linalg.norm(outside, axis=1))
        # without skew the whole sweep is cast at its end, where MuJoCo has the bodies now
        assert best.max() < 0.15  # range noise (3 cm) and the pedestrians' tessellated capsules
        seen += len(pts)
    assert seen > 50  # the test actually saw actors


@pytest.mark.parametrize("skew", [True, False])
def test_skew_follows_the_sweep_timing(wall_scene, skew):
    """Driving at the wall: a point fired dt before the sweep's end appears v·dt farther than the wall."""
    rng = np.random.default_rng(2)
    world = World(wall_scene)
    spec = load_spec("os1-64")
    spec = dataclasses.replace(spec, range_noise_m=0.0)  # exact ranges for this check
    drive = Drive(world, straight_route(), spec, rng, skew=skew, cruise_mps=10.0, settle_s=0.3)
    frames = [drive.next_frame() for _ in range(35)]  # reach speed
    prev, frame = frames[-2], frames[-1]
    v = np.linalg.norm(frame.T_world_sensor[:3, 3] - prev.T_world_sensor[:3, 3]) / 0.1
    assert v > 5.0
    s = frame.sweep
    T = frame.T_world_sensor
    world_pts = s.points @ T[:3, :3].T + T[:3, 3]
    on_wall = (
        (np.abs(world_pts[:, 0] - WALL_X) < 3.0) & (world_pts[:, 2] > 1.0) & (np.abs(world_pts[:, 1]) < 5)
    )
    assert on_wall.sum() > 200
    apparent = world_pts[on_wall, 0]
    expected = WALL_X + (v * -s.time_s[on_wall] if skew else 0.0)
    assert np.abs(apparent - expected).max() < 0.05
    if skew:  # and the skew is real: early columns are off by decimetres
        assert (-s.time_s[on_wall]).min() > 0.03 and (apparent - WALL_X).mean() > 0.3


def test_same_seed_same_recording(tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    kw = {"frames": 3, "actors": 3, "progress": False}
    record("town_small", "test", "vlp-16", a, seed=5, **kw)
    record("town_small", "test", "vlp-16", b, seed=5, **kw)
    record("town_small", "test", "vlp-16", c, seed=6, **kw)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) >= 3 * 2 + 6
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    assert (a / "velodyne/000002.bin").read_bytes() != (c / "velodyne/000002.bin").read_bytes()


def test_recording_loads_back_with_exact_poses(tmp_path, monkeypatch):
    frames = []
    original = Drive.next_frame

    def spy(self):
        f = original(self)
        frames.append(f)
        return f

    monkeypatch.setattr(Drive, "next_frame", spy)
    out = tmp_path / "seq"
    summary = record("town_small", "mapping", "hdl-32e", out, frames=4, seed=1, progress=False)
    seq = load_sequence(out, require_poses=True)
    assert len(seq) == summary.frames == 4
    truth = np.stack([f.T_world_sensor for f in frames])
    np.testing.assert_allclose(seq.poses, truth, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(seq.odometry, np.stack([f.T_odom_sensor for f in frames]), atol=1e-8)
    np.testing.assert_allclose(seq.times, [f.time_s for f in frames], atol=1e-9)
    for i, f in enumerate(frames):
        assert np.array_equal(seq.scan(i), f.sweep.points)
        meta = seq.point_meta(i)
        assert np.array_equal(meta["ring"], f.sweep.ring) and np.array_equal(meta["label"], f.sweep.label)
    assert seq.meta["sensor"]["name"] == "hdl-32e" and seq.meta["complete"] is True


def test_odometry_drifts_but_tracks(tmp_path):
    """Odometry follows the true motion closely over a short drive and is not the truth."""
    out = tmp_path / "seq"
    record("town_small", "mapping", "vlp-16", out, frames=40, seed=4, progress=False)
    seq = load_sequence(out)
    rel_true = np.linalg.inv(seq.poses[0]) @ seq.poses[-1]
    rel_odom = np.linalg.inv(seq.odometry[0]) @ seq.odometry[-1]
    dist = np.linalg.norm(rel_true[:2, 3])
    assert dist > 15.0
    err = np.linalg.norm(rel_true[:2, 3] - rel_odom[:2, 3])
    assert 1e-4 < err < 0.05 * dist
    # frame by frame too, from the standing start on: no wheelspin or locked wheels fool the odometry
    step_true = np.linalg.norm(np.diff(seq.poses[:, :2, 3], axis=0), axis=1)
    step_odom = np.linalg.norm(np.diff(seq.odometry[:, :2, 3], axis=0), axis=1)
    assert np.abs(step_true - step_odom).max() < 0.05
    # the drive's drawn wheel scale is in meta.yaml, and it is what the odometry's distance shows
    drawn = seq.meta["odometry"]["wheel_scale"]
    assert drawn != 1.0 and seq.meta["odometry"]["spreads_1sigma"]["wheel_scale"] == 0.01
    assert abs(step_odom.sum() / step_true.sum() - drawn) < 0.004
    roll_pitch = seq.imu_roll_pitch
    assert np.abs(roll_pitch).max() < np.deg2rad(5)


def _stop_after(monkeypatch, n: int) -> None:
    """Make the n-th next frame of any drive raise KeyboardInterrupt (an interrupted recording)."""
    original, calls = Drive.next_frame, [0]

    def stopping(self):
        calls[0] += 1
        if calls[0] == n:
            raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(Drive, "next_frame", stopping)


@pytest.mark.parametrize("sensor_model", ["ideal", "realistic"])
def test_a_resumed_recording_gives_the_same_bytes(tmp_path, monkeypatch, sensor_model):
    """A recording interrupted after its checkpoint and resumed equals one recorded in one go, to the byte:
    scans, per-point arrays, poses, odometry, IMU, times, meta (the physics, the random generator, the
    controller, the odometry and the LiDAR's state all come back), with moving actors and, for the
    realistic sensor, weather clutter drawing from the generator; the checkpoint is gone at the end."""
    kw = {"frames": 7, "actors": 3, "seed": 5, "progress": False, "checkpoint_every": 3}
    if sensor_model == "realistic":
        kw.update(sensor_model="realistic", weather="rain:20")
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    record("town_small", "test", "vlp-16", whole, **kw)
    with monkeypatch.context() as m:
        _stop_after(m, 6)  # frames 0-4 written, the checkpoint holds 3
        with pytest.raises(KeyboardInterrupt):
            record("town_small", "test", "vlp-16", cut, **kw)
    assert checkpoint_path(cut).is_file() and len(list((cut / "velodyne").iterdir())) == 5
    assert "complete: false" in (cut / "meta.yaml").read_text()
    assert resumable(cut) and not resumable(whole)  # what the demo and the suites ask before recording
    summary = record("town_small", "test", "vlp-16", cut, resume=True, **kw)
    assert summary.frames == 7 and not checkpoint_path(cut).exists() and not resumable(cut)
    files = sorted(p.relative_to(whole) for p in whole.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(cut) for p in cut.rglob("*") if p.is_file())
    assert len(files) >= 7 * 2 + 6
    for f in files:
        assert (whole / f).read_bytes() == (cut / f).read_bytes(), f
    assert summary.distance_driven_m == pytest.approx(record_distance(whole))


def record_distance(seq_dir) -> float:
    p = load_sequence(seq_dir).poses[:, :2, 3]
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def test_a_resume_that_cannot_continue_is_one_clear_line(tmp_path, monkeypatch):
    """Resuming with other arguments, without a checkpoint, or a finished recording: one InputError naming
    the file and the problem, and nothing written."""
    kw = {"frames": 5, "seed": 5, "progress": False, "checkpoint_every": 2}
    out = tmp_path / "seq"
    with monkeypatch.context() as m:
        _stop_after(m, 4)
        with pytest.raises(KeyboardInterrupt):
            record("town_small", "test", "vlp-16", out, **kw)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(InputError, match=r"other arguments \(seed: 5\)"):
        record("town_small", "test", "vlp-16", out, resume=True, **{**kw, "seed": 6})
    with pytest.raises(InputError, match="holds 2 frames already"):
        record("town_small", "test", "vlp-16", out, resume=True, **{**kw, "frames": 2})
    assert before == {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    fresh = tmp_path / "fresh"
    with pytest.raises(InputError, match="no checkpoint to resume from"):
        record("town_small", "test", "vlp-16", fresh, resume=True, **kw)
    record("town_small", "test", "vlp-16", out, resume=True, **kw)
    with pytest.raises(InputError, match="the recording is complete"):
        record("town_small", "test", "vlp-16", out, resume=True, **kw)
    checkpoint_path(out).write_bytes(b"garbage")
    (out / "meta.yaml").write_text(
        (out / "meta.yaml").read_text().replace("complete: true", "complete: false")
    )
    with pytest.raises(InputError, match="unreadable checkpoint"):
        record("town_small", "test", "vlp-16", out, resume=True, **kw)
