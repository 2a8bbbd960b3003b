"""The shield: the network chooses among the actions the local map says are safe (no ROS).

Every frame goes into the local map (uav_common.local_map: the measured depth of the last frames moved by odometry,
weather filtered), and the planner's search (uav_common.plan_search) checks each of the four actions on it: does the
action, followed by the best continuation, survive the horizon and end on a free turning circle? The network's best
action among those that do flies. When none does, the planner's own choice (the safest by its ranking) flies. The
network keeps deciding, and explaining, among what is safe (Alshiekh et al. 2018, "Safe reinforcement learning via
shielding"); its unshielded choice, the action flown and why are kept with the decision and counted.

Without fresh odometry nothing can be vouched for: `check` then says so and the caller stops forward flight.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from uav_common.actions import Action
from uav_common.local_map import CAMERA_FORWARD_M, LocalMap, MapConfig, PinholeCamera, camera_position
from uav_common.plan_search import Planner, PlannerConfig
from uav_common.settings import setting

# The largest pose change between two frames still taken as motion (m); beyond it odometry was reset (or the
# simulator started a new episode): the map forgets.
JUMP_M = 3.0
SHIELD_MODES = ("auto", "always", "never")


@dataclasses.dataclass(frozen=True)
class ShieldSettings:
    """policy_node's shield (off in training: the student learns its own safety)."""

    shield: str = setting(
        "auto",
        "Shield: check each action on the local map of the last depth frames and odom (uav_policy.shield); the "
        "network's best safe action flies, the planner's when none is safe; without fresh odom forward flight stops. "
        "auto: on when flying from a camera (a drone), off for a simulator's frames; always (a simulator's frames "
        "wait for its odom of the same stamp); never (train sets it: the student learns its own safety)",
        choices=SHIELD_MODES,
    )
    odom_timeout_s: float = setting(
        0.5, "Shield: odometry older than this (against the frame's stamp) vouches for nothing: forward flight stops", 0.01, 10.0
    )
    camera_forward_m: float = setting(
        CAMERA_FORWARD_M,
        "Shield and local map: the camera's position ahead of base_link (m; sim_node's camera is 0.22 m ahead)",
        -5.0,
        5.0,
    )
    map_frames: int = setting(5, "Shield: depth frames the local map remembers", 1, 32)


@dataclasses.dataclass
class ShieldCounts:
    """What the shield did, counted since start."""

    checked: int = 0  # decisions it checked
    overridden: int = 0  # the network's choice was unsafe and another action flew
    none_safe: int = 0  # no action was safe: the planner's choice flew
    no_odometry: int = 0  # no fresh odometry: nothing vouched for

    def values(self, on: bool = True) -> dict:
        """As /diagnostics reports them."""
        return {"shield": "on" if on else "off", **{f"shield_{f.name}": getattr(self, f.name) for f in dataclasses.fields(self)}}


@dataclasses.dataclass(frozen=True)
class Verdict:
    action: int  # the action to fly
    safe: np.ndarray  # (actions,) bool: what the map vouched for (all False without odometry)
    why: str  # "" when the network's choice flies, else what the shield did
    vouched: bool = True  # False without fresh odometry: nothing was checked, forward flight must stop


class Shield:
    """`observe` each frame with its pose, then `check` the network's Q-values: the action to fly, and why."""

    def __init__(self, actions: tuple[Action, ...], step_duration_s: float, st: ShieldSettings = ShieldSettings()):
        self.st = st
        self.map = LocalMap(MapConfig(frames=st.map_frames, confirm_frames=min(3, st.map_frames)))
        # The search at the simulator's physics rate (40 Hz sub-steps: the body cannot pass a 5 cm cell unseen).
        self.search = Planner(step_duration_s, 40.0, actions, PlannerConfig(knowledge="map"))
        self.counts = ShieldCounts()
        self._pose: tuple[float, float, float] | None = None  # the vehicle's (x, y, yaw) at the newest frame
        self.last_why = ""  # what the shield did last time it changed a decision

    def reset(self) -> None:
        """Forget the map (a new episode, or odometry reset)."""
        self.map.reset()
        self._pose = None

    def observe(self, depth_m: np.ndarray, camera: PinholeCamera, x_m: float, y_m: float, z_m: float, yaw_rad: float):
        """One measured frame (metres; +Inf, NaN or 0: no return) and the vehicle's pose (base_link in the odometry
        frame) when it was taken. A jump of the pose of more than JUMP_M forgets what was mapped before."""
        if self._pose is not None and math.hypot(x_m - self._pose[0], y_m - self._pose[1]) > JUMP_M:
            self.map.reset()
        self.map.insert(depth_m, camera, *camera_position(x_m, y_m, yaw_rad, self.st.camera_forward_m), z_m, yaw_rad)
        self._pose = (x_m, y_m, yaw_rad)

    def forget_pose(self) -> None:
        """Odometry went stale: nothing is vouched for until a frame comes with fresh odometry."""
        self._pose = None

    def check(self, q: np.ndarray, choice: int) -> Verdict:
        """The action to fly for the network's `choice` made on Q-values `q`."""
        verdict = self._check(q, choice)
        self.last_why = verdict.why or self.last_why
        return verdict

    def _check(self, q: np.ndarray, choice: int) -> Verdict:
        self.counts.checked += 1
        n = len(q)
        if self._pose is None:
            self.counts.no_odometry += 1
            return Verdict(choice, np.zeros(n, dtype=bool), "shield: no fresh odometry, nothing vouched for", vouched=False)
        plan = self.search.plan(*self._pose, self.map)
        safe = np.asarray(plan.safe, dtype=bool)
        if safe[choice]:
            return Verdict(choice, safe, "")
        if safe.any():
            best = int(np.flatnonzero(safe)[np.argmax(np.asarray(q)[safe])])
            self.counts.overridden += 1
            return Verdict(best, safe, f"shield: action {choice} unsafe on the map, the network's best safe action {best}")
        self.counts.overridden += plan.action != choice
        self.counts.none_safe += 1
        return Verdict(plan.action, safe, f"shield: no action safe on the map, the planner's {plan.action}")


