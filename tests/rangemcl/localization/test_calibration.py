"""Online odometry calibration: the scale and gyro-bias estimator against trajectories whose
truth is known, including standing still, reversing and turning on the spot; and, through the filter, a
3 % wheel scale error recovered in a synthetic corridor with cross walls."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.localization import LocalizerSettings, MotionSettings, ObservationSettings, build_localizer
from rangemcl.localization.factory import odometry_calibrator
from rangemcl.maps.meshmap import MeshMap
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster
from rangemcl.se2 import se2_between, se2_compose
from rangemcl.sensors import load_spec

HEIGHT = 1.73


def _drive(cal, truth, odo_scale, bias, dt, rng, noise_m=0.03, noise_rad=0.001):
    """Feed the calibrator the intervals of a true trajectory: raw odometry (translation x odo_scale,
    yaw + bias·dt) and estimates = truth + iid noise."""
    est = truth + rng.normal(0.0, 1.0, truth.shape) * [noise_m, noise_m, noise_rad]
    history = []
    for k in range(1, len(truth)):
        step = se2_between(truth[k - 1], truth[k])
        raw = np.array([step[0] * odo_scale, step[1] * odo_scale, step[2] + bias * dt])
        cal.observe(raw, dt, est[k - 1], est[k])
        history.append((cal.scale, cal.gyro_bias))
    return np.array(history)


def _path(rng, n, speed=1.0, turn=0.05):
    pose = np.zeros(3)
    out = [pose]
    for _ in range(n - 1):
        pose = se2_compose(pose, np.array([speed, 0.0, rng.normal(0.0, turn)]))
        out.append(pose)
    return np.array(out)


@pytest.mark.parametrize("seed", range(4))
def test_scale_and_bias_converge_on_random_drives(seed):
    rng = np.random.default_rng(seed)
    odo_scale = rng.uniform(0.95, 1.05)  # the wheel reads this times the true distance
    bias = math.radians(rng.uniform(-1.0, 1.0))
    cal = odometry_calibrator(MotionSettings())
    truth = _path(rng, 250, speed=0.8)  # 200 m, an update every 0.8 m (8 m/s)
    hist = _drive(cal, truth, odo_scale, bias, 0.1, rng)
    assert cal.scale == pytest.approx(1.0 / odo_scale, rel=0.003)
    assert math.degrees(cal.gyro_bias) == pytest.approx(math.degrees(bias), abs=0.05)
    assert cal.observed == 249 and cal.rejected == 0
    # it had settled well before the end (within 0.3 % over the last 50 m)
    assert np.all(np.abs(hist[-60:, 0] * odo_scale - 1.0) < 0.003)


def test_standing_still_measures_the_bias_and_leaves_the_scale():
    cal = odometry_calibrator(MotionSettings(odometry_scale=1.02))
    bias = math.radians(0.4)
    for _ in range(100):  # 100 intervals of 1 s without moving; the gyro turns, the estimate does not
        cal.observe(np.array([0.0, 0.0, bias * 1.0]), 1.0, np.zeros(3), np.zeros(3))
    assert cal.scale == 1.02
    assert math.degrees(cal.gyro_bias) == pytest.approx(0.4, abs=0.02)


def test_reversing_and_turning_on_the_spot():
    rng = np.random.default_rng(3)
    cal = odometry_calibrator(MotionSettings())
    pose = np.zeros(3)
    for k in range(900):  # 300 m backwards; the configured scale's weight is forgotten
        spot = k % 3 == 2  # turn on the spot (no translation), else reverse
        step = np.array([0.0, 0.0, 0.2]) if spot else np.array([-0.5, 0.0, rng.normal(0.0, 0.02)])
        nxt = se2_compose(pose, step)
        raw = np.array([step[0] / 1.03, step[1] / 1.03, step[2]])
        cal.observe(raw, 0.1, pose, nxt)
        pose = nxt
    assert cal.scale == pytest.approx(1.03, rel=5e-4)  # (the start value, 1.0, keeps a trace)
    assert abs(math.degrees(cal.gyro_bias)) < 1e-6


def test_a_jump_of_the_estimate_is_left_out():
    cal = odometry_calibrator(MotionSettings())
    assert not cal.observe(np.array([1.0, 0.0, 0.0]), 0.1, np.zeros(3), np.array([3.0, 0.0, 0.0]))
    assert cal.rejected == 1 and cal.scale == 1.0
    cal.reset()
    assert cal.rejected == 0


def test_correct_applies_scale_and_bias():
    cal = odometry_calibrator(MotionSettings(odometry_scale=1.05, gyro_bias_deg_s=math.degrees(0.01)))
    assert cal.correct([1.0, 2.0, 0.5], 0.1) == pytest.approx([1.05, 2.1, 0.499])
    assert cal.correct([1.0, 2.0, 0.5], None) == pytest.approx([1.05, 2.1, 0.5])


# ---------------------------------------------------------------------------------------------- filter level


@pytest.fixture(scope="module")
def corridor():
    """A 200 m corridor along x between two long walls (they constrain y and yaw, never x), with cross
    walls (buttresses 1 m deep) every 9 m on alternating sides: the only evidence along the corridor."""
    parts = [
        meshgen.grid_patch((-20.0, -15.0, 0.0), (240.0, 0, 0), (0, 30.0, 0), 60, 8),
        meshgen.box((240.0, 0.5, 4.0), (100.0, -6.0, 2.0), cell_m=4.0),
        meshgen.box((240.0, 0.5, 4.0), (100.0, 6.0, 2.0), cell_m=4.0),
    ]
    for i, x in enumerate(np.arange(-10.0, 215.0, 9.0)):
        side = 1.0 if i % 2 else -1.0
        parts.append(meshgen.box((0.4, 1.0, 4.0), (x, side * 5.3, 2.0), cell_m=1.0))
    v, f = meshgen.merge(parts)
    caster = RayCaster(threads=2)
    caster.add_mesh(v, f, name="corridor")
    m = MeshMap.from_mesh(v, f, tile_size_m=50.0, meta={"sensor_height_m": HEIGHT})
    return caster, m


def _scan(caster, geo, pose):
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    d = geo.directions.reshape(-1, 3)
    hits = caster.cast(np.array([x, y, HEIGHT]), d @ R.T, 40.0)
    return (d[hits.hit] * hits.ranges[hits.hit, None]).astype(np.float32)


def _track(corridor, calibrate: bool, mode: str = "estimator", refine: bool | None = None, noise=None):
    caster, m = corridor
    geo = RangeImageGeometry.for_spec(load_spec("vlp-16").with_columns(720))
    s = LocalizerSettings()
    s.observation = ObservationSettings(rays=300, max_range_m=40.0)
    s.motion.calibrate_scale = s.motion.calibrate_gyro_bias = s.refine.enabled = calibrate
    if refine is not None:
        s.refine.enabled = refine
    if noise is not None:
        s.motion.trans_per_trans = noise
    s.refine.min_hit_height_m = None  # nothing changes between this map and its scans: every hit counts
    s.motion.calibration = mode
    loc = build_localizer(m, s, seed=2, caster=caster)
    n = 220
    path = np.column_stack([np.arange(n) * 0.8, np.zeros(n), np.zeros(n)])  # 8 m/s, 175 m
    loc.start_at(path[0])
    err = []
    for k in range(n):
        delta = se2_between(path[k - 1], path[k]) * [0.97, 0.97, 1.0] if k else np.zeros(3)
        info = loc.step(delta, _scan(caster, geo, path[k]), dt_s=0.1 if k else None)
        err.append(info.estimate[0] - path[k, 0])
    return loc, np.array(err)


def test_a_three_percent_wheel_error_is_calibrated_away_in_a_corridor(corridor):
    loc, along = _track(corridor, calibrate=True)
    assert loc.calibrator.scale == pytest.approx(1 / 0.97, rel=0.003)
    assert abs(math.degrees(loc.calibrator.gyro_bias)) < 0.05
    assert np.abs(along[-50:]).max() < 0.05
    assert loc.refinements > 100
    # without calibration and refinement the same drive lags: the odometry's error sets the accuracy
    loc0, along0 = _track(corridor, calibrate=False)
    assert loc0.calibrator.scale == 1.0 and loc0.refinements == 0
    assert np.abs(along0[-50:]).mean() > 3 * np.abs(along[-50:]).mean()


def test_scale_as_particle_state_is_learned_without_the_refinement(corridor):
    """The alternative estimator (``motion.calibration: particles``): each particle carries its own scale
    and the weighting selects. With motion noise below the wheel's error (1 % of the distance) and no
    refinement it learns the 3 % error. (With the refinement, which moves the whole cloud onto the scan at
    every update, the selection rests on what the refinement leaves of each particle's offset: in this
    corridor it ended 0.54 % off with version 0.17's observation model and 0.23 % off with 0.18's, so
    nothing is asserted of it.)"""
    loc, _ = _track(corridor, True, mode="particles", refine=False, noise=0.01)
    assert loc.calibrator.scale == pytest.approx(1 / 0.97, rel=0.005)
