"""The planner's search: the four actions' sequences flown ahead from a pose and ranked on what is known (numpy).

At every step it expands every sequence of `horizon` actions (4^5 = 1024 over 2.5 s) with the vehicle's own
kinematics (uav_common.kinematics.integrate, at the physics sub-steps), measures each plan's clearance to what it
knows (minus `body_radius_m`), and keeps the first action of the best plan, ranked by

1. surviving the whole horizon and ending where a turning circle (either way, 1 m/s at 30 deg a step) is free, so
   the vehicle could circle there for ever: no plan is accepted that only postpones a crash;
2. its smallest clearance, capped at `clearance_cap_m` (beyond it every plan is as safe);
3. progress: the path length flown (the 2 m/s action flies twice as far as the others), each step's discounted by
   `progress_discount` per step ahead, so that of two plans as fast the one that is fast first wins.

Ties go to the plan whose actions come first in the table (a deterministic choice).

What it knows is a `Clearance`: the distance from any points to the nearest thing it avoids, and a code naming that
thing. uav_sim.planner gives it the world's geometry (what the frames' segmentation showed, or everything); the local
map (uav_common.local_map: measured depth and odometry only) gives it what a drone can know, in the simulator and on
a drone alike.

Its decision has a reason (docs/INSIGHT.md): what bounds the clearance of the plan it keeps, and for each action it
rejects, what bounds the best plan starting with it when that plan ranks lower on safety.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Protocol

import numpy as np

from .actions import PAPER_ACTIONS, Action
from .kinematics import BodyTwist, Pose, integrate

# What the planner knows: what the last memory_frames frames' segmentation showed (stack), the whole world (all), or
# the local map of the measured depth and odometry (map: what a drone knows).
KNOWLEDGE = ("stack", "all", "map")
NO_REASON = -1


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    horizon: int = 5  # actions a plan looks ahead (4^horizon plans)
    body_radius_m: float = 0.3  # subtracted from every footprint distance (the body's half diagonal 0.28 m, and a little)
    clearance_cap_m: float = 0.5  # clearances above it rank alike
    progress_discount: float = 0.9  # a metre flown one step later counts this much
    knowledge: str = "stack"  # one of KNOWLEDGE
    memory_frames: int = 5

    def validate(self) -> None:
        if self.knowledge not in KNOWLEDGE:
            raise ValueError(f"planner knowledge {self.knowledge!r} is invalid: expected one of {', '.join(KNOWLEDGE)}")
        if not 1 <= self.horizon <= 7:
            raise ValueError(f"planner horizon {self.horizon} is invalid: expected 1..7 (4^horizon plans)")
        if self.memory_frames < 1:
            raise ValueError(f"planner memory_frames {self.memory_frames} is invalid: expected >= 1")


@dataclasses.dataclass(frozen=True)
class Plan:
    """The planner's answer for one frame."""

    action: int  # the first action of the best plan
    scores: np.ndarray  # (actions,) the best plan's rank value starting with each action (higher is better)
    clearance_m: np.ndarray  # (actions,) the smallest clearance of the best plan starting with each action
    reason: tuple[int, ...]  # codes of what the decision is about (Clearance's); () when nothing bounds it
    safe: np.ndarray  # (actions,) bool: the best plan starting with each action survives and ends on a free circle


