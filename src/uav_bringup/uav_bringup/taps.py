"""Listening to the stack's topics as they are, for recording and the live view: raw subscriptions
(serialized CDR, never deserialized) to topics found by name, with QoS matched to their publishers,
and message definitions from rosbags' ROS 2 Jazzy type store (the PyPI set-up has no ros2cli to ask)."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from uav_common import contract

# The stack's own topics (relative to its namespace) and their types: subscribed at once, so nothing
# published after the tap starts is missed while discovery catches up. `record` and `live_view` take
# them all by default; any other topic is subscribed once it is published.
STACK_TOPICS = {
    contract.DEPTH_TOPIC: "sensor_msgs/msg/Image",
    contract.CAMERA_INFO_TOPIC: "sensor_msgs/msg/CameraInfo",
    contract.ATTENTION_TOPIC: "sensor_msgs/msg/Image",
    contract.ATTENTION_OVERLAY_TOPIC: "sensor_msgs/msg/Image",
    contract.ATTENTION_LOCAL_MAP_TOPIC: "sensor_msgs/msg/Image",
    contract.SALIENCY_TOPIC: "sensor_msgs/msg/Image",
    contract.SALIENCY_OVERLAY_TOPIC: "sensor_msgs/msg/Image",
    contract.ODOM_TOPIC: "nav_msgs/msg/Odometry",
    contract.CMD_VEL_TOPIC: "geometry_msgs/msg/Twist",
    contract.ACTION_TOPIC: "geometry_msgs/msg/TwistStamped",
    contract.Q_VALUES_TOPIC: "uav_interfaces/msg/ActionValues",
    contract.OUTCOME_TOPIC: "uav_interfaces/msg/StepOutcome",
    contract.WORLD_MARKERS_TOPIC: "visualization_msgs/msg/MarkerArray",
    contract.TRAJECTORY_TOPIC: "nav_msgs/msg/Path",
    contract.DIAGNOSTICS_TOPIC: "diagnostic_msgs/msg/DiagnosticArray",
}
DEFAULT_TOPICS = tuple(STACK_TOPICS)
LATCHED_TOPICS = (contract.WORLD_MARKERS_TOPIC,)
POLL_S = 0.5  # how often topics not yet seen are looked for
DEPTH = 1000  # per-topic reader queue: a recorder that falls behind for a moment loses nothing


def typestore():
    """The ROS 2 Jazzy message definitions and the stack's own (uav_interfaces, from its installed .msg files), loaded
    once: rosbags serializes with them and writes them into a bag as its schemas."""
    from ament_index_python.packages import get_package_share_directory
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    global _TYPESTORE
    if _TYPESTORE is None:
        store, types = get_typestore(Stores.ROS2_JAZZY), {}
        for path in sorted((Path(get_package_share_directory("uav_interfaces")) / "msg").glob("*.msg")):
            types |= get_types_from_msg(path.read_text(), f"uav_interfaces/msg/{path.stem}")
        store.register(types)
        _TYPESTORE = store
    return _TYPESTORE


_TYPESTORE = None


def message_class(msgtype: str):
    """The rclpy class of 'pkg/msg/Name' (ImportError, AttributeError if this install lacks it)."""
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def matching_qos(node: Node, topic: str) -> QoSProfile | None:
    """A subscription QoS every publisher of `topic` can serve, or None while it has none: reliable
    and transient-local only when all publishers are (so latched markers arrive to a late tap)."""
    pubs = node.get_publishers_info_by_topic(topic)
    if not pubs:
        return None
    reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
    latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


class TopicTap:
    """Subscribes `node` to each of `topics` once it has a publisher; every message goes to
    `on_message(topic, msgtype, data, receive_ns, seq)` as serialized bytes with its publication sequence number (its
    publisher's count, None where the middleware gives none: uav_bringup.accounting). `on_new(topic, msgtype)` is
    called once per topic before its first message and may return False to skip the topic."""

    def __init__(
        self,
        node: Node,
        topics,
        on_message: Callable[[str, str, bytes, int], None],
        on_new: Callable[[str, str], bool] | None = None,
    ):
        self.node = node
        self.wanted = [node.resolve_topic_name(t) for t in topics]
        self.on_message = on_message
        self.on_new = on_new or (lambda topic, msgtype: True)
        self.types: dict[str, str] = {}
        self.skipped: set[str] = set()
        self._subs = []
        known = {node.resolve_topic_name(t): (m, t in LATCHED_TOPICS) for t, m in STACK_TOPICS.items()}
        for topic in self.wanted:
            if topic in known:
                msgtype, latched = known[topic]
                qos = contract.LATCHED_QOS if latched else QoSProfile(depth=DEPTH)  # reliable, volatile: the stack's
                self._subscribe(topic, msgtype, qos)
        self.poll()
        node.create_timer(POLL_S, self.poll)

    def publishers(self) -> dict[str, int]:
        """{topic: publishers matched} of every topic subscribed."""
        return {sub.topic_name: sub.get_publisher_count() for sub in self._subs}

    @property
    def waiting(self) -> list[str]:
        return [t for t in self.wanted if t not in self.types and t not in self.skipped]

    def poll(self) -> None:
        if not self.waiting:
            return
        found = dict(self.node.get_topic_names_and_types())
        for topic in self.waiting:
            if topic not in found:
                continue
            qos = matching_qos(self.node, topic)
            if qos is None:  # only subscribers so far
                continue
            self._subscribe(topic, found[topic][0], qos)

    def _subscribe(self, topic: str, msgtype: str, qos: QoSProfile) -> None:
        try:
            cls = message_class(msgtype)
        except (ImportError, AttributeError, ValueError):
            self.node.get_logger().warning(f"skipping {topic}: type {msgtype} is not installed here")
            self.skipped.add(topic)
            return
        if not self.on_new(topic, msgtype):
            self.skipped.add(topic)
            return
        self.types[topic] = msgtype
        clock = self.node.get_clock()

        def cb(data, info, t=topic, m=msgtype):
            self.on_message(t, m, data, clock.now().nanoseconds, info.get("publication_sequence_number"))

        self._subs.append(self.node.create_subscription(cls, topic, cb, qos, raw=True))
