"""The simulator's state as ROS messages: the vehicle's odometry, the depth camera's CameraInfo and a teacher's label
(the world and the path flown are in markers.py, the frames and step outcomes in uav_common.contract)."""

from __future__ import annotations

import math

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo

from uav_common import contract
from uav_common.kinematics import BodyTwist
from uav_common.plan_search import Plan
from uav_interfaces.msg import TeacherLabel


def teacher_label_msg(plan: Plan, reason: np.ndarray, stamp, frame_id: str) -> TeacherLabel:
    """The teacher's label for the frame at `stamp`: its action, its score for each action, and `reason` (a bool mask
    of the frame's pixels its decision is about)."""
    msg = TeacherLabel(action=int(plan.action), scores=[float(v) for v in plan.scores])
    msg.header.stamp, msg.header.frame_id = stamp, frame_id
    msg.reason = contract.mask_to_image(reason, stamp, frame_id)
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
