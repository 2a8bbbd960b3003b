"""The simulator as a learning agent sees it: an action of the table applied for one step, and the last
N depth frames as the observation. In-process training, evaluation, figures, benchmarks (through
uav_policy.rollout.Flight) and the Gymnasium environment (uav_sim.gym) all step through it."""

from __future__ import annotations

import numpy as np

from uav_common.actions import PAPER_ACTIONS, Action
from uav_common.frame_stack import FrameStack, NetworkInput
from uav_common.kinematics import BodyTwist
from uav_common.local_map import LocalMap, PinholeCamera

from .simulator import Simulator, StepResult


class StackedSim:
    """`step(action)` applies the action's body velocity for one step and stacks the new frame; a new
    episode (after a collision, a time limit or `reset`) restarts the stack with its first frame.

    With `input_hw`, frames are mapped onto a network input of that size and `trained_hfov_deg` (default:
    the simulator's camera) as policy_node maps a camera's frames through CameraInfo: a sensor preset's
    frames are cropped or padded to the trained field of view and min-pooled. `last_input` is the newest.

    With `map_grid` (cells, resolution_m) every frame also goes into a local map (its measured depth, placed by the
    camera's pose: exact odometry), and the state's last channel is its egocentric grid (`last_grid`), as a network
    with NetConfig.local_map takes it."""

    def __init__(
        self,
        sim: Simulator,
        frames: int,
        actions: tuple[Action, ...] = PAPER_ACTIONS,
        input_hw: tuple[int, int] | None = None,
        trained_hfov_deg: float | None = None,
        map_grid: tuple[int, float] | None = None,
    ):
        self.sim, self.actions = sim, actions
        self.map_grid = map_grid
        self.map = LocalMap() if map_grid is not None else None
        self.last_grid: np.ndarray | None = None
        self.stack = FrameStack(frames)
        cfg = sim.config
        self.to_input = None  # frames are the network's input as they are
        hfov = cfg.hfov_deg if trained_hfov_deg is None else trained_hfov_deg
        if input_hw is not None and (input_hw != (cfg.image_height, cfg.image_width) or hfov != cfg.hfov_deg):
            k = sim.camera.intrinsics.k_matrix()
            self.to_input = NetworkInput(*input_hw)
            self.to_input.set_camera((k[0], k[4], k[2], k[5], cfg.image_width, cfg.image_height), hfov)
        self.last = sim.observe()
        self.last_input = self._input(self.last)
        self._stacked = self.stack.reset(self.last_input)

    @property
    def state(self) -> np.ndarray:
        """(frames, H, W) the stacked inputs, and the local map's grid as one more channel with `map_grid`."""
        if self.last_grid is None:
            return self._stacked
        return np.concatenate([self._stacked, self.last_grid[None]])

    def _input(self, r: StepResult) -> np.ndarray:
        if self.map is not None:
            if r.collided or r.truncated:  # its first frame of a new episode
                self.map.reset()
            cam, k = self.sim.camera.intrinsics, self.sim.camera.intrinsics.k_matrix()  # as camera_info says
            x, y, z = self.sim.camera_xyz()
            self.map.insert(r.depth_m, PinholeCamera(cam.width, cam.height, k[0], k[4], k[2], k[5]), x, y, z, r.pose.yaw_rad)
            self.last_grid = self.map.egocentric(*self.map_grid)
        return r.depth_m if self.to_input is None else self.to_input(r.depth_m)

    def input_mask(self, mask: np.ndarray) -> np.ndarray:
        """A camera-sized bool mask on the network's input, as the frames are mapped (NetworkInput.mask)."""
        return np.asarray(mask, dtype=bool) if self.to_input is None else self.to_input.mask(mask)

    def step(self, action: int) -> StepResult:
        a = self.actions[action]
        return self.step_command(a.linear_x_mps, a.yaw_rate_radps(self.sim.config.step_duration_s))

    def step_command(self, linear_x_mps: float, yaw_rate_radps: float) -> StepResult:
        """One step of a body command that is not an action's (what a safety layer made of one)."""
        r = self.sim.step(BodyTwist(linear_x_mps, yaw_rate_radps=yaw_rate_radps))
        self.last_input = x = self._input(r)
        self._stacked = self.stack.reset(x) if r.collided or r.truncated else self.stack.push(x)
        self.last = r
        return r

    def reset(self) -> StepResult:
        """End the episode without a collision (the simulator's reset) and start the stack again."""
        if self.map is not None:
            self.map.reset()
        self.last = self.sim.reset()
        self.last_input = self._input(self.last)
        self._stacked = self.stack.reset(self.last_input)
        return self.last
