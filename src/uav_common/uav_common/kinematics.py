"""Quadrotor kinematics: body-frame velocity commands (REP 103) integrated at the physics rate.

The vehicle is modelled as a velocity-controlled multirotor: the flight controller tracks
the commanded body velocity and yaw rate, so a step integrates the command exactly
(unicycle model plus vertical speed). Roll and pitch rates (angular.x, angular.y) are not
commandable on a multirotor's velocity interface and are ignored.
"""

from __future__ import annotations

import dataclasses
import math

from .settings import setting


@dataclasses.dataclass(frozen=True)
class BodyTwist:
    """Commanded body-frame velocity: x forward, y left, z up (m/s); yaw rate left-positive (rad/s)."""

    vx_mps: float = 0.0
    vy_mps: float = 0.0
    vz_mps: float = 0.0
    yaw_rate_radps: float = 0.0


HOVER = BodyTwist()


@dataclasses.dataclass(frozen=True)
class TwistLimits:
    max_speed_mps: float = setting(3.0, "Largest |linear.x| and |linear.y| accepted (m/s)", 0.1, 20.0)
    max_climb_mps: float = setting(1.0, "Largest |linear.z| accepted (m/s)", 0.0, 5.0)
    max_yaw_rate_radps: float = setting(2.0, "Largest |angular.z| accepted (rad/s)", 0.1, 10.0)


def twist_error(t: BodyTwist, limits: TwistLimits) -> str | None:
    """Why a command cannot be executed, or None if it is valid."""
    for name, v, lim in (
        ("linear.x", t.vx_mps, limits.max_speed_mps),
        ("linear.y", t.vy_mps, limits.max_speed_mps),
        ("linear.z", t.vz_mps, limits.max_climb_mps),
        ("angular.z", t.yaw_rate_radps, limits.max_yaw_rate_radps),
    ):
        if not math.isfinite(v):
            return f"{name} is {v}, not a finite number"
        if abs(v) > lim:
            return f"{name}={v:.3f} exceeds the limit of +/-{lim}"
    return None


@dataclasses.dataclass
class Pose:
    x_m: float
    y_m: float
    z_m: float
    yaw_rad: float


def integrate(pose: Pose, cmd: BodyTwist, dt_s: float) -> Pose:
    """Exact constant-twist motion over dt (an arc when turning)."""
    wz = cmd.yaw_rate_radps
    yaw0 = pose.yaw_rad
    yaw1 = yaw0 + wz * dt_s
    if abs(wz) < 1e-9:
        c, s = math.cos(yaw0) * dt_s, math.sin(yaw0) * dt_s
        dx = cmd.vx_mps * c - cmd.vy_mps * s
        dy = cmd.vx_mps * s + cmd.vy_mps * c
    else:
        # Integral of R(yaw(t)) v over dt.
        sin_d = (math.sin(yaw1) - math.sin(yaw0)) / wz
        cos_d = (math.cos(yaw0) - math.cos(yaw1)) / wz
        dx = cmd.vx_mps * sin_d - cmd.vy_mps * cos_d
        dy = cmd.vx_mps * cos_d + cmd.vy_mps * sin_d
    yaw1 = math.atan2(math.sin(yaw1), math.cos(yaw1))
    return Pose(pose.x_m + dx, pose.y_m + dy, pose.z_m + cmd.vz_mps * dt_s, yaw1)
