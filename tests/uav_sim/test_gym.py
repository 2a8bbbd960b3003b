"""The Gymnasium interface to the simulator: the checker's rules, seeding, the paper's reward, and vector envs."""

import os

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import uav_sim.gym  # noqa: F401  (registers the environment)
from conftest import SMALL_WORLD
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
    env = gymnasium.make(ENV_ID, world=SMALL_WORLD, start_yaw_jitter_deg=0.0, max_episode_steps=500)
    try:
        env.reset(seed=0)
        for _ in range(100):  # 2 m/s straight ahead: into the wall
            obs, reward, terminated, truncated, info = env.step(3)
            if terminated:
                break
        assert terminated and not truncated and reward == -10.0
        obs, info = env.reset()
        assert info["episode_index"] == 1 and env.observation_space.contains(obs)
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


def test_a_vector_of_simulators_steps_in_two_subprocesses():
    envs = gymnasium.make_vec(ENV_ID, num_envs=2, vectorization_mode="async")
    try:
        pids = {p.pid for p in envs.processes}
        assert len(pids) == 2 and os.getpid() not in pids and all(p.is_alive() for p in envs.processes)
        obs, info = envs.reset(seed=[5, 6])
        assert obs.shape == (2, 5, 64, 64) and not np.array_equal(obs[0], obs[1])
        obs, reward, terminated, truncated, info = envs.step(np.array([0, 3]))
        assert obs.shape == (2, 5, 64, 64) and reward.shape == (2,)
    finally:
        envs.close()


def test_a_bad_world_is_refused_when_the_environment_is_made():
    with pytest.raises(Exception, match="unknown world 'nowhere'"):
        gymnasium.make(ENV_ID, world="nowhere")


def test_stable_baselines3_trains_on_it_alone_and_on_a_vector_of_two():
    """A client nobody here wrote: SB3's checker, then its DQN learns through its first logs (which read
    info["episode"] as Gymnasium's episode statistics), on one environment and on a vector env of two."""
    from stable_baselines3 import DQN
    from stable_baselines3.common.env_checker import check_env as sb3_check_env
    from stable_baselines3.common.env_util import make_vec_env

    def make():
        return gymnasium.make(ENV_ID, world=SMALL_WORLD, max_episode_steps=20)

    env = make()
    sb3_check_env(env.unwrapped)
    for venv in (env, make_vec_env(make, n_envs=2, seed=0)):
        kw = dict(buffer_size=400, learning_starts=60, train_freq=4, batch_size=16, seed=0, device="cpu")
        model = DQN("CnnPolicy", venv, policy_kwargs=dict(normalize_images=False), stats_window_size=5, **kw)
        model.learn(200, log_interval=1)
        assert model.num_timesteps >= 200 and len(model.ep_info_buffer) > 0, "episodes ended and were counted"
        assert {"r", "l", "t"} <= set(model.ep_info_buffer[-1]) and model.ep_info_buffer[-1]["l"] <= 20
        venv.close()


def test_record_episode_statistics_reports_each_episodes_return_and_length():
    env = gymnasium.wrappers.RecordEpisodeStatistics(gymnasium.make(ENV_ID, world="basic", max_episode_steps=4))
    try:
        env.reset(seed=0)
        total = 0.0
        for _ in range(4):
            _, reward, terminated, truncated, info = env.step(1)
            total += reward
        assert truncated and info["episode"]["l"] == 4 and info["episode"]["r"] == pytest.approx(total)
        assert isinstance(info["episode_index"], int), "the simulator's own count, under a key of its own"
    finally:
        env.close()
