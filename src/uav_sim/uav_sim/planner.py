"""A privileged planner: the four actions searched on the world's true geometry (no ROS, no torch).

At every step it expands every sequence of `horizon` actions (4^5 = 1024 over 2.5 s) with the simulator's own
kinematics (uav_sim.vehicle.integrate, at the physics sub-steps), measures each plan's clearance to the obstacle
footprints and walls it knows (minus `margin_m`), and keeps the first action of the best plan, ranked by

1. surviving the whole horizon and ending where a turning circle (either way, 1 m/s at 30 deg a step) is free, so
   the vehicle could circle there for ever: no plan is accepted that only postpones a crash;
2. its smallest clearance, capped at `clearance_cap_m` (beyond it every plan is as safe);
3. progress: the path length flown (the 2 m/s action flies twice as far as the others), each step's discounted by
   `progress_discount` per step ahead, so that of two plans as fast the one that is fast first wins.

Ties go to the plan whose actions come first in the table (a deterministic choice).

What it knows (`knowledge`):
- `all`: every obstacle and wall of the world (the task's limit with these four actions);
- `stack`: only what the last `memory_frames` depth frames showed, the frames a network's stack holds: an obstacle or
  wall is known once one of its pixels, nearer than the camera's range, was in one of them (pybullet's segmentation
  mask); a new episode forgets. This planner is realizable from the frame stack, so it is the teacher by default.

Its decision has a reason (docs/INSIGHT.md): the obstacle or wall that bounds the clearance of the plan it keeps, and
for each action it rejects, the one that bounds the best plan starting with it when that plan ranks lower on safety.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque

import numpy as np

from uav_common.actions import PAPER_ACTIONS, Action

from .simulator import Simulator
from .vehicle import BodyTwist, Pose, integrate
from .world import World, wall_code

KNOWLEDGE = ("stack", "all")
NO_REASON = -1


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    horizon: int = 5  # actions a plan looks ahead (4^horizon plans)
    margin_m: float = 0.3  # subtracted from every footprint distance (the body's half diagonal 0.28 m, and a little)
    clearance_cap_m: float = 0.5  # clearances above it rank alike
    progress_discount: float = 0.9  # a metre flown one step later counts this much
    knowledge: str = "stack"  # "stack" (what the last memory_frames frames showed) or "all"
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
    reason: tuple[int, ...]  # obstacle indices (walls: -2 - wall index) the decision is about; () when nothing bounds it


class Geometry:
    """The world's obstacle footprints and walls, vectorised: clearance of many points at once."""

    def __init__(self, world: World, z_m: float = 1.0, body_half_height_m: float = 0.06):
        self.world = world
        # An obstacle lower than the vehicle's underside is flown over.
        tall = [i for i, o in enumerate(world.obstacles) if o.height_m > z_m - body_half_height_m]
        cyl = [i for i in tall if world.obstacles[i].shape != "box"]
        box = [i for i in tall if world.obstacles[i].shape == "box"]
        obs = world.obstacles
        self.cyl_index = np.array(cyl, dtype=np.int64)
        self.cyl = np.array([(obs[i].x_m, obs[i].y_m, obs[i].radius_m) for i in cyl], dtype=np.float64).reshape(-1, 3)
        self.box_index = np.array(box, dtype=np.int64)
        self.box = np.array(
            [
                (
                    obs[i].x_m,
                    obs[i].y_m,
                    math.cos(math.radians(obs[i].yaw_deg)),
                    math.sin(math.radians(obs[i].yaw_deg)),
                    obs[i].size_x_m / 2,
                    obs[i].size_y_m / 2,
                )
                for i in box
            ],
            dtype=np.float64,
        ).reshape(-1, 6)
        self.walls = np.array([world.length_m / 2, world.length_m / 2, world.width_m / 2, world.width_m / 2])
        # One code per column of distances(): cylinders, boxes, then the four walls.
        self.codes = np.concatenate([self.cyl_index, self.box_index, [wall_code(i) for i in range(4)]]).astype(np.int64)

    def distances(self, x: np.ndarray, y: np.ndarray, known: np.ndarray | None = None) -> np.ndarray:
        """(..., columns): horizontal distance from each point to each footprint and wall (0 inside); with `known`
        (a bool per column) only those columns."""
        if known is None:
            known = np.ones(len(self.codes), dtype=bool)
        n_cyl, n_box = len(self.cyl), len(self.box)
        x, y = np.asarray(x, dtype=np.float32)[..., None], np.asarray(y, dtype=np.float32)[..., None]
        cx, cy, r = self.cyl[known[:n_cyl]].T.astype(np.float32)
        d_cyl = np.maximum(np.hypot(x - cx, y - cy) - r, 0.0)
        bx, by, c, s, hx, hy = self.box[known[n_cyl : n_cyl + n_box]].T.astype(np.float32)
        dx, dy = x - bx, y - by
        u = np.maximum(np.abs(dx * c + dy * s) - hx, 0.0)
        v = np.maximum(np.abs(-dx * s + dy * c) - hy, 0.0)
        d_box = np.hypot(u, v)
        lx, ly = np.float32(self.walls[0]), np.float32(self.walls[2])
        walls = [lx - x, x + lx, ly - y, y + ly]
        d_wall = [np.maximum(w, 0.0) for w, k in zip(walls, known[-4:], strict=True) if k]
        return np.concatenate([d_cyl, d_box, *d_wall], axis=-1)


