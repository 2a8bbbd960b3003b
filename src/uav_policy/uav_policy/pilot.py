"""The decision path, once (no ROS): a state of stacked network inputs -> the network's action, its Q-values and
attention -> the shield (when there is one: the network's best action of those the local map says are safe) -> the
action's body command -> the safety layer -> the command flown.

policy_node decides every frame through `Pilot.decide`, and so do the in-process flights (uav_policy.rollout:
training, `evaluate --inprocess`, figures, benchmarks), so a frame becomes a command the same way with or without
ROS, the safety layer included (`evaluate --inprocess --safety`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from uav_common.actions import Action, turning_indices

from .agent import Agent
from .safety import SafetyLayer
from .shield import Shield


@dataclasses.dataclass(frozen=True)
class Decision:
    action: int  # the network's choice (or in training a teacher's): the action flown, learnt from and recorded
    q: np.ndarray  # the Q-values it was chosen on
    attention: np.ndarray | None  # SAM's attention on the state (None for the CNN)
    explored: bool  # a random action (epsilon)
    linear_x_mps: float  # the command flown: the action's, or what the safety layer made of it
    yaw_rate_radps: float
    safety: str  # what the safety layer (or a shield without odometry) changed, in words ("" when nothing)
    unshielded: int = -1  # the network's own choice when a shield checked it (-1: no shield)
    shield: str = ""  # what the shield changed, in words ("" when the network's choice flew)


class Pilot:
    """Decides on a state: the agent's action, the shield's verdict on it and the safety layer (each when there is
    one), as a body command."""

    def __init__(
        self,
        agent: Agent,
        actions: tuple[Action, ...],
        step_duration_s: float,
        safety: SafetyLayer | None = None,
        shield: Shield | None = None,
    ):
        self.agent, self.actions, self.step_duration_s, self.safety = agent, actions, step_duration_s, safety
        self.shield = shield
        self.turning = turning_indices(actions)

    def command_of(self, action: int) -> tuple[float, float]:
        """An action's body command: forward speed (m/s) and yaw rate (rad/s, left +)."""
        a = self.actions[action]
        return a.linear_x_mps, a.yaw_rate_radps(self.step_duration_s)

    def decide(self, state: np.ndarray, newest_input: np.ndarray, epsilon: float = 0.0, instead: int | None = None) -> Decision:
        """The decision on `state` (frames, H, W); `newest_input` (its last frame on the network's input) is what the
        safety layer checks the corridor in. `instead`: the action flown in place of the network's (a teacher's, in
        training), after the network has decided as ever (its Q-values, attention and exploration draw)."""
        action, q, w, explored = self.agent.act(state, epsilon)
        if instead is not None:
            action, explored = instead, False
        unshielded, shielded, why = -1, "", ""
        if self.shield is not None and instead is None:
            verdict = self.shield.check(q, action)
            unshielded, shielded = action, verdict.why
            if not verdict.vouched:
                why = verdict.why  # nothing vouched for: stop, as the safety layer does when frames stop
            action = verdict.action
        vx, wz = self.command_of(action)
        if why:
            vx, wz = 0.0, 0.0
        elif self.safety is not None:
            # Should the way be blocked, the network's best turning action decides the way round.
            best_turn = max(self.turning, key=lambda i: q[i], default=None)
            turn = self.command_of(best_turn)[1] if best_turn is not None else 0.0
            vx, wz, why = self.safety.filter(vx, wz, newest_input, turn)
        return Decision(action, q, w, explored, vx, wz, why, unshielded, shielded)
