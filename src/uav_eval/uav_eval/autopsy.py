"""A crash autopsy for `evaluate --crash-log` (no ROS): beside the flight, the map planner (the teacher the student
could follow: uav_sim.planner with knowledge `map`) labels every frame, so that each crash says how many steps
before it the flown action last differed from the teacher's, what was hit, and whether that was in the frame the
decision was made on, only in the local map (seen in an earlier frame), or never seen; and over the flight, how often
the student flew the teacher's action on its own frames (an action the teacher scores as high as its best, a tie, is
the teacher's too)."""

from __future__ import annotations

import math

import numpy as np

from uav_common.kinematics import BodyTwist, Pose, integrate

# What the hit obstacle was to the decision that hit it.
SEEN_IN_FRAME, SEEN_IN_MAP, NEVER_SEEN = "frame", "map", "never"
FIELDS = ("steps_since_teacher_disagreed", "hit", "hit_seen")
SEEN_WORDS = {SEEN_IN_FRAME: "the frame showed", SEEN_IN_MAP: "only the map held", NEVER_SEEN: "was never seen"}


class Autopsy:
    """`before(step)` on each frame before it is acted on, `after(step, action)` once it flew; `crash(...)` names why."""

    def __init__(self, sim):
        from uav_sim.planner import PlannerConfig, SimPlanner

        self.sim = sim
        self.teacher = SimPlanner(sim, PlannerConfig(knowledge="map"))  # turns on the segmentation mask too
        self.geometry = _geometry(sim)
        self._world = sim.world
        self.last_disagreed: int | None = None
        self.agreed = self.labelled = 0  # steps flown the teacher's way (ties counted), steps labelled
        self._scores, self._visible = np.zeros(0), frozenset()

    def before(self) -> None:
        """The frame about to be decided on: the teacher's label and what it shows."""
        if self.sim.world is not self._world:
            self.geometry, self._world = _geometry(self.sim), self.sim.world
        self._scores = np.asarray(self.teacher.label().scores, dtype=np.float64)
        self._visible = self.sim.visible

    def after(self, step: int, action: int) -> None:
        self.labelled += 1
        if self._scores[action] < self._scores.max():
            self.last_disagreed = step
        else:
            self.agreed += 1

    @property
    def agreement(self) -> float:
        """The share of the steps flown the teacher's way (a tie with its best counts), -1 before any."""
        return self.agreed / self.labelled if self.labelled else -1.0

    def crash(self, step: int, pose: Pose, action) -> dict:
        """The autopsy of a crash on `step`, flown with `action` (uav_common.actions.Action) from `pose`."""
        hit = self._hit(pose, action)
        if hit is None:
            seen = NEVER_SEEN
        elif hit in self._visible:
            seen = SEEN_IN_FRAME
        else:
            seen = SEEN_IN_MAP if self._in_map(hit) else NEVER_SEEN
        since = step - self.last_disagreed if self.last_disagreed is not None else -1
        return dict(steps_since_teacher_disagreed=since, hit=hit if hit is not None else "", hit_seen=seen)

    def _hit(self, pose: Pose, action) -> int | None:
        """The obstacle or wall code (uav_sim.world) nearest to the crashing step's path."""
        cfg = self.sim.config
        n = max(1, int(math.ceil(cfg.step_duration_s * cfg.physics_rate_hz)))
        cmd = BodyTwist(action.linear_x_mps, yaw_rate_radps=action.yaw_rate_radps(cfg.step_duration_s))
        p, xs, ys = Pose(pose.x_m, pose.y_m, pose.z_m, pose.yaw_rad), [], []
        for _ in range(n):
            p = integrate(p, cmd, cfg.step_duration_s / n)
            xs.append(p.x_m)
            ys.append(p.y_m)
        d = self.geometry.distances(np.array(xs), np.array(ys)).min(axis=0)
        return int(self.geometry.codes[int(d.argmin())]) if len(d) else None

    def _in_map(self, code: int) -> bool:
        """Whether the teacher's local map had a cell on that obstacle's footprint (within 0.1 m)."""
        xy = self.teacher.map.occupied_xy()
        if not len(xy):
            return False
        column = int(np.flatnonzero(self.geometry.codes == code)[0])
        return bool((self.geometry.distances(xy[:, 0], xy[:, 1])[:, column] < 0.1).any())


def _geometry(sim):
    from uav_sim.planner import Geometry

    return Geometry(sim.world, sim.pose.z_m)