class Clearance(Protocol):
    """What the planner knows: distances from points to the nearest thing to avoid."""

    def clearance(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance (m; +Inf where nothing is known), the code of what is nearest (NO_REASON where nothing)), shaped
        like the points."""


class Planner:
    """Plans from a pose on what a Clearance knows."""

    def __init__(
        self,
        step_duration_s: float,
        physics_rate_hz: float,
        actions: tuple[Action, ...] = PAPER_ACTIONS,
        config: PlannerConfig = PlannerConfig(),
    ):
        config.validate()
        self.config, self.actions = config, actions
        self.step_duration_s = step_duration_s
        self.n_sub = max(1, int(math.ceil(step_duration_s * physics_rate_hz)))
        self.dt = step_duration_s / self.n_sub
        self.speed = np.array([a.linear_x_mps for a in actions], dtype=np.float64)
        # Each action's sub-step positions from the origin facing +x, by the simulator's own integrate(): a plan's
        # are these rotated onto its pose (the motion does not depend on where it starts).
        offsets = []
        for a in actions:
            cmd = BodyTwist(a.linear_x_mps, yaw_rate_radps=a.yaw_rate_radps(step_duration_s))
            pose, path = Pose(0.0, 0.0, 0.0, 0.0), []
            for _ in range(self.n_sub):
                pose = integrate(pose, cmd, self.dt)
                path.append((pose.x_m, pose.y_m))
            offsets.append(path)
        self._offset_x, self._offset_y = np.array(offsets)[..., 0], np.array(offsets)[..., 1]  # (actions, sub-steps)
        self._turn = np.array([math.radians(a.yaw_deg_per_step) for a in actions])
        turning = [a for a in actions if a.yaw_deg_per_step != 0.0]
        # The turning circle a plan must be able to end on: the slowest turn's radius.
        self.circle_m = min((a.linear_x_mps / abs(a.yaw_rate_radps(step_duration_s)) for a in turning), default=math.inf)

    def plan(self, x_m: float, y_m: float, yaw_rad: float, known: Clearance) -> Plan:
        """The best plan's first action from this pose, with what decided it."""
        cfg, n_act = self.config, len(self.actions)
        x = np.array([x_m], dtype=np.float64)
        y, yaw = np.array([y_m], dtype=np.float64), np.array([yaw_rad], dtype=np.float64)
        clear = np.full(1, np.inf)  # each plan's smallest clearance so far
        bound = np.full(1, NO_REASON, dtype=np.int64)  # what bounds it
        alive_steps = np.zeros(1, dtype=np.int64)  # steps survived before the first contact
        length = np.zeros(1)
        for depth in range(cfg.horizon):
            # Every plan so far, extended by every action: the child k*n_act + a continues plan k with action a.
            x, y, yaw = (np.repeat(v, n_act) for v in (x, y, yaw))
            clear, bound, alive_steps, length = (np.repeat(v, n_act) for v in (clear, bound, alive_steps, length))
            reps = len(x) // n_act
            v = np.tile(self.speed, reps)
            c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
            ox, oy = np.tile(self._offset_x, (reps, 1)), np.tile(self._offset_y, (reps, 1))  # (plans, sub-steps)
            xs, ys = x[:, None] + c * ox - s * oy, y[:, None] + s * ox + c * oy
            x, y, yaw = xs[:, -1], ys[:, -1], yaw + np.tile(self._turn, reps)
            length = length + cfg.progress_discount**depth * v * self.step_duration_s
            d, code = known.clearance(xs, ys)  # (plans, sub-steps)
            at = d.argmin(axis=1)
            rows = np.arange(len(d))
            step_clear = d[rows, at] - cfg.body_radius_m
            nearer = step_clear < clear
            clear = np.where(nearer, step_clear, clear)
            bound = np.where(nearer, code[rows, at], bound)
            alive_steps = np.where((clear > 0.0) & (alive_steps == depth), depth + 1, alive_steps)
        survives = alive_steps == cfg.horizon
        circle_free = survives & self._circle_free(x, y, yaw, known)
        capped = np.where(np.isfinite(clear), np.minimum(clear, cfg.clearance_cap_m), cfg.clearance_cap_m)
        # The safety rank in one number (each term outweighs all below it), then progress (under 1e3 m).
        safety = circle_free * 1e7 + alive_steps * 1e5 + capped * 1e3
        score = (safety + length).reshape(n_act, -1)  # rows: the first action
        best_in = score.argmax(axis=1)
        rows = np.arange(n_act)
        scores = score[rows, best_in]
        first_safety = safety.reshape(n_act, -1)[rows, best_in]
        first_clear = clear.reshape(n_act, -1)[rows, best_in]
        first_bound = bound.reshape(n_act, -1)[rows, best_in]
        first_safe = circle_free.reshape(n_act, -1)[rows, best_in]
        action = int(np.argmax(scores))  # the first maximum: table order breaks ties
        reason = self._reason(action, first_safety, first_clear, first_bound)
        return Plan(action, scores, first_clear, reason, first_safe)

    def _circle_free(self, x, y, yaw, known: Clearance) -> np.ndarray:
        """Whether a disc of the turning circle's radius beside the end pose (left or right) is free."""
        if not math.isfinite(self.circle_m):
            return np.ones(len(x), dtype=bool)
        r = self.circle_m
        free = np.zeros(len(x), dtype=bool)
        for side in (1.0, -1.0):  # left, right
            cx, cy = x - side * r * np.sin(yaw), y + side * r * np.cos(yaw)
            free |= known.clearance(cx, cy)[0] - self.config.body_radius_m >= r
        return free

    def _reason(self, action: int, safety: np.ndarray, clear: np.ndarray, bound: np.ndarray) -> tuple[int, ...]:
        """The decision is about what bounds the kept plan's clearance when it is under the cap, and what bounds the
        best plan of each rejected action that ranks lower on safety (not on progress alone)."""
        out = []
        if clear[action] < self.config.clearance_cap_m and bound[action] != NO_REASON:
            out.append(int(bound[action]))
        for a in range(len(safety)):
            if a != action and safety[a] < safety[action] - 1e-6 and bound[a] != NO_REASON and int(bound[a]) not in out:
                out.append(int(bound[a]))
        return tuple(out)
