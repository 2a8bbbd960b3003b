"""The act -> step -> stack loop, once: a policy flying the simulator with the paper's actions.

In-process training, evaluation, figures and benchmarks all fly through `Flight.step`, so they
act, move and stack frames exactly alike (and as policy_node and sim_node do over ROS); the stepping
itself is uav_sim.stacked_sim.StackedSim, which the Gymnasium environment uses too.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from uav_common.actions import PAPER_ACTIONS, Action
from uav_policy.agent import Agent
from uav_sim.simulator import Simulator, StepResult
from uav_sim.stacked_sim import StackedSim


@dataclasses.dataclass(frozen=True)
class Step:
    action: int  # the index into the action table
    q: np.ndarray  # the Q-values it was chosen on
    attention: np.ndarray | None  # SAM's attention weights on the state (None for the CNN)
    before: StepResult  # the frame acted on (and the pose the step began at)
    after: StepResult  # what the step led to: the next frame, its reward, a collision or time limit


class Flight:
    """An Agent flying a Simulator: `step(epsilon)` acts on the stacked frames and steps the simulator."""

    def __init__(
        self,
        sim: Simulator,
        agent: Agent,
        frames: int,
        actions: tuple[Action, ...] = PAPER_ACTIONS,
        trained_hfov_deg: float | None = None,
    ):
        """Frames reach the network as policy_node gives them: mapped onto its input size and the field of
        view it was trained with (`trained_hfov_deg`; default: the simulator's camera)."""
        hw = (agent.cfg.height, agent.cfg.width)
        self.env = StackedSim(sim, frames, actions, input_hw=hw, trained_hfov_deg=trained_hfov_deg)
        self.agent, self.actions = agent, actions

    @property
    def last(self) -> StepResult:
        return self.env.last

    def step(self, epsilon: float = 0.0) -> Step:
        action, q, w, _ = self.agent.act(self.env.state, epsilon)
        before = self.env.last
        return Step(action, q, w, before, self.env.step(action))
