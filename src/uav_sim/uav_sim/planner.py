"""The planner in the simulator: uav_common.plan_search's search on what a frame stack can know (no ROS, no torch).

What it knows (`knowledge`):
- `stack`: the world's obstacles and walls that the last `memory_frames` depth frames showed (an obstacle or wall is
  known once one of its pixels, nearer than the camera's range, was in one of them: pybullet's segmentation mask);
- `all`: every obstacle and wall of the world (the task's limit with these four actions);
- `map`: the local map (uav_common.local_map) of the last `memory_frames` *measured* frames moved by odometry, weather
  filtered: nothing of the world's geometry, so a drone can plan the same way.
A new episode forgets. Its decision has a reason: for `stack` and `all` the obstacles and walls that bound its plans,
for `map` the map cells that do, shown by the pixels that put them there.
"""

from __future__ import annotations

import math

import numpy as np

from uav_common.actions import PAPER_ACTIONS, Action
from uav_common.local_map import LocalMap, MapConfig, PinholeCamera
from uav_common.plan_search import Plan, Planner, PlannerConfig

from .simulator import Simulator
from .world import World, wall_code

__all__ = ["Geometry", "Plan", "PlannerAgent", "PlannerConfig", "SimPlanner"]


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


class KnownGeometry:
    """The Clearance of the footprints and walls of a Geometry that `known` marks (one bool per column)."""

    def __init__(self, geometry: Geometry, known: np.ndarray):
        self.geometry, self.known = geometry, known
        self.codes = geometry.codes[known]

    def clearance(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x_m)
        if not len(self.codes):
            return np.full(x.shape, np.inf), np.full(x.shape, -1, dtype=np.int64)
        d = self.geometry.distances(x, y_m, self.known)
        at = d.argmin(axis=-1)
        return np.take_along_axis(d, at[..., None], axis=-1)[..., 0], self.codes[at]


class SimPlanner:
    """The planner on a Simulator's frames: `label()` plans for the current frame, keeping what the frames have shown
    (knowledge 'stack' turns on the simulator's segmentation mask; 'map' maps its measured frames)."""

    def __init__(
        self,
        sim: Simulator,
        config: PlannerConfig = PlannerConfig(),
        actions: tuple[Action, ...] = PAPER_ACTIONS,
        map_config: MapConfig | None = None,
    ):
        config.validate()
        self.sim, self.config = sim, config
        cfg = sim.config
        self.search = Planner(cfg.step_duration_s, cfg.physics_rate_hz, actions, config)
        self.map = LocalMap(map_config or MapConfig(frames=config.memory_frames)) if config.knowledge == "map" else None
        self.geometry: Geometry | None = None
        self._seen: list[frozenset[int]] = []
        self._world, self._episode, self._frame, self._plan = None, None, None, None
        if not sim.see_bodies:  # what the frames show ('stack' plans around it) and the pixels of a plan's reason
            sim.see_bodies = True
            sim.render()  # the current frame's mask (rendering draws no random numbers)

    def known(self) -> np.ndarray:
        """(columns,) bool: which of the world's footprints a geometry planner avoids."""
        codes = self.geometry.codes
        if self.config.knowledge == "all":
            return np.ones(len(codes), dtype=bool)
        seen = frozenset().union(*self._seen)
        return np.array([int(c) in seen for c in codes], dtype=bool)

    def reason_mask(self) -> np.ndarray:
        """The current frame's pixels that show what label()'s decision is about (its reason): a bool image."""
        reason = self.label().reason
        if self.map is not None:
            return self.map.pixels_near(reason) if reason else np.zeros(self.sim.body_ids.shape, dtype=bool)
        return np.isin(self.sim.body_ids, reason)

    def label(self) -> Plan:
        """The plan for the simulator's current frame (the same plan when asked again before the next step)."""
        sim = self.sim
        frame = (sim.total_steps, sim.episode, id(sim.world))
        if frame == self._frame:
            return self._plan
        if sim.world is not self._world:
            self.geometry, self._world = Geometry(sim.world, sim.pose.z_m), sim.world
            self._seen, self._episode = [], None
        if sim.episode != self._episode:
            self._seen = []
            if self.map is not None:
                self.map.reset()
            self._episode = sim.episode
        pose = sim.pose
        if self.map is not None:
            cam = sim.camera.intrinsics
            x, y, z = sim.camera_xyz()
            self.map.insert(sim.measured, PinholeCamera.from_fov(cam.width, cam.height, cam.hfov_deg), x, y, z, pose.yaw_rad)
            known = self.map
        else:
            self._seen = [*self._seen, sim.visible][-self.config.memory_frames :]
            known = KnownGeometry(self.geometry, self.known())
        self._frame, self._plan = frame, self.search.plan(pose.x_m, pose.y_m, pose.yaw_rad, known)
        return self._plan


class PlannerAgent:
    """The planner as uav_policy.rollout.Flight's agent: it acts on the simulator's world and pose, not on the state."""

    def __init__(self, planner: SimPlanner):
        self.planner = planner

    def act(self, state: np.ndarray, epsilon: float = 0.0) -> tuple[int, np.ndarray, None, bool]:
        """(action, the plan scores per first action as its 'Q-values', no attention, never explored)."""
        plan = self.planner.label()
        return plan.action, plan.scores, None, False
