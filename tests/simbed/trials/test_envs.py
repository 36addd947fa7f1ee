"""The gymnasium environments: gymnasium's own checker, same-seed rollouts, vector environments, the
reward and info against the truth, kidnapping, Drive-v0's controls, and rangemcl's localizer as the
agent (against the scene's true static mesh as its map)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import simbed  # noqa: F401  (registers the environments)
from rangemcl.localization import LocalizerSettings
from rangemcl.maps.meshmap import MeshMap
from simbed.sim.world import World
from simbed.trials.agents import MCLAgent, run_episode

SMALL = {"sensor": "vlp-16", "columns": 256}
IDS = ["simbed/LocalizationTrial-v0", "simbed/Drive-v0"]


def action_for(env_id, info, k):
    if env_id.startswith("simbed/Drive"):
        return np.array([4.0, 0.05 * np.sin(k)], np.float32)
    return (info["true_pose"] + [0.5, 0.0, 0.0]).astype(np.float32)


@pytest.mark.parametrize("env_id", IDS)
def test_registered_envs_pass_gymnasiums_checker(env_id):
    env = gym.make(env_id, **SMALL, actors=2)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.parametrize("env_id", IDS)
def test_same_seed_same_rollout(env_id):
    def rollout(seed):
        env = gym.make(env_id, **SMALL, actors=3)
        obs, info = env.reset(seed=seed)
        frames = [obs["range_image"].copy()]
        rewards = []
        for k in range(4):
            obs, r, _, _, info = env.step(action_for(env_id, info, k))
            frames.append(obs["range_image"].copy())
            rewards.append(r)
        return np.array(frames), np.array(rewards), info["true_pose"]

    a, b, c = rollout(5), rollout(5), rollout(6)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[2], b[2])
    assert not np.array_equal(a[0], c[0])  # another seed: other noise, other actors


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_vector_env_steps(mode):
    envs = gym.make_vec("simbed/LocalizationTrial-v0", num_envs=2, vectorization_mode=mode, **SMALL)
    obs, info = envs.reset(seed=[1, 2])
    assert obs["range_image"].shape == (2, 16, 256)
    for _ in range(2):
        obs, reward, _, _, info = envs.step(info["true_pose"].astype(np.float32))
    assert reward.shape == (2,) and np.all(reward > -0.1)  # the true pose was the action
    envs.close()


def test_reward_and_info_measure_the_estimate_against_the_truth():
    env = gym.make("simbed/LocalizationTrial-v0", **SMALL, max_episode_steps=3)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    truth = info["true_pose"]
    obs, r, term, trunc, info = env.step((truth + np.array([3.0, 4.0, 0.0])).astype(np.float32))
    assert info["position_error_m"] == pytest.approx(5.0, abs=1e-4) and r == pytest.approx(-5.0, abs=1e-3)
    truth = info["true_pose"]
    obs, r, term, trunc, info = env.step((truth + np.array([0.0, 0.0, np.radians(10)])).astype(np.float32))
    assert info["yaw_error_deg"] == pytest.approx(10.0, abs=1e-3)
    assert r == pytest.approx(-0.05 * 10.0, abs=1e-3)
    obs, r, term, trunc, info = env.step(info["true_pose"].astype(np.float32))
    assert trunc and not term  # max_episode_steps
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(seed=0, options={"kidnap": 3})


def test_kidnapping_moves_the_car_but_not_its_odometry():
    env = gym.make("simbed/LocalizationTrial-v0", **SMALL)
    obs, info = env.reset(seed=0, options={"start_frame": 20, "kidnap_at": 3, "kidnap_ahead_m": 80.0})
    poses, odo = [info["true_pose"]], []
    for _ in range(5):
        obs, _, _, _, info = env.step(info["true_pose"].astype(np.float32))
        poses.append(info["true_pose"])
        odo.append(np.hypot(*obs["odometry"][:2]))
    jumps = np.hypot(*np.diff(np.array(poses)[:, :2], axis=0).T)
    assert jumps[2] > 40.0 and info["kidnapped"]  # teleported at the third step
    assert max(odo) < 1.5  # the odometry saw an ordinary drive
    assert np.delete(jumps, 2).max() < 1.5


def test_drive_env_follows_speed_and_steering():
    env = gym.make("simbed/Drive-v0", **SMALL)
    _, info = env.reset(seed=0)
    yaw0 = info["true_pose"][2]
    total = 0.0
    for _ in range(25):
        _, r, _, _, info = env.step(np.array([6.0, 0.0], np.float32))
        total += r
    assert info["speed_mps"] > 3.0 and total > 3.0
    for _ in range(15):
        *_, info = env.step(np.array([4.0, 0.4], np.float32))
    assert abs(((info["true_pose"][2] - yaw0 + np.pi) % (2 * np.pi)) - np.pi) > 0.3  # it turned


def test_rangemcl_agent_tracks_the_car_in_a_trial():
    world = World("town_small", variant=0)
    truth_map = MeshMap.from_mesh(*world.static_triangles)
    env = gym.make(
        "simbed/LocalizationTrial-v0", sensor="vlp-16", columns=512, actors=3, max_episode_steps=40
    )
    s = LocalizerSettings()
    s.observation.rays = 300
    agent = MCLAgent.for_env(env, truth_map, settings=s, seed=0, threads=2)
    result = run_episode(env, agent, seed=0, tracking=True)
    assert result["steps"] == 40 and result["converged"].all()
    assert np.sqrt(np.mean(result["position_error_m"] ** 2)) < 0.5
    assert np.sqrt(np.mean(result["yaw_error_deg"] ** 2)) < 1.0


def test_the_realistic_sensor_observes_intensity_where_it_returns():
    env = gym.make("simbed/LocalizationTrial-v0", **SMALL, sensor_model="realistic")
    obs, _ = env.reset(seed=2)
    assert env.observation_space.contains(obs)
    ranges, intensity = obs["range_image"], obs["intensity_image"]
    assert np.all(intensity[ranges == 0] == 0)
    assert (intensity[ranges > 0] > 0).mean() > 0.9  # a few returns are too weak to read
    ideal = gym.make("simbed/LocalizationTrial-v0", **SMALL)
    obs_ideal, _ = ideal.reset(seed=2)
    assert not obs_ideal["intensity_image"].any()
    assert (ranges > 0).sum() < (obs_ideal["range_image"] > 0).sum()  # weak returns lost
