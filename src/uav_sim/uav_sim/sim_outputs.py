"""What sim_node publishes, and how much of it: its publishers, the episode's path (trajectory), the world's markers,
and per topic how many messages it has sent (`published TOPIC` on /diagnostics: `fly --record` pauses the simulator
and stops it only once a recorder has written, or counted lost, every one of them; at the end of a stream no later
message shows a gap)."""

from __future__ import annotations

import collections
import math
import time

from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry, Path
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image
from visualization_msgs.msg import MarkerArray

from uav_common import contract
from uav_interfaces.msg import StepOutcome, TeacherLabel

from .markers import path_msg, path_pose, world_markers

TRAJECTORY_POSES = 2000  # the longest path kept for the trajectory topic
TRAJECTORY_PERIOD_S = 0.2  # the trajectory goes out at most this often (wall time), and at episode ends


class SimOutputs:
    def __init__(self, node: Node, teacher: bool, clock: bool, odom_frame: str):
        q, pub = contract.STREAM_QOS, node.create_publisher
        self.depth = pub(Image, contract.DEPTH_TOPIC, q)
        self.info = pub(CameraInfo, contract.CAMERA_INFO_TOPIC, q)
        self.odom = pub(Odometry, contract.ODOM_TOPIC, q)
        self.outcome = pub(StepOutcome, contract.OUTCOME_TOPIC, q)
        self.teacher = pub(TeacherLabel, contract.TEACHER_TOPIC, q) if teacher else None
        self.clock = pub(Clock, "/clock", q) if clock else None
        self.diag = pub(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, 10)
        self.markers = pub(MarkerArray, contract.WORLD_MARKERS_TOPIC, contract.LATCHED_QOS)
        self.trajectory = pub(Path, contract.TRAJECTORY_TOPIC, 10)
        self.odom_frame = odom_frame
        self.marked_world = None
        self.path = collections.deque(maxlen=TRAJECTORY_POSES)
        self.path_wall = -math.inf
        self.sent: dict[str, int] = {}  # messages sent per topic (/diagnostics aside)

    def send(self, pub, msg) -> None:
        pub.publish(msg)
        self.sent[pub.topic_name] = self.sent.get(pub.topic_name, 0) + 1

    def published(self) -> dict[str, int]:
        """{`published TOPIC`: messages sent} of every topic but /diagnostics (the clock's too: a recorder may take it)."""
        pubs = (self.depth, self.info, self.odom, self.outcome, self.teacher, self.clock, self.markers, self.trajectory)
        return {f"published {p.topic_name}": self.sent.get(p.topic_name, 0) for p in pubs if p is not None}

    def world(self, world, stamp) -> None:
        """The world's markers, once per layout (the first frame, or a new layout at an episode's start)."""
        if world is not self.marked_world:
            self.marked_world = world
            self.send(self.markers, world_markers(world, self.odom_frame, stamp))

    def path_step(self, pose, new_episode: bool, stamp) -> None:
        """The path flown in this episode; sent only to listeners, at most every TRAJECTORY_PERIOD_S and with the
        complete path at each episode's end."""
        listening = self.trajectory.get_subscription_count() > 0
        now = time.monotonic()
        if listening and (new_episode or now - self.path_wall >= TRAJECTORY_PERIOD_S) and self.path:
            self.send(self.trajectory, path_msg(self.odom_frame, stamp, self.path))
            self.path_wall = now
        if new_episode:
            self.path.clear()
        self.path.append(path_pose(self.odom_frame, stamp, pose.x_m, pose.y_m, pose.z_m, pose.yaw_rad))
