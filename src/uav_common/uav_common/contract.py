"""The ROS contract shared by every node: topic names, QoS, message conversions, stamp joins.

Pairing by stamp: every message of one simulator step carries the same `header.stamp` (the sim time of the frame).
The policy's `action` (TwistStamped) carries the stamp of the frame it answered, and so does a teacher's label
(`teacher_label`, uav_interfaces/TeacherLabel: sim_node's planner's action, its score for every action and the
pixels its decision is about). `step_outcome` (uav_interfaces/StepOutcome) carries, with the frame's stamp, what the
step that produced the frame ended in: it continued the episode (beta_m: the reward's depth, the centre window's
minimum depth), it collided (the frame is the first of a new episode), or a new episode began without a collision
(the time limit `max_episode_steps`, or `~/reset`): the step that led to it has no outcome to learn from.
"""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

from uav_interfaces.msg import ActionValues, AttentionWeights, StepOutcome

DEPTH_TOPIC = "depth/image_raw"
CAMERA_INFO_TOPIC = "depth/camera_info"
ODOM_TOPIC = "odom"
OUTCOME_TOPIC = "step_outcome"
CMD_VEL_TOPIC = "cmd_vel"
CMD_VEL_STAMPED_TOPIC = "cmd_vel_stamped"
ACTION_TOPIC = "action"
# Training with a teacher: sim_node's planner's label for a frame (uav_interfaces/TeacherLabel, the frame's stamp: its
# action, its score for each action, the frame's pixels its decision is about), paired by trainer_node like the
# policy's `action`. Its knowledge: none (no teacher), or uav_sim.planner's stack, all or map.
TEACHER_TOPIC = "teacher_label"
TEACHERS = ("none", "stack", "all", "map")
Q_VALUES_TOPIC = "q_values"
ATTENTION_TOPIC = "attention"
ATTENTION_OVERLAY_TOPIC = "attention/overlay"
ATTENTION_WEIGHTS_TOPIC = "attention/weights"
ATTENTION_LOCAL_MAP_TOPIC = "attention/local_map"  # a network with the local map: what it weighs there, top-down
SALIENCY_TOPIC = "saliency"  # the CNN's Grad-CAM: never called attention
SALIENCY_OVERLAY_TOPIC = "saliency/overlay"
WORLD_MARKERS_TOPIC = "world/markers"
TRAJECTORY_TOPIC = "trajectory"
DIAGNOSTICS_TOPIC = "/diagnostics"
PUSH_WEIGHTS_SERVICE = "policy_node/push_weights"

