"""The paper's four actions, as body-frame velocity commands (REP 103: x forward, yaw left +)."""

from __future__ import annotations

import dataclasses
import math

from .settings import setting


@dataclasses.dataclass(frozen=True)
class Action:
    name: str
    linear_x_mps: float
    yaw_deg_per_step: float  # turned during one step; negative = right

    def yaw_rate_radps(self, step_duration_s: float) -> float:
        return math.radians(self.yaw_deg_per_step) / step_duration_s


def turning_indices(actions) -> tuple[int, ...]:
    """Indices of the actions that yaw (the paper's a1 and a2)."""
    return tuple(i for i, a in enumerate(actions) if a.yaw_deg_per_step != 0.0)


PAPER_ACTIONS = (
    Action("a0_forward_1mps", 1.0, 0.0),
    Action("a1_yaw_right_30deg_forward_1mps", 1.0, -30.0),
    Action("a2_yaw_left_30deg_forward_1mps", 1.0, 30.0),
    Action("a3_forward_2mps", 2.0, 0.0),
)


def make_actions(names, linear_x_mps, yaw_deg) -> tuple[Action, ...]:
    """An action table from three parallel lists (as ROS parameters give them)."""
    if not (len(names) == len(linear_x_mps) == len(yaw_deg)) or len(names) < 2:
        raise ValueError(
            f"action_names, action_linear_x_mps and action_yaw_deg must have the same length >= 2, "
            f"got {len(names)}, {len(linear_x_mps)}, {len(yaw_deg)}"
        )
    return tuple(Action(str(n), float(v), float(y)) for n, v, y in zip(names, linear_x_mps, yaw_deg, strict=True))


def match_action(actions, linear_x_mps: float, yaw_rate_radps: float, step_duration_s: float, tol: float = 1e-3) -> int | None:
    """Index of the action a command came from, or None if it matches none (never guessed)."""
    for i, a in enumerate(actions):
        if abs(a.linear_x_mps - linear_x_mps) <= tol and abs(a.yaw_rate_radps(step_duration_s) - yaw_rate_radps) <= tol:
            return i
    return None


@dataclasses.dataclass(frozen=True)
class ActionSettings:
    """The action table as parameters (policy_node and trainer_node must be given the same)."""

    action_names: tuple[str, ...] = setting(tuple(a.name for a in PAPER_ACTIONS), "Action names (q_values labels)")
    action_linear_x_mps: tuple[float, ...] = setting(
        tuple(a.linear_x_mps for a in PAPER_ACTIONS), "Forward speed of each action (m/s)"
    )
    action_yaw_deg: tuple[float, ...] = setting(
        tuple(a.yaw_deg_per_step for a in PAPER_ACTIONS), "Yaw turned during one step by each action (deg, left +)"
    )

    def table(self) -> tuple[Action, ...]:
        """The actions; ValueError when the lists disagree or the networks' four outputs do not fit."""
        actions = make_actions(self.action_names, self.action_linear_x_mps, self.action_yaw_deg)
        if len(actions) != 4:
            raise ValueError(f"the networks have 4 outputs, got {len(actions)} actions")
        return actions
