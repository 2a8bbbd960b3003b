"""The act -> step -> stack loop, once: a policy flying the simulator with the paper's actions.

In-process training, evaluation, figures and benchmarks all fly through `Flight.step`, so they
act, move and stack frames exactly alike (and as policy_node and sim_node do over ROS).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from uav_policy.actions import PAPER_ACTIONS, Action
from uav_policy.agent import Agent
from uav_policy.frame_stack import FrameStack
from uav_sim.simulator import Simulator, StepResult
from uav_sim.vehicle import BodyTwist


@dataclasses.dataclass(frozen=True)
class Step:
    action: int  # the index into the action table
    q: np.ndarray  # the Q-values it was chosen on
    attention: np.ndarray | None  # SAM's attention weights on the state (None for the CNN)
    before: StepResult  # the frame acted on (and the pose the step began at)
    after: StepResult  # what the step led to: the next frame, its reward, a collision or time limit


class Flight:
    """An Agent flying a Simulator: `step(epsilon)` acts on the stacked frames, applies the action for one
    step and stacks the new frame (a new episode, after a collision or time limit, restarts the stack)."""

    def __init__(self, sim: Simulator, agent: Agent, frames: int, actions: tuple[Action, ...] = PAPER_ACTIONS):
        self.sim, self.agent, self.actions = sim, agent, actions
        self.stack = FrameStack(frames)
        self.last = sim.observe()
        self.state = self.stack.reset(self.last.depth_m)

    def step(self, epsilon: float = 0.0) -> Step:
        action, q, w, _ = self.agent.act(self.state, epsilon)
        a = self.actions[action]
        before = self.last
        r = self.sim.step(BodyTwist(a.linear_x_mps, yaw_rate_radps=a.yaw_rate_radps(self.sim.config.step_duration_s)))
        self.state = self.stack.reset(r.depth_m) if r.collided or r.truncated else self.stack.push(r.depth_m)
        self.last = r
        return Step(action, q, w, before, r)
