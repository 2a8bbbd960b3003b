"""The simulator's state as ROS messages: the vehicle's odometry, the depth camera's CameraInfo and a teacher's action
(the world and the path flown are in markers.py, the frames and step outcomes in uav_common.contract)."""

from __future__ import annotations

import math

from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo

from uav_common.actions import PAPER_ACTIONS
from uav_common.kinematics import BodyTwist


def teacher_msg(action: int, stamp, base_frame: str, step_duration_s: float) -> TwistStamped:
    """The teacher's action for the frame at `stamp` as the body command it flies (as policy_node's `action`)."""
    a = PAPER_ACTIONS[action]
    msg = TwistStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = base_frame
    msg.twist.linear.x, msg.twist.angular.z = a.linear_x_mps, a.yaw_rate_radps(step_duration_s)
    return msg


def odometry_msg(pose, flown: BodyTwist, stamp, odom_frame: str, base_frame: str) -> Odometry:
    """The pose after a step, and the body velocity `flown` during it."""
    msg = Odometry()
    msg.header.stamp = stamp
    msg.header.frame_id = odom_frame
    msg.child_frame_id = base_frame
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = pose.x_m, pose.y_m, pose.z_m
    msg.pose.pose.orientation.z = math.sin(pose.yaw_rad / 2)
    msg.pose.pose.orientation.w = math.cos(pose.yaw_rad / 2)
    msg.twist.twist.linear.x, msg.twist.twist.linear.y = flown.vx_mps, flown.vy_mps
    msg.twist.twist.linear.z, msg.twist.twist.angular.z = flown.vz_mps, flown.yaw_rate_radps
    return msg


def camera_info_msg(stamp, frame_id: str, width: int, height: int, k) -> CameraInfo:
    """A pinhole camera without distortion, its intrinsic matrix `k` (row-major 3x3)."""
    info = CameraInfo()
    info.header.stamp = stamp
    info.header.frame_id = frame_id
    info.width, info.height = width, height
    info.distortion_model = "plumb_bob"
    info.d = [0.0] * 5
    info.k = k
    info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    info.p = [k[0], 0.0, k[2], 0.0, 0.0, k[4], k[5], 0.0, 0.0, 0.0, 1.0, 0.0]
    return info
