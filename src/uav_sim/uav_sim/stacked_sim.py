"""The simulator as a learning agent sees it: an action of the table applied for one step, and the last
N depth frames as the observation. In-process training, evaluation, figures, benchmarks (through
uav_trainer.rollout.Flight) and the Gymnasium environment (uav_sim.gym) all step through it."""

from __future__ import annotations

from uav_common.actions import PAPER_ACTIONS, Action
from uav_common.frame_stack import FrameStack

from .simulator import Simulator, StepResult
from .vehicle import BodyTwist


class StackedSim:
    """`step(action)` applies the action's body velocity for one step and stacks the new frame; a new
    episode (after a collision, a time limit or `reset`) restarts the stack with its first frame."""

    def __init__(self, sim: Simulator, frames: int, actions: tuple[Action, ...] = PAPER_ACTIONS):
        self.sim, self.actions = sim, actions
        self.stack = FrameStack(frames)
        self.last = sim.observe()
        self.state = self.stack.reset(self.last.depth_m)

    def step(self, action: int) -> StepResult:
        a = self.actions[action]
        r = self.sim.step(BodyTwist(a.linear_x_mps, yaw_rate_radps=a.yaw_rate_radps(self.sim.config.step_duration_s)))
        self.state = self.stack.reset(r.depth_m) if r.collided or r.truncated else self.stack.push(r.depth_m)
        self.last = r
        return r

    def reset(self) -> StepResult:
        """End the episode without a collision (the simulator's reset) and start the stack again."""
        self.last = self.sim.reset()
        self.state = self.stack.reset(self.last.depth_m)
        return self.last