# Lockstep needs every message: reliable, with room for bursts.
STREAM_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=100)
# What every decision says (commands, actions, Q-values, attention maps: small messages): kept 1000 deep, so a recorder
# that falls seconds behind on a busy machine loses none (100 lost a few a minute beside the main job).
DECISION_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=1000)
# For consumers that must not lose anything even when they lag (the trainer): the reader's DDS
# history holds the backlog (64x64 frames: ~16 KiB each).
DEEP_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=5000)
# The key prefix of a recorder's per-topic count of messages lost to it, in its /diagnostics and its bag's metadata.
LOST_KEY = "lost "
# What camera drivers publish with (rclpy's sensor-data profile): best effort, a few frames. A best-effort
# reader takes both these and sim_node's reliable frames; a lost simulator frame is said again by sim_node.
SENSOR_QOS = QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST, depth=5)
# State that a late subscriber must still get (the world's markers): the last message is kept for it.
LATCHED_QOS = QoSProfile(
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


def vehicle_frame(namespace: str, name: str) -> str:
    """A frame of this vehicle: `name` prefixed with the node's namespace (`/uav1`: `uav1/odom`), so that
    two vehicles never share one `odom`; in the root namespace, or when `name` holds a '/', as given."""
    ns = namespace.strip("/")
    return f"{ns}/{name}" if ns and "/" not in name else name


def stamp_from_seconds(t_s: float) -> Time:
    ns = int(round(t_s * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def stamp_ns(stamp: Time) -> int:
    """A header stamp as one integer (ns): the join key."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def depth_to_image(depth_m: np.ndarray, stamp: Time, frame_id: str, encoding: str = "32FC1") -> Image:
    """REP 118 depth image, depth along the optical axis: 32FC1 in metres (+Inf: nothing in range), or
    16UC1 in millimetres as camera drivers publish it (0: no return; beyond 65.534 m: no return)."""
    h, w = depth_m.shape
    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = h, w
    msg.encoding = encoding
    msg.is_bigendian = 0
    if encoding == "16UC1":
        with np.errstate(invalid="ignore"):
            mm = np.rint(np.asarray(depth_m, dtype=np.float64) * 1000.0)
            mm[~((mm > 0) & (mm < 65535))] = 0
        msg.step = 2 * w
        msg.data = mm.astype("<u2").tobytes()
    elif encoding == "32FC1":
        msg.step = 4 * w
        msg.data = np.ascontiguousarray(depth_m, dtype="<f4").tobytes()
    else:
        raise ValueError(f"depth encoding must be one of {sorted(DEPTH_ENCODINGS)}, got {encoding!r}")
    return msg


DEPTH_ENCODINGS = {"32FC1": "f4", "16UC1": "u2"}  # REP 118: metres as float, millimetres as uint16


def image_to_depth(msg: Image) -> np.ndarray:
    """A (H, W) float32 depth array in metres from a REP 118 depth Image: 32FC1 (metres) or 16UC1
    (millimetres, 0 = no return, read as +Inf: nothing in range), either byte order. ValueError says
    what is malformed."""
    kind = DEPTH_ENCODINGS.get(msg.encoding)
    if kind is None:
        raise ValueError(f"depth image encoding must be 32FC1 or 16UC1, got '{msg.encoding}'")
    size = int(kind[1])
    h, w = int(msg.height), int(msg.width)
    if h <= 0 or w <= 0:
        raise ValueError(f"depth image has an empty size {w}x{h}")
    if msg.step < size * w:
        raise ValueError(f"depth image step {msg.step} is smaller than {size}*width={size * w}")
    if len(msg.data) != msg.step * h:  # shorter or longer than the header says: not this image
        raise ValueError(f"depth image data has {len(msg.data)} bytes, expected {msg.step * h}")
    dtype = (">" if msg.is_bigendian else "<") + kind
    rows = np.frombuffer(bytes(msg.data[: msg.step * h]), dtype=np.uint8).reshape(h, msg.step)
    values = rows[:, : size * w].copy().view(dtype).reshape(h, w)
    if kind == "u2":
        depth = values.astype(np.float32) / 1000.0
        depth[values == 0] = np.inf
        return depth
    return values.astype(np.float32)


def mask_to_image(mask: np.ndarray, stamp: Time, frame_id: str) -> Image:
    """A bool (H, W) mask as a mono8 Image: 255 where set."""
    h, w = mask.shape
    msg = Image(height=h, width=w, encoding="mono8", is_bigendian=0, step=w)
    msg.header.stamp, msg.header.frame_id = stamp, frame_id
    msg.data = np.where(np.asarray(mask, dtype=bool), np.uint8(255), np.uint8(0)).tobytes()
    return msg


def image_to_mask(msg: Image) -> np.ndarray:
    """The bool (H, W) mask of a mono8 Image (set where not 0); ValueError says what is malformed."""
    h, w = int(msg.height), int(msg.width)
    if msg.encoding != "mono8" or h <= 0 or w <= 0 or msg.step < w or len(msg.data) != msg.step * h:
        raise ValueError(f"a mask must be a mono8 image with step * height bytes, got {msg.encoding} {w}x{h}")
    return np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(h, msg.step)[:, :w] != 0


def diagnostics(node, name: str, level: str, message: str, values: dict) -> DiagnosticArray:
    """A one-status /diagnostics message from `node` (level: OK, WARN or ERROR), values as strings."""
    st = DiagnosticStatus(level=getattr(DiagnosticStatus, level), name=name, message=message)
    st.hardware_id = node.get_fully_qualified_name()
    st.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
    msg = DiagnosticArray(status=[st])
    msg.header.stamp = node.get_clock().now().to_msg()
    return msg


def rgb_image(header, rgb: np.ndarray) -> Image:
    """An rgb8 Image of an (H, W, 3) uint8 array."""
    h, w = rgb.shape[:2]
    return Image(header=header, height=h, width=w, encoding="rgb8", is_bigendian=0, step=3 * w, data=rgb.tobytes())


def action_values_msg(header, q: np.ndarray, names: tuple[str, ...], action: int) -> ActionValues:
    """The network's value of each action (named) for the frame of `header`, and the action it chose."""
    return ActionValues(header=header, actions=list(names), values=q.astype(np.float32).tolist(), action=int(action))


def attention_weights_msg(header, w: np.ndarray, grid_hw: tuple[int, int]) -> AttentionWeights:
    """SAM's raw attention the decision uses [heads, queries, key_nodes] for the frame of `header`, nodes row-major
    on the grid: the relational block's (queries = the nodes) or the attention readout's (one query per head); a
    network with the local map has the map's cells after the image's."""
    h, n, k = w.shape
    rows, cols = grid_hw
    msg = AttentionWeights(header=header, heads=h, queries=n, grid_rows=rows, grid_cols=cols, map_cells=k - rows * cols)
    msg.weights = w.astype(np.float32).ravel().tolist()
    return msg


def make_outcome(
    beta_m: float,
    collided: bool,
    stamp: Time,
    frame_id: str,
    min_range_m: float,
    max_range_m: float,
    fov_rad: float,
    truncated: bool = False,
    reset: bool = False,
) -> StepOutcome:
    """The outcome of the step that produced the frame at `stamp`: a collision, a new episode without one (`truncated`:
    the time limit, or with `reset` too sim_node's ~/reset), or a step that continued the episode with depth beta_m."""
    event = (
        StepOutcome.COLLIDED
        if collided
        else (StepOutcome.RESET if reset else StepOutcome.TIME_LIMIT)
        if truncated
        else StepOutcome.CONTINUES
    )
    msg = StepOutcome(event=event, beta_m=0.0 if event != StepOutcome.CONTINUES else float(beta_m))
    msg.header.stamp, msg.header.frame_id = stamp, frame_id
    msg.min_range_m, msg.max_range_m, msg.window_fov_rad = float(min_range_m), float(max_range_m), float(fov_rad)
    return msg


def outcome_collided(msg: StepOutcome) -> bool:
    return msg.event == StepOutcome.COLLIDED


def outcome_truncated(msg: StepOutcome) -> bool:
    """The frame starts a new episode that began without a collision (time limit or reset)."""
    return msg.event in (StepOutcome.TIME_LIMIT, StepOutcome.RESET)


def outcome_new_episode(msg: StepOutcome) -> bool:
    return msg.event != StepOutcome.CONTINUES


def outcome_beta(msg: StepOutcome) -> float:
    """The reward's depth of a step (0 after a collision), within the camera's range (a faulty publisher's NaN: 0)."""
    if outcome_collided(msg) or math.isnan(msg.beta_m):
        return 0.0
    return min(max(float(msg.beta_m), 0.0), float(msg.max_range_m))


def camera_info_intrinsics(msg) -> tuple[float, float, float, float, int, int] | None:
    """(fx, fy, cx, cy, width, height) of a sensor_msgs/CameraInfo; None when unusable (a zero focal length)."""
    try:
        fx, fy, cx, cy = (float(msg.k[i]) for i in (0, 4, 2, 5))
        width, height = int(msg.width), int(msg.height)
    except (AttributeError, IndexError, TypeError, ValueError):
        return None
    values = (fx, fy, cx, cy)
    if not all(math.isfinite(v) for v in values) or fx <= 0 or fy <= 0 or width <= 0 or height <= 0:
        return None
    return fx, fy, cx, cy, width, height


def odometry_pose(msg) -> tuple[float, float, float, float] | None:
    """(x, y, z, yaw) of a nav_msgs/Odometry's pose (REP 105: base_link in odom); None when not finite."""
    try:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
        pose = (float(p.x), float(p.y), float(p.z), yaw)
    except (AttributeError, TypeError, ValueError):
        return None
    return pose if all(math.isfinite(v) for v in pose) else None


def camera_info_hfov_deg(msg) -> float | None:
    """Horizontal field of view (deg) of a sensor_msgs/CameraInfo: 2 atan((w/2) / fx); None if malformed."""
    try:
        width, fx = float(msg.width), float(msg.k[0])
    except (AttributeError, IndexError, TypeError, ValueError):
        return None
    if not (width > 0 and math.isfinite(fx) and fx > 0):
        return None
    return math.degrees(2.0 * math.atan(width / 2.0 / fx))


class StampJoiner:
    """Joins messages from several streams by exact stamp (a small TimeSynchronizer).

    `add(stream, stamp_ns, item)` returns {stream: item} once every stream has an item with
    that stamp, else None. Incomplete stamps older than `max_pending` newer ones are
    dropped and counted per missing stream in `dropped` - never guessed.

    Each stream is ordered (one reliable publisher), so an item stamped before the newest completed
    stamp, and not awaited, means its source restarted (a simulator's clock starts again) or that
    stamp was a glitch far in the future: the joiner starts afresh, counts it in `restarts`, and
    joins from that item on. An item at the newest completed stamp again is a duplicate (`late`).
    """

    def __init__(self, streams: tuple[str, ...], max_pending: int = 200):
        self.streams = tuple(streams)
        self.max_pending = max_pending
        self.pending: OrderedDict[int, dict] = OrderedDict()
        self.dropped = {s: 0 for s in self.streams}
        self.duplicates = 0
        self.late = 0
        self.restarts = 0
        self._last_done = None

    def add(self, stream: str, stamp: int, item) -> dict | None:
        if stream not in self.dropped:
            raise KeyError(f"unknown stream '{stream}'")
        if self._last_done is not None and stamp not in self.pending:
            if stamp == self._last_done:
                self.late += 1  # said again after it was completed (a republished frame)
                return None
            if stamp < self._last_done:  # the source went back in time: start afresh
                self.restarts += 1
                self.pending.clear()
                self._last_done = None
        slot = self.pending.setdefault(stamp, {})
        if stream in slot:
            self.duplicates += 1
            return None
        slot[stream] = item
        if len(slot) == len(self.streams):
            del self.pending[stamp]
            # Everything older than a completed stamp can no longer complete in order.
            for old in [s for s in self.pending if s < stamp]:
                self._drop(old)
            self._last_done = stamp
            return slot
        while len(self.pending) > self.max_pending:
            self._drop(next(iter(self.pending)))
        return None

    def _drop(self, stamp: int) -> None:
        """Give up on an incomplete stamp. Only completed stamps move the join forward, so a lone item
        stamped far in the future is dropped in time and never silences the stamps after it."""
        slot = self.pending.pop(stamp)
        for s in self.streams:
            if s not in slot:
                self.dropped[s] += 1
