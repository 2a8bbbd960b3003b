"""The act -> step -> stack loop, once: a policy flying the simulator with the paper's actions.

In-process training (uav_trainer), evaluation, figures (uav_eval) and benchmarks all fly through `Flight.step`, so
they act, move and stack frames exactly alike (and as policy_node and sim_node do over ROS): the decision is
uav_policy.pilot.Pilot's, policy_node's own, safety layer included when one is given; the stepping is the caller's
uav_sim.stacked_sim.StackedSim, which the Gymnasium environment uses too. It lives with the policy, whose decision
path it is, and imports no simulator (a drone installs none): learning and measuring both import it, neither the other.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from uav_common.local_map import PinholeCamera

from .agent import Agent
from .pilot import Decision, Pilot
from .safety import SafetyLayer
from .shield import Shield

if TYPE_CHECKING:
    from uav_sim.simulator import StepResult
    from uav_sim.stacked_sim import StackedSim


@dataclasses.dataclass(frozen=True)
class Step:
    action: int  # the index into the action table
    q: np.ndarray  # the Q-values it was chosen on
    attention: np.ndarray | None  # SAM's attention weights on the state (None for the CNN)
    before: StepResult  # the frame acted on (and the pose the step began at)
    after: StepResult  # what the step led to: the next frame, its reward, a collision or time limit
    safety: str = ""  # what the safety layer changed ("" when nothing, or flown without one)
    unshielded: int = -1  # the network's own choice when a shield checked it (-1: no shield)
    shield: str = ""  # what the shield changed ("" when the network's choice flew)


class Flight:
    """An Agent flying a StackedSim: `step(epsilon)` acts on the stacked frames and steps the simulator."""

    def __init__(self, env: StackedSim, agent: Agent, safety: SafetyLayer | None = None, shield: Shield | None = None):
        """`env` steps the simulator and stacks its frames as policy_node gives them to `agent`'s network (its input
        size, the field of view it was trained with: StackedSim's input_hw and trained_hfov_deg); with `safety`, the
        commands pass policy_node's safety layer; with `shield`, the network chooses among the actions the local map
        of the simulator's measured frames and exact odometry says are safe."""
        self.env, self.agent, self.actions = env, agent, env.actions
        self.pilot = Pilot(agent, env.actions, env.sim.config.step_duration_s, safety, shield)
        self._shown = None  # the frame the shield saw last (episode, step)

    @property
    def last(self) -> StepResult:
        return self.env.last

    def step(self, epsilon: float = 0.0) -> Step:
        return self.execute(self.decide(epsilon))

    def decide(self, epsilon: float = 0.0, instead: int | None = None) -> Decision:
        """The decision on the frames so far (the simulator does not move); `instead`: Pilot.decide's."""
        shield, last = self.pilot.shield, self.env.last
        if shield is not None and (last.episode, last.sim_time_s) != self._shown:
            if self._shown is not None and last.episode != self._shown[0]:
                shield.reset()  # a new episode: the vehicle is back at its start
            cam = self.env.sim.camera.intrinsics
            camera = PinholeCamera.from_fov(cam.width, cam.height, cam.hfov_deg)
            p = last.pose
            shield.observe(last.depth_m, camera, p.x_m, p.y_m, p.z_m, p.yaw_rad)
            self._shown = (last.episode, last.sim_time_s)
        return self.pilot.decide(self.env.state, self.env.last_input, epsilon, instead)

    def execute(self, d: Decision) -> Step:
        """Fly decision `d` (made by `decide` on the current frames) one step."""
        before = self.env.last
        after = self.env.step_command(d.linear_x_mps, d.yaw_rate_radps) if d.safety else self.env.step(d.action)
        return Step(d.action, d.q, d.attention, before, after, d.safety, d.unshielded, d.shield)
