"""The act -> step -> stack loop, once: a policy flying the simulator with the paper's actions.

In-process training, evaluation, figures and benchmarks all fly through `Flight.step`, so they
act, move and stack frames exactly alike (and as policy_node and sim_node do over ROS): the decision is
uav_policy.pilot.Pilot's, policy_node's own, safety layer included when one is given; the stepping is
uav_sim.stacked_sim.StackedSim, which the Gymnasium environment uses too.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from uav_common.actions import PAPER_ACTIONS, Action
from uav_policy.agent import Agent
from uav_policy.pilot import Decision, Pilot
from uav_policy.safety import SafetyLayer
from uav_sim.simulator import Simulator, StepResult
from uav_sim.stacked_sim import StackedSim


@dataclasses.dataclass(frozen=True)
class Step:
    action: int  # the index into the action table
    q: np.ndarray  # the Q-values it was chosen on
    attention: np.ndarray | None  # SAM's attention weights on the state (None for the CNN)
    before: StepResult  # the frame acted on (and the pose the step began at)
    after: StepResult  # what the step led to: the next frame, its reward, a collision or time limit
    safety: str = ""  # what the safety layer changed ("" when nothing, or flown without one)


class Flight:
    """An Agent flying a Simulator: `step(epsilon)` acts on the stacked frames and steps the simulator."""

    def __init__(
        self,
        sim: Simulator,
        agent: Agent,
        frames: int,
        actions: tuple[Action, ...] = PAPER_ACTIONS,
        trained_hfov_deg: float | None = None,
        safety: SafetyLayer | None = None,
    ):
        """Frames reach the network as policy_node gives them: mapped onto its input size and the field of
        view it was trained with (`trained_hfov_deg`; default: the simulator's camera); with `safety`, its
        commands pass policy_node's safety layer."""
        hw = (agent.cfg.height, agent.cfg.width)
        self.env = StackedSim(sim, frames, actions, input_hw=hw, trained_hfov_deg=trained_hfov_deg)
        self.agent, self.actions = agent, actions
        self.pilot = Pilot(agent, actions, sim.config.step_duration_s, safety)

    @property
    def last(self) -> StepResult:
        return self.env.last

    def step(self, epsilon: float = 0.0) -> Step:
        return self.execute(self.decide(epsilon))

    def decide(self, epsilon: float = 0.0) -> Decision:
        """The decision on the frames so far (the simulator does not move)."""
        return self.pilot.decide(self.env.state, self.env.last_input, epsilon)

    def execute(self, d: Decision) -> Step:
        """Fly decision `d` (made by `decide` on the current frames) one step."""
        before = self.env.last
        after = self.env.step_command(d.linear_x_mps, d.yaw_rate_radps) if d.safety else self.env.step(d.action)
        return Step(d.action, d.q, d.attention, before, after, d.safety)
