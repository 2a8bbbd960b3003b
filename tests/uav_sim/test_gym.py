"""The Gymnasium interface to the simulator: the checker's rules, seeding, the paper's reward, and vector envs."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import uav_sim.gym  # noqa: F401  (registers the environment)
from uav_sim.gym import ENV_ID


def test_the_environment_passes_gymnasiums_checker():
    env = gymnasium.make(ENV_ID, world="complex")
    try:
        check_env(env.unwrapped, skip_render_check=False)
        assert env.observation_space.shape == (5, 64, 64) and env.action_space.n == 4
    finally:
        env.close()


def test_the_same_seed_gives_the_same_first_observations_and_another_seed_others():
    def first(seed, steps=5):
        env = gymnasium.make(ENV_ID, world="turbulent")  # weather and start heading are seeded
        try:
            obs = [env.reset(seed=seed)[0]]
            obs += [env.step(k % 4)[0] for k in range(steps)]
            return np.stack(obs)
        finally:
            env.close()

    a, b, c = first(3), first(3), first(4)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert a.dtype == np.float32 and a.min() >= 0.0 and a.max() <= 10.0


def test_a_collision_terminates_with_the_papers_penalty_and_a_time_limit_truncates():
    env = gymnasium.make(ENV_ID, world="tests/worlds/small.yaml", start_yaw_jitter_deg=0.0, max_episode_steps=500)
    try:
        env.reset(seed=0)
        for _ in range(100):  # 2 m/s straight ahead: into the wall
            obs, reward, terminated, truncated, info = env.step(3)
            if terminated:
                break
        assert terminated and not truncated and reward == -10.0
        obs, info = env.reset()
        assert info["episode"] == 1 and env.observation_space.contains(obs)
    finally:
        env.close()
    env = gymnasium.make(ENV_ID, world="basic", max_episode_steps=3)
    try:
        env.reset(seed=1)
        ends = [env.step(1)[2:4] for _ in range(3)]  # turning on the spot for three steps
        assert ends[-1] == (False, True) and ends[0] == (False, False)
        with pytest.raises(ValueError, match="action must be an integer in"):
            env.step(7)
    finally:
        env.close()


def test_a_vector_of_simulators_in_subprocesses_steps_in_parallel():
    envs = gymnasium.make_vec(ENV_ID, num_envs=2, vectorization_mode="async")
    try:
        obs, info = envs.reset(seed=[5, 6])
        assert obs.shape == (2, 5, 64, 64) and not np.array_equal(obs[0], obs[1])
        obs, reward, terminated, truncated, info = envs.step(np.array([0, 3]))
        assert obs.shape == (2, 5, 64, 64) and reward.shape == (2,)
    finally:
        envs.close()


def test_a_bad_world_is_refused_when_the_environment_is_made():
    with pytest.raises(Exception, match="unknown world 'nowhere'"):
        gymnasium.make(ENV_ID, world="nowhere")
