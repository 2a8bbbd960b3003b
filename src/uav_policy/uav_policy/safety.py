"""The safety layer between the network and cmd_vel, as flight stacks put one: a stop when depth frames
stop, no forward motion while an obstacle is in the flight corridor nearer than the stop distance (turning
stays allowed), and speed and yaw-rate limits. Every intervention is counted."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from uav_common.settings import setting


@dataclasses.dataclass(frozen=True)
class SafetySettings:
    """policy_node's safety layer (train turns it off: it learns from the network's own actions)."""

    safety: bool = setting(
        True, "Safety layer between the network and cmd_vel (stop on lost frames, stop distance, limits); train sets false"
    )
    frame_timeout_s: float = setting(
        0.5,
        "Safety: with a camera (no simulator), no depth frame for this long publishes a stop (zero velocity) at "
        "control_rate_hz until frames come back",
        0.05,
        10.0,
    )
    stop_distance_m: float = setting(
        0.6, "Safety: an obstacle nearer than this in the flight corridor stops forward motion (turning allowed)", 0.0, 10.0
    )
    corridor_half_width_m: float = setting(
        0.35, "Safety: half the width and height of the flight corridor ahead (the vehicle's half-size and some room)", 0.05, 5.0
    )
    max_speed_mps: float = setting(2.0, "Safety: largest forward speed commanded (m/s)", 0.0, 20.0)
    max_yaw_rate_radps: float = setting(1.2, "Safety: largest yaw rate commanded (rad/s)", 0.0, 10.0)


@dataclasses.dataclass
class Interventions:
    """What the safety layer changed, counted since start."""

    stops_no_frames: int = 0  # stop commands published because frames stopped
    forward_blocked: int = 0  # commands whose forward motion was removed (obstacle in the corridor)
    speed_limited: int = 0
    yaw_rate_limited: int = 0

    @property
    def total(self) -> int:
        return self.stops_no_frames + self.forward_blocked + self.speed_limited + self.yaw_rate_limited

    def values(self, on: bool = True) -> dict:
        """As /diagnostics reports them (`on`: whether there is a safety layer)."""
        return {
            "safety": "on" if on else "off",
            "safety_interventions": self.total,
            **{f"safety_{f.name}": getattr(self, f.name) for f in dataclasses.fields(self)},
        }


def corridor_mask(height: int, width: int, hfov_deg: float, half_width_m: float, max_depth_m: float) -> np.ndarray:
    """(H, W, depth threshold) of the network input (square pixels, `hfov_deg`): a cell at depth z is in the
    corridor when its lateral and vertical offsets at z, |u| z / f and |v| z / f, are within half_width_m;
    returned as the largest depth at which each cell's ray is still inside (capped at max_depth_m)."""
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    u = np.abs(np.arange(width) + 0.5 - width / 2.0)
    v = np.abs(np.arange(height) + 0.5 - height / 2.0)
    off = np.maximum(v[:, None], u[None, :]) / f  # offset per metre of depth, the cell's nearer edge counted
    off = np.maximum(off - 0.5 / f, 0.0)
    with np.errstate(divide="ignore"):
        reach = np.where(off > 0, half_width_m / off, np.inf)
    return np.minimum(reach, max_depth_m).astype(np.float32)


class SafetyLayer:
    """`filter(linear_x, yaw_rate, net_input)` -> the command to fly and whether it was changed."""

    def __init__(self, st: SafetySettings, height: int, width: int, hfov_deg: float):
        self.st, self.hw = st, (height, width)
        self.counts = Interventions()
        self.escape_sign = 0.0  # while blocked: the way round, kept until clear (no left-right dithering)
        self.set_hfov(hfov_deg)

    def set_hfov(self, hfov_deg: float) -> None:
        """The network input's field of view (the corridor's place in it)."""
        self.reach = corridor_mask(*self.hw, hfov_deg, self.st.corridor_half_width_m, self.st.stop_distance_m)

    def nearest_in_corridor_m(self, depth: np.ndarray) -> float:
        """The nearest depth inside the corridor and nearer than the stop distance; +Inf when clear."""
        with np.errstate(invalid="ignore"):
            hit = depth < self.reach
        return float(depth[hit].min()) if hit.any() else math.inf

    def filter(
        self, linear_x_mps: float, yaw_rate_radps: float, depth: np.ndarray, turn_radps: float = 0.0
    ) -> tuple[float, float, str]:
        """(linear_x, yaw_rate, reason): the command within the limits, no forward motion while the corridor
        is blocked; reason is "" when nothing changed. A blocked command that does not turn turns at
        `turn_radps` (the policy's best turning action): hovering in front of the obstacle would leave
        the same view, the same choice and the vehicle stuck for good. The first blocked command's way
        round is kept until the corridor is clear, so the vehicle does not dither left and right."""
        reasons = []
        blocked = math.isfinite(self.nearest_in_corridor_m(depth))
        if not blocked:
            self.escape_sign = 0.0
        elif linear_x_mps > 0:
            linear_x_mps = 0.0
            self.counts.forward_blocked += 1
            reasons.append(f"obstacle nearer than {self.st.stop_distance_m:g} m ahead: no forward motion")
            rate = yaw_rate_radps if yaw_rate_radps != 0.0 else turn_radps
            if self.escape_sign == 0.0:
                self.escape_sign = math.copysign(1.0, rate) if rate != 0.0 else 0.0
            if rate != 0.0:
                yaw_rate_radps = self.escape_sign * abs(rate)
                reasons.append(f"turning at {yaw_rate_radps:g} rad/s until clear")
        if abs(linear_x_mps) > self.st.max_speed_mps:
            linear_x_mps = math.copysign(self.st.max_speed_mps, linear_x_mps)
            self.counts.speed_limited += 1
            reasons.append(f"speed limited to {self.st.max_speed_mps:g} m/s")
        if abs(yaw_rate_radps) > self.st.max_yaw_rate_radps:
            yaw_rate_radps = math.copysign(self.st.max_yaw_rate_radps, yaw_rate_radps)
            self.counts.yaw_rate_limited += 1
            reasons.append(f"yaw rate limited to {self.st.max_yaw_rate_radps:g} rad/s")
        return linear_x_mps, yaw_rate_radps, "; ".join(reasons)
