"""A Gymnasium interface to the simulator core: the same worlds, actions and reward, without ROS.

    import gymnasium as gym
    import uav_sim.gym  # registers uav_sim/DepthAvoid-v0

    env = gym.make("uav_sim/DepthAvoid-v0", world="complex")
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    envs = gym.make_vec("uav_sim/DepthAvoid-v0", num_envs=4, vectorization_mode="async")  # subprocesses

Observation: the last `frames` depth frames, (frames, image_size, image_size) float32 metres, clipped
to [0, max_range_m] (beyond range and invalid pixels read as the range, too close as 0). Actions: the
paper's four (uav_common.actions.PAPER_ACTIONS). Reward: the paper's (uav_sim.reward.step_reward; -10
for a collision). A collision terminates the episode; `max_episode_steps` truncates it. `reset(seed=N)`
rebuilds the simulator with that seed (weather, start heading, `random` worlds), so the same seed gives
the same first observations. `info`: beta_m, episode_index (the simulator's episode count), x_m, y_m, world;
the key "episode" is left to gymnasium.wrappers.RecordEpisodeStatistics and SB3's Monitor.

With Stable-Baselines3 (observations are metres, not pixels, hence normalize_images=False):

    from stable_baselines3 import DQN
    model = DQN("CnnPolicy", gym.make("uav_sim/DepthAvoid-v0"), policy_kwargs=dict(normalize_images=False))
    model.learn(10_000)
"""

from __future__ import annotations

import dataclasses

import gymnasium
import numpy as np

from .simulator import SimConfig, Simulator
from .stacked_sim import StackedSim
from .world import WorldChoice

ENV_ID = "uav_sim/DepthAvoid-v0"


class DepthAvoidEnv(gymnasium.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(
        self,
        world: str = "basic",
        frames: int = 5,
        image_size: int = 64,
        hfov_deg: float = SimConfig.hfov_deg,
        reward_window_fraction: float = SimConfig.reward_window_fraction,
        start_yaw_jitter_deg: float = 180.0,
        max_episode_steps: int = 1000,
        render_mode: str | None = None,
    ):
        """`world` as sim_node's parameter (basic, complex, turbulent, random:SEED, random_each_episode, a
        file); the camera by `hfov_deg`, `image_size` and the reward window (the shipped recipe's by default;
        the paper's camera is hfov_deg=90, reward_window_fraction=0.2)."""
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.worlds = WorldChoice(world=world)
        self.config = SimConfig(
            image_width=image_size,
            image_height=image_size,
            hfov_deg=hfov_deg,
            reward_window_fraction=reward_window_fraction,
            start_yaw_jitter_deg=start_yaw_jitter_deg,
            max_episode_steps=max_episode_steps,
        )
        self.config.validate()
        self.worlds.load(0)  # a bad world fails here, not at the first reset
        self.frames, self.render_mode = frames, render_mode
        self.observation_space = gymnasium.spaces.Box(
            0.0, self.config.max_range_m, (frames, image_size, image_size), dtype=np.float32
        )
        self.action_space = gymnasium.spaces.Discrete(4)
        self._env: StackedSim | None = None
        self._seed = 0
        self._done = False

    def _observation(self) -> np.ndarray:
        far = self.config.max_range_m
        return np.clip(np.nan_to_num(self._env.state, nan=far, posinf=far, neginf=0.0), 0.0, far).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None or self._env is None:
            self._seed = int(seed) if seed is not None else int(self.np_random.integers(2**31 - 1))
            self.close()
            world, layouts = self.worlds.load(self._seed)
            self._env = StackedSim(Simulator(world, dataclasses.replace(self.config, seed=self._seed), layouts), self.frames)
        elif not self._done:  # a collision or time limit has already started the next episode
            self._env.reset()
        self._done = False
        return self._observation(), self._info()

    def step(self, action):
        if self._env is None:
            raise RuntimeError("call reset() before step()")
        if not self.action_space.contains(action):
            raise ValueError(f"action must be an integer in [0, 4), got {action!r}")
        r = self._env.step(int(action))
        self._done = r.collided or r.truncated
        return self._observation(), float(r.reward), bool(r.collided), bool(r.truncated), self._info()

    def _info(self) -> dict:
        r = self._env.last
        return {
            "beta_m": float(r.beta_m),
            "episode_index": r.episode,  # not "episode": Gymnasium and SB3 reserve it for episode statistics
            "x_m": r.pose.x_m,
            "y_m": r.pose.y_m,
            "world": self._env.sim.world.name,
        }

    def render(self):
        if self.render_mode != "rgb_array" or self._env is None:
            return None
        grey = (255.0 * (1.0 - self._observation()[-1] / self.config.max_range_m)).astype(np.uint8)  # near = bright
        return np.repeat(grey[:, :, None], 3, axis=2)

    def close(self):
        if self._env is not None:
            self._env.sim.close()
            self._env = None


if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="uav_sim.gym:DepthAvoidEnv")
