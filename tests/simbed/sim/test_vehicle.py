"""scenes/car.xml: the car MuJoCo simulates rests, drives, steers, brakes and pitches like a car."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

CAR_XML = Path(__file__).resolve().parents[3] / "scenes" / "car.xml"
WHEELBASE = 2.7
DT = 0.002


def _flat_world() -> tuple[mujoco.MjModel, mujoco.MjData]:
    xml = f"""<mujoco model="flat">
      <include file="{CAR_XML}"/>
      <option timestep="{DT}"/>
      <worldbody><geom name="floor" type="plane" size="300 300 0.1"/></worldbody>
    </mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    return m, mujoco.MjData(m)


def _act(m: mujoco.MjModel, name: str) -> int:
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, name)
    assert i >= 0, name
    return i


def _rpy(q: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (rad) of a MuJoCo quaternion (w, x, y, z); pitch > 0 is nose down."""
    w, x, y, z = q
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.array([roll, pitch, yaw])


def _forward_speed(d: mujoco.MjData) -> float:
    yaw = _rpy(d.qpos[3:7])[2]
    return float(d.qvel[0] * np.cos(yaw) + d.qvel[1] * np.sin(yaw))


def _run(m, d, seconds: float, control) -> None:
    for _ in range(round(seconds / DT)):
        control(d)
        mujoco.mj_step(m, d)
        assert np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))


@pytest.fixture
def world():
    return _flat_world()


def test_names_dimensions_and_conventions(world):
    m, _ = world
    assert m.joint("car_root").type == mujoco.mjtJoint.mjJNT_FREE
    car = m.body("car").id
    assert m.jnt_bodyid[m.joint("car_root").id] == car
    assert m.body_subtreemass[car] == pytest.approx(1500.0, rel=0.05)
    for corner in ("fl", "fr", "rl", "rr"):
        j = m.joint(f"susp_{corner}")
        assert j.type == mujoco.mjtJoint.mjJNT_SLIDE and m.jnt_limited[j.id]
        assert m.jnt_stiffness[j.id] > 0 and m.dof_damping[m.jnt_dofadr[j.id]] > 0
        assert m.joint(f"wheel_{corner}").type == mujoco.mjtJoint.mjJNT_HINGE
        assert m.geom(f"wheel_{corner}").group == 2
    for side in ("fl", "fr"):
        j = m.joint(f"steer_{side}")
        np.testing.assert_allclose(m.jnt_range[j.id], [-0.6, 0.6], atol=1e-4)  # radians once compiled
        np.testing.assert_allclose(m.actuator_ctrlrange[_act(m, f"steer_{side}")], [-0.6, 0.6])
    for side in ("rl", "rr"):
        np.testing.assert_allclose(m.actuator_ctrlrange[_act(m, f"drive_{side}")], [-1500, 1500])
    assert [m.actuator(i).name for i in range(m.nu)] == ["steer_fl", "steer_fr", "drive_rl", "drive_rr"]
    assert m.geom("chassis").group == 1
    np.testing.assert_allclose(m.geom("chassis").size * 2, [4.5, 1.8, 1.2])
    np.testing.assert_allclose(m.site("lidar_mount").pos, [0, 0, 1.73])
    mujoco.mj_forward(m, mujoco.MjData(m))
    # wheel axles at z = wheel radius in the base frame; wheelbase and track
    rl, rr, fl = (m.body(f"susp_{c}").pos for c in ("rl", "rr", "fl"))
    np.testing.assert_allclose(rl, [0, 0.8, 0.33])
    assert fl[0] - rl[0] == pytest.approx(WHEELBASE) and rl[1] - rr[1] == pytest.approx(1.6)
    assert m.geom("wheel_rl").size[0] == pytest.approx(0.33)


def test_rests_level_at_its_nominal_height(world):
    m, d = world
    _run(m, d, 3.0, lambda d: None)
    assert abs(d.qpos[2]) < 0.03
    roll, pitch, _ = _rpy(d.qpos[3:7])
    assert abs(np.degrees(roll)) < 1.0 and abs(np.degrees(pitch)) < 1.0
    assert np.linalg.norm(d.qvel[:3]) < 0.01


def test_drive_torque_accelerates_forward_and_pitches_nose_up(world):
    m, d = world
    _run(m, d, 1.0, lambda d: None)
    pitches, t_5 = [], None

    def drive(d):
        d.ctrl[_act(m, "drive_rl")] = d.ctrl[_act(m, "drive_rr")] = 800.0

    for k in range(round(8.0 / DT)):
        drive(d)
        mujoco.mj_step(m, d)
        pitches.append(_rpy(d.qpos[3:7])[1])
        if t_5 is None and _forward_speed(d) > 5.0:
            t_5 = k * DT
    assert t_5 is not None and t_5 < 8.0
    assert d.qpos[0] > 10.0 and abs(d.qpos[1]) < 0.5  # straight ahead along +x
    nose_up = -np.degrees(np.array(pitches[100:]))  # pitch > 0 is nose down
    assert 0.05 < np.median(nose_up) < 3.0 and nose_up.max() < 3.0  # the suspension squats at the rear


def test_steering_tracks_quickly_and_turns_left_like_a_bicycle(world):
    m, d = world

    def cruise(steer):
        def control(d):
            tq = np.clip(600.0 * (4.0 - _forward_speed(d)), -1500, 1500)
            d.ctrl[_act(m, "drive_rl")] = d.ctrl[_act(m, "drive_rr")] = tq
            d.ctrl[_act(m, "steer_fl")] = d.ctrl[_act(m, "steer_fr")] = steer

        return control

    _run(m, d, 3.0, cruise(0.0))
    qadr = m.jnt_qposadr[m.joint("steer_fl").id]
    _run(m, d, 0.1, cruise(0.3))
    assert d.qpos[qadr] == pytest.approx(0.3, abs=0.03)  # tracked within 0.1 s
    _run(m, d, 2.0, cruise(0.3))
    yaw0 = _rpy(d.qpos[3:7])[2]
    xy = []
    for _ in range(round(6.0 / DT)):
        cruise(0.3)(d)
        mujoco.mj_step(m, d)
        xy.append(d.qpos[:2].copy())
    dyaw = np.angle(np.exp(1j * (_rpy(d.qpos[3:7])[2] - yaw0)))
    assert dyaw > 0.5  # turned left (yaw increased); ~4 m/s for 6 s on a ~9 m circle
    xy = np.array(xy)
    # least-squares circle through the rear-axle track
    A = np.c_[2 * xy, np.ones(len(xy))]
    cx, cy, c = np.linalg.lstsq(A, (xy**2).sum(1), rcond=None)[0]
    radius = np.sqrt(c + cx**2 + cy**2)
    bicycle = WHEELBASE / np.tan(0.3)
    assert abs(radius - bicycle) < 0.3 * bicycle, (radius, bicycle)


def test_negative_torque_brakes(world):
    m, d = world

    def drive(tq):
        def control(d):
            d.ctrl[_act(m, "drive_rl")] = d.ctrl[_act(m, "drive_rr")] = tq

        return control

    _run(m, d, 4.0, drive(800.0))
    v0 = _forward_speed(d)
    assert v0 > 5.0
    _run(m, d, 1.0, drive(-1200.0))
    v1 = _forward_speed(d)
    assert v1 < v0 - 2.0
    _run(m, d, 3.0, lambda d: None)  # rolling without torque: slows, never speeds up
    assert _forward_speed(d) <= v1 + 1e-6


def test_twenty_seconds_of_mixed_driving_stay_finite_and_upright(world):
    m, d = world
    rng = np.random.default_rng(0)
    plan = rng.uniform([-0.5, -1000], [0.5, 1200], size=(10, 2))

    def control(d):
        steer, tq = plan[min(int(d.time / 2.0), 9)]
        if _forward_speed(d) > 12.0:
            tq = min(tq, 0.0)
        d.ctrl[_act(m, "steer_fl")] = d.ctrl[_act(m, "steer_fr")] = steer
        d.ctrl[_act(m, "drive_rl")] = d.ctrl[_act(m, "drive_rr")] = tq

    _run(m, d, 20.0, control)
    roll, pitch, _ = _rpy(d.qpos[3:7])
    assert abs(roll) < 0.2 and abs(pitch) < 0.2
    assert -0.1 < d.qpos[2] < 0.1
    assert np.abs(d.qvel).max() < 200.0


def test_wheel_torque_never_spins_a_wheel_backwards_or_beyond_the_car():
    from simbed.sim.vehicle import MAX_WHEEL_NM, wheel_torque

    rng = np.random.default_rng(3)
    for tq, rate, speed in rng.uniform([-3000, -5, 0], [3000, 40, 12], size=(500, 3)):
        out = wheel_torque(tq, rate, speed, 0.33)
        assert abs(out) <= MAX_WHEEL_NM
        assert np.sign(out) in (0, np.sign(tq))  # brakes brake, drives drive
        if tq < 0 and rate <= 0:
            assert out == 0.0  # a wheel at rest or turning backwards gets no braking torque
        if tq > 0 and rate * 0.33 > 1.1 * speed + 0.3:
            assert out == 0.0  # traction control
    assert wheel_torque(-5000, 30.0, 10.0, 0.33) == -MAX_WHEEL_NM
    assert wheel_torque(5000, 10.0, 3.3, 0.33) == MAX_WHEEL_NM