def pooled(depth_m: np.ndarray, camera: PinholeCamera, max_width: int = 128) -> tuple[np.ndarray, PinholeCamera]:
    """A frame wider than `max_width` pixels min-pooled (the nearest return of each block wins; no return counts as
    none) to at most that width, with its intrinsics: an 848x480 camera maps in milliseconds."""
    k = -(-depth_m.shape[1] // max_width)
    if k <= 1:
        return depth_m, camera
    h, w = (depth_m.shape[0] // k) * k, (depth_m.shape[1] // k) * k
    d = np.where(np.isfinite(depth_m[:h, :w]) & (depth_m[:h, :w] > 0), depth_m[:h, :w], np.inf)
    d = d.reshape(h // k, k, w // k, k).min(axis=(1, 3))
    return d, PinholeCamera(w // k, h // k, camera.fx / k, camera.fy / k, camera.cx / k, camera.cy / k)


class ShieldFeed:
    """policy_node's frames and odometry onto a Shield (no ROS): a simulator's frame comes with the odometry of its
    own stamp; a camera's is matched with the newest odometry, which must be within odom_timeout_s of it. With
    `needs_map` (a network with the local map) every frame is mapped, whether or not the shield checks decisions, and
    the network's state gets the map (`with_map`); without fresh odometry forward flight stops all the same."""

    def __init__(self, actions: tuple[Action, ...], step_duration_s: float, st: ShieldSettings, log, needs_map=False):
        self.shield, self.log, self.mode = Shield(actions, step_duration_s, st), log, st.shield
        self.needs_map = needs_map
        self.odom: tuple[int, tuple[float, float, float, float]] | None = None  # (stamp ns, (x, y, z, yaw))
        self.stale = 0
        self.odometry_received = 0

    def odometry(self, stamp, pose: tuple[float, float, float, float] | None) -> bool:
        """The newest odometry (its header stamp; base_link in the odometry frame: x, y, z, yaw; None: malformed,
        ignored); whether it was taken."""
        if pose is not None:
            self.odom = (stamp.sec * 1_000_000_000 + stamp.nanosec, pose)
            self.odometry_received += 1
        return pose is not None

    def on(self, camera: bool) -> bool:
        """Whether the shield checks decisions on a camera's (`camera`) or a simulator's frames."""
        return self.mode == "always" or (self.mode == "auto" and camera)

    def joins(self, camera: bool) -> bool:
        """Whether odometry is joined with a simulator's frames (shield on, no camera flying)."""
        return (self.mode == "always" or self.needs_map) and not camera

    def frame(self, depth_m, intrinsics, stamp_ns: int, pose=None, new_episode=False, camera=True) -> Shield | None:
        """A frame (metres) with its CameraInfo intrinsics ((fx, fy, cx, cy, width, height); None: unknown) and, from a
        simulator, the odometry of its stamp and whether it begins an episode (the map forgets, as in process); the
        shield to decide with, None where it is off (`camera`: a camera's frame)."""
        if not (self.on(camera) or self.needs_map):
            return None
        if new_episode:
            self.shield.reset()
        if pose is None and self.odom is not None:
            age_s = abs(stamp_ns - self.odom[0]) / 1e9
            pose = self.odom[1] if age_s <= self.shield.st.odom_timeout_s else None
        if pose is None or intrinsics is None:
            self.stale += 1
            self.shield.forget_pose()
            who = "shield" if self.on(camera) else "the network's local map"
            if intrinsics is None:  # each cause throttled on its own (a throttle is per call site)
                self.log.warning(
                    f"{who}: no depth/camera_info: nothing is vouched for, forward flight stops", throttle_duration_sec=2.0
                )
            else:
                self.log.warning(
                    f"{who}: no odometry within odom_timeout_s of the frame: nothing is vouched for, forward flight stops",
                    throttle_duration_sec=2.0,
                )
            return self.shield
        fx, fy, cx, cy, width, height = intrinsics
        if (height, width) != depth_m.shape:
            scale = depth_m.shape[1] / width  # a frame of another size than its CameraInfo: scaled alike
            fx, fy, cx, cy = fx * scale, fy * scale, cx * scale, cy * scale
        depth, view = pooled(depth_m, PinholeCamera(depth_m.shape[1], depth_m.shape[0], fx, fy, cx, cy))
        self.shield.observe(depth, view, *pose)
        return self.shield if self.on(camera) else None

    def with_map(self, state: np.ndarray, map_grid: tuple[int, float]) -> np.ndarray:
        """`state` with the local map's egocentric grid (NetConfig.map_grid) as its last channel."""
        return np.concatenate([state, self.shield.map.egocentric(*map_grid)[None]])

    def values(self, on: bool) -> dict:
        """For /diagnostics (`on`: whether it checks the decisions now)."""
        return {
            **self.shield.counts.values(on),
            "shield_odometry_received": self.odometry_received,
            "local_map_input": "on" if self.needs_map else "off",  # the network's own map (it needs odom too)
            "shield_frames_without_odometry": self.stale,
            "shield_last": self.shield.last_why,
        }