class Planner:
    """Plans from a pose in a world; `knowledge` 'stack' plans only around what `observe` was shown."""

    def __init__(
        self,
        world: World,
        step_duration_s: float,
        physics_rate_hz: float,
        actions: tuple[Action, ...] = PAPER_ACTIONS,
        config: PlannerConfig = PlannerConfig(),
        z_m: float | None = None,
    ):
        config.validate()
        self.config, self.actions = config, actions
        self.step_duration_s = step_duration_s
        self.n_sub = max(1, int(math.ceil(step_duration_s * physics_rate_hz)))
        self.dt = step_duration_s / self.n_sub
        self.speed = np.array([a.linear_x_mps for a in actions], dtype=np.float64)
        self.yaw_rate = np.array([a.yaw_rate_radps(step_duration_s) for a in actions], dtype=np.float64)
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
        self.set_world(world, z_m if z_m is not None else world.start_xyz_m[2])
        self._seen: deque[frozenset[int]] = deque(maxlen=config.memory_frames)

    def set_world(self, world: World, z_m: float) -> None:
        """A new world (the simulator changed it): its geometry, and nothing seen in it yet."""
        self.geometry = Geometry(world, z_m)
        self._seen = deque(maxlen=self.config.memory_frames)

    # -- what is known -------------------------------------------------------------------------
    def forget(self) -> None:
        """A new episode: the frame stack restarts, and so does what the planner knows."""
        self._seen.clear()

    def observe(self, visible: frozenset[int]) -> None:
        """The obstacles (indices) and walls (wall_code) one new frame showed."""
        self._seen.append(frozenset(visible))

    def known(self) -> np.ndarray:
        """(columns,) bool: which of the geometry's footprints the plan avoids."""
        if self.config.knowledge == "all":
            return np.ones(len(self.geometry.codes), dtype=bool)
        seen = frozenset().union(*self._seen) if self._seen else frozenset()
        return np.array([int(c) in seen for c in self.geometry.codes], dtype=bool)

    # -- planning -------------------------------------------------------------------------------
    def plan(self, x_m: float, y_m: float, yaw_rad: float) -> Plan:
        """The best plan's first action from this pose, with what decided it."""
        cfg, n_act = self.config, len(self.actions)
        known = self.known()
        cols = np.flatnonzero(known)
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
            if len(cols):
                d = self.geometry.distances(xs, ys, known) - cfg.margin_m  # (plans, sub-steps, known)
                per = d.min(axis=1)  # (plans, known)
                step_clear = per.min(axis=1)
                step_bound = self.geometry.codes[cols][per.argmin(axis=1)]
                nearer = step_clear < clear
                clear = np.where(nearer, step_clear, clear)
                bound = np.where(nearer, step_bound, bound)
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
        action = int(np.argmax(scores))  # the first maximum: table order breaks ties
        reason = self._reason(action, first_safety, first_clear, first_bound)
        return Plan(action, scores, first_clear, reason)

    def _circle_free(self, x, y, yaw, known) -> np.ndarray:
        """Whether a disc of the turning circle's radius beside the end pose (left or right) is free."""
        if not known.any() or not math.isfinite(self.circle_m):
            return np.ones(len(x), dtype=bool)
        r = self.circle_m
        free = np.zeros(len(x), dtype=bool)
        for side in (1.0, -1.0):  # left, right
            cx, cy = x - side * r * np.sin(yaw), y + side * r * np.cos(yaw)
            d = self.geometry.distances(cx, cy, known).min(axis=-1) - self.config.margin_m
            free |= d >= r
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


class SimPlanner:
    """The planner on a Simulator's frames: `label()` plans for the current frame, keeping what the stack of frames
    has shown (knowledge 'stack' turns on the simulator's segmentation mask)."""

    def __init__(self, sim: Simulator, config: PlannerConfig = PlannerConfig(), actions: tuple[Action, ...] = PAPER_ACTIONS):
        self.sim = sim
        cfg = sim.config
        self.planner = Planner(sim.world, cfg.step_duration_s, cfg.physics_rate_hz, actions, config, sim.pose.z_m)
        self._world, self._episode, self._frame, self._plan = sim.world, None, None, None
        if not sim.see_bodies:  # what the frames show ('stack' plans around it) and the pixels of a plan's reason
            sim.see_bodies = True
            sim.render()  # the current frame's mask (rendering draws no random numbers)

    def reason_mask(self) -> np.ndarray:
        """The current frame's pixels that show what label()'s decision is about (its reason): a bool image."""
        return np.isin(self.sim.body_ids, self.label().reason)

    def label(self) -> Plan:
        """The plan for the simulator's current frame (the same plan when asked again before the next step)."""
        sim = self.sim
        frame = (sim.total_steps, sim.episode, id(sim.world))
        if frame == self._frame:
            return self._plan
        if sim.world is not self._world:
            self.planner.set_world(sim.world, sim.pose.z_m)
            self._world = sim.world
        if sim.episode != self._episode:
            self.planner.forget()
            self._episode = sim.episode
        self.planner.observe(sim.visible)
        pose = sim.pose
        self._frame, self._plan = frame, self.planner.plan(pose.x_m, pose.y_m, pose.yaw_rad)
        return self._plan


class PlannerAgent:
    """The planner as uav_policy.rollout.Flight's agent: it acts on the simulator's world and pose, not on the state."""

    def __init__(self, planner: SimPlanner):
        self.planner = planner

    def act(self, state: np.ndarray, epsilon: float = 0.0) -> tuple[int, np.ndarray, None, bool]:
        """(action, the plan scores per first action as its 'Q-values', no attention, never explored)."""
        plan = self.planner.label()
        return plan.action, plan.scores, None, False
