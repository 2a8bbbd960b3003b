"""The world as RViz/Foxglove sees it: room, floor and obstacles as a visualization_msgs/MarkerArray,
and the vehicle's path in the current episode as a nav_msgs/Path, both in the vehicle's odom frame
(the simulator's world frame)."""

from __future__ import annotations

import math

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from visualization_msgs.msg import Marker, MarkerArray

from .world import World

WALL_THICKNESS_M = 0.1  # as the simulator builds them (simulator.py:_build_world)
WALL_RGBA = (0.6, 0.6, 0.65, 0.25)
FLOOR_RGBA = (0.35, 0.35, 0.35, 1.0)
OBSTACLE_RGBA = (0.85, 0.45, 0.15, 0.9)


def _marker(ns: str, mid: int, kind: int, frame_id: str, stamp, xyz, size, yaw_deg: float, rgba) -> Marker:
    m = Marker(ns=ns, id=mid, type=kind, action=Marker.ADD)
    m.header.frame_id = frame_id
    m.header.stamp = stamp
    m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in xyz)
    m.pose.orientation.z = math.sin(math.radians(yaw_deg) / 2)
    m.pose.orientation.w = math.cos(math.radians(yaw_deg) / 2)
    m.scale.x, m.scale.y, m.scale.z = (float(v) for v in size)
    m.color.r, m.color.g, m.color.b, m.color.a = (float(v) for v in rgba)
    return m


def world_markers(world: World, frame_id: str, stamp) -> MarkerArray:
    """DELETEALL, then the floor, the four walls (ns `walls`) and one marker per obstacle (ns
    `obstacles`, in the world file's order: CUBE or CYLINDER at its size)."""
    clear = Marker(action=Marker.DELETEALL)
    clear.header.frame_id = frame_id
    clear.header.stamp = stamp
    L, W, H, t = world.length_m, world.width_m, world.wall_height_m, WALL_THICKNESS_M
    out = [clear, _marker("floor", 0, Marker.CUBE, frame_id, stamp, (0, 0, -t / 2), (L, W, t), 0.0, FLOOR_RGBA)]
    walls = [
        ((L / 2 + t / 2, 0, H / 2), (t, W + 2 * t, H)),
        ((-L / 2 - t / 2, 0, H / 2), (t, W + 2 * t, H)),
        ((0, W / 2 + t / 2, H / 2), (L + 2 * t, t, H)),
        ((0, -W / 2 - t / 2, H / 2), (L + 2 * t, t, H)),
    ]
    out += [_marker("walls", i, Marker.CUBE, frame_id, stamp, c, s, 0.0, WALL_RGBA) for i, (c, s) in enumerate(walls)]
    for i, o in enumerate(world.obstacles):
        centre = (o.x_m, o.y_m, o.height_m / 2)
        if o.shape == "box":
            size, kind = (o.size_x_m, o.size_y_m, o.height_m), Marker.CUBE
        else:
            size, kind = (2 * o.radius_m, 2 * o.radius_m, o.height_m), Marker.CYLINDER
        out.append(_marker("obstacles", i, kind, frame_id, stamp, centre, size, o.yaw_deg, OBSTACLE_RGBA))
    return MarkerArray(markers=out)


def path_pose(frame_id: str, stamp, x: float, y: float, z: float, yaw_rad: float) -> PoseStamped:
    ps = PoseStamped()
    ps.header.frame_id = frame_id
    ps.header.stamp = stamp
    ps.pose.position.x, ps.pose.position.y, ps.pose.position.z = float(x), float(y), float(z)
    ps.pose.orientation.z, ps.pose.orientation.w = math.sin(yaw_rad / 2), math.cos(yaw_rad / 2)
    return ps


def path_msg(frame_id: str, stamp, poses) -> Path:
    msg = Path(poses=list(poses))
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    return msg
