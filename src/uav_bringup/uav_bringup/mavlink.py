"""Velocity commands to a PX4 or ArduPilot autopilot over MAVLink, and its state back (pymavlink; no ROS).

Frames, done here once:
- ROS (REP 103) body frame: x forward, y left, z up; yaw rate counter-clockwise (seen from above) is positive.
- MAVLink body frame (MAV_FRAME_BODY_NED): x forward, y right, z down; yaw rate clockwise is positive.
So (vx, vy, vz, yaw_rate) in MAVLink is (x, -y, -z, -yaw_rate) of the ROS command: a left turn in `cmd_vel`
(angular.z > 0) is a negative MAVLink yaw rate.

A setpoint is SET_POSITION_TARGET_LOCAL_NED (message 84) in MAV_FRAME_BODY_NED with the position, acceleration and
yaw fields ignored (type_mask 0x5C7 = 1479): velocity and yaw rate only, which PX4 takes in offboard mode and
ArduPilot Copter in guided mode. Nothing here arms, takes off or changes modes: no COMMAND_LONG or SET_MODE is sent.
"""

from __future__ import annotations

import dataclasses
import math
import time

from uav_common.settings import setting

MAV_FRAME_BODY_NED = 8
# Ignore position (1, 2, 4), acceleration (64, 128, 256) and yaw (1024): velocity (8, 16, 32) and yaw rate (2048) act.
VELOCITY_YAW_RATE_MASK = 1 | 2 | 4 | 64 | 128 | 256 | 1024
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4 = 3, 12
MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER = 6, 18
MAV_AUTOPILOT_INVALID, MAV_STATE_ACTIVE = 8, 4
# The mode a pilot switches to for the setpoints to act, by autopilot.
CONTROL_MODES = {MAV_AUTOPILOT_PX4: "OFFBOARD", MAV_AUTOPILOT_ARDUPILOTMEGA: "GUIDED"}


@dataclasses.dataclass(frozen=True)
class BridgeSettings:
    """mavlink_bridge's parameters (declared once here; params/mavlink_bridge.yaml and docs/PARAMETERS.md follow)."""

    url: str = setting(
        "udpin:0.0.0.0:14540",
        "MAVLink connection as pymavlink and MAVSDK write it: udpin:HOST:PORT (listen; PX4 SITL's offboard port 14540), "
        "udpout:HOST:PORT, tcp:HOST:PORT, or a serial device /dev/ttyACM0 with baud",
    )
    baud: int = setting(57600, "Serial baud rate (serial urls only)", 1200, 4_000_000)
    rate_hz: float = setting(20.0, "Setpoints streamed per second (PX4 offboard needs a steady stream above 2 Hz)", 2.0, 100.0)
    cmd_timeout_s: float = setting(
        0.5, "No cmd_vel for this long streams zero velocity (the safety layer's frame_timeout_s)", 0.05, 10.0
    )
    heartbeat_timeout_s: float = setting(
        3.0, "No autopilot heartbeat for this long: streaming stops until it is heard again", 0.5, 60.0
    )
    max_linear_mps: float = setting(3.0, "Largest speed along any axis streamed; larger commands are clipped", 0.0, 20.0)
    max_yaw_rate_radps: float = setting(1.2, "Largest yaw rate streamed (rad/s); larger commands are clipped", 0.0, 10.0)
    stamped: bool = setting(False, "Subscribe to cmd_vel_stamped (TwistStamped) instead of cmd_vel (Twist)")
    source_system: int = setting(1, "This bridge's MAVLink system id (the autopilot's companion: usually 1)", 1, 255)
    source_component: int = setting(191, "This bridge's MAVLink component id (191: onboard computer)", 1, 255)
    publish_odometry: bool = setting(
        True, "Publish the autopilot's LOCAL_POSITION_NED and ATTITUDE as odom (nav_msgs/Odometry, REP 105 frames)"
    )
    target_system: int = setting(
        0,
        "The vehicle commanded and reported: its MAVLink system id; 0 = the first autopilot heard, then kept (another "
        "system's messages are ignored and counted; a lost target stops the stream, never switches vehicle)",
        0,
        255,
    )
    target_component: int = setting(
        0, "The autopilot's component id within target_system; 0 = the first heard, then kept (usually 1)", 0, 255
    )
    signing_key_file: str = setting(
        "",
        "MAVLink 2 signing: a file holding the 32-byte secret (raw, or 64 hex digits), the key ArduPilot's SETUP_SIGNING "
        "and pymavlink use; outgoing messages are signed, unsigned or wrongly signed ones refused and counted; "
        "'' = no signing",
    )


@dataclasses.dataclass(frozen=True)
class Setpoint:
    """Body velocity (m/s) and yaw rate (rad/s) in MAVLink's FRD body frame."""

    vx: float
    vy: float
    vz: float
    yaw_rate: float


ZERO = Setpoint(0.0, 0.0, 0.0, 0.0)


def to_mavlink(linear_xyz, yaw_rate_ccw: float, max_linear: float, max_yaw_rate: float) -> tuple[Setpoint, str]:
    """A REP 103 body twist as a MAVLink setpoint, clipped to the limits; (ZERO, why) for a value that is not finite,
    which never reaches the autopilot. The second item says what was changed ("" when nothing)."""
    values = (*linear_xyz, yaw_rate_ccw)
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
        return ZERO, f"non-finite command {values} replaced by zero velocity"
    x, y, z = (max(-max_linear, min(max_linear, float(v))) for v in linear_xyz)
    w = max(-max_yaw_rate, min(max_yaw_rate, float(yaw_rate_ccw)))
    clipped = (x, y, z, w) != tuple(float(v) for v in values)
    return Setpoint(x, -y, -z, -w), "clipped to the limits" if clipped else ""


def send_setpoint(mav, target_system: int, target_component: int, sp: Setpoint, time_boot_ms: int) -> None:
    """SET_POSITION_TARGET_LOCAL_NED: velocity and yaw rate in the body frame, everything else ignored."""
    mav.set_position_target_local_ned_send(
        time_boot_ms & 0xFFFFFFFF,
        target_system,
        target_component,
        MAV_FRAME_BODY_NED,
        VELOCITY_YAW_RATE_MASK,
        0.0,
        0.0,
        0.0,
        sp.vx,
        sp.vy,
        sp.vz,
        0.0,
        0.0,
        0.0,
        0.0,
        sp.yaw_rate,
    )


@dataclasses.dataclass
class Autopilot:
    """The one vehicle the bridge commands and reports, and what its heartbeats said.

    `target_system` / `target_component` 0 take the first autopilot heard and keep it: once locked, messages
    from any other system (or another component of the system) are never taken, only counted in `foreign`."""

    target_system: int = 0
    target_component: int = 0
    system: int = 0  # the vehicle locked on (0: none yet)
    component: int = 0
    autopilot: int = -1
    mode: str = "-"
    armed: bool = False
    last_heartbeat: float | None = None  # time.monotonic() of the last one
    heartbeats: int = 0
    foreign: dict = dataclasses.field(default_factory=dict)  # system id -> its messages ignored

    def ours(self, msg) -> bool:
        """True for a message of the commanded vehicle; another system's is counted in `foreign`. Before a
        heartbeat has locked a vehicle, only a heartbeat (heard()) can be taken."""
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        wanted = self.system or self.target_system
        if wanted and src != wanted:
            self.foreign[src] = self.foreign.get(src, 0) + 1
            return False
        return bool(self.system) and comp == self.component

    def heard(self, msg, now: float) -> bool:
        """Take a HEARTBEAT; True when it is the commanded vehicle's autopilot (not another vehicle's, a GCS's or a
        companion's). The first one that fits target_system/target_component locks the vehicle."""
        if msg.type in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER) or msg.autopilot == MAV_AUTOPILOT_INVALID:
            return False
        if not self.system:
            src, comp = msg.get_srcSystem(), msg.get_srcComponent()
            if self.target_system and src != self.target_system:
                self.foreign[src] = self.foreign.get(src, 0) + 1
                return False
            if self.target_component and comp != self.target_component:
                return False
            self.system, self.component = src, comp
        elif not self.ours(msg):
            return False
        from pymavlink import mavutil

        self.autopilot = msg.autopilot
        self.mode = mavutil.mode_string_v10(msg)
        self.armed = bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
        self.last_heartbeat, self.heartbeats = now, self.heartbeats + 1
        return True

    @property
    def foreign_systems(self) -> str:
        return ", ".join(str(s) for s in sorted(self.foreign)) or "-"

    def alive(self, now: float, timeout_s: float) -> bool:
        return self.last_heartbeat is not None and now - self.last_heartbeat <= timeout_s

    @property
    def name(self) -> str:
        return {MAV_AUTOPILOT_PX4: "PX4", MAV_AUTOPILOT_ARDUPILOTMEGA: "ArduPilot"}.get(
            self.autopilot, f"autopilot {self.autopilot}"
        )

    def advice(self) -> str:
        """What the pilot must do for the setpoints to act (the bridge never does it)."""
        wanted = CONTROL_MODES.get(self.autopilot, "OFFBOARD (PX4) or GUIDED (ArduPilot)")
        if self.mode.upper() == wanted and self.armed:
            return f"{self.name} is armed in {self.mode}: the setpoints act"
        todo = [] if self.armed else ["arm"]
        todo += [] if self.mode.upper() == wanted else [f"switch to {wanted}"]
        state = f"{self.name} in {self.mode}, {'armed' if self.armed else 'disarmed'}"
        return f"{state}: the pilot must {' and '.join(todo)} (the bridge never does)"


def read_signing_key(path: str) -> bytes:
    """The 32-byte MAVLink 2 signing secret in `path`: 32 raw bytes, or 64 hex digits (whitespace around them
    ignored). ValueError saying why not."""
    import os

    try:
        data = open(os.path.expanduser(path), "rb").read(200)
    except OSError as e:
        raise ValueError(f"cannot read '{path}': {e.strerror or e}") from None
    if len(data) == 32:
        return data
    try:
        key = bytes.fromhex(data.decode("ascii").strip())
    except (UnicodeDecodeError, ValueError):
        key = b""
    if len(key) != 32:
        raise ValueError(f"'{path}' holds {len(data)} bytes: a signing key is 32 raw bytes or 64 hex digits")
    return key


class SigningCounts:
    """Incoming messages refused by MAVLink 2 signing, read from pymavlink's counters."""

    def __init__(self, mav):
        self.signing = mav.signing

    @property
    def bad_signature(self) -> int:
        return self.signing.badsig_count

    @property
    def unsigned(self) -> int:  # refused without a signature (a refused bad signature counts in both of pymavlink's)
        return self.signing.reject_count - self.signing.badsig_count


def sign(link, key: bytes) -> SigningCounts:
    """Sign everything sent on `link` with `key` and refuse every incoming message not signed with it."""
    link.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda _mav, _msg_id: False)
    return SigningCounts(link.mav)


def connect(url: str, baud: int, source_system: int, source_component: int, mavlink2: bool = False):
    """A pymavlink connection; ValueError naming the url when it cannot be opened. `mavlink2` speaks MAVLink 2 from
    the first message (signing needs it; otherwise pymavlink starts with 1 and follows the autopilot to 2)."""
    import os

    from pymavlink import mavutil

    if mavlink2 and not os.environ.get("MAVLINK20"):
        os.environ["MAVLINK20"] = "1"  # pymavlink picks the protocol of its dialect module from this
        mavutil.set_dialect(mavutil.current_dialect)

    try:
        return mavutil.mavlink_connection(
            url, baud=baud, source_system=source_system, source_component=source_component, autoreconnect=True
        )
    except Exception as e:  # pymavlink raises OSError, ValueError, serial errors ...
        raise ValueError(f"cannot open MAVLink connection '{url}': {e}") from None


def send_heartbeat(mav) -> None:
    """This bridge's own heartbeat (an onboard controller), so the autopilot sees its companion."""
    mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE)


def boot_ms(start: float) -> int:
    return int((time.monotonic() - start) * 1000)


def ned_to_enu_pose(x_n: float, y_e: float, z_d: float, roll: float, pitch: float, yaw_ned: float):
    """LOCAL_POSITION_NED / ATTITUDE (NED world, FRD body) as a REP 105 pose: position in ENU (x east, y north, z
    up) and the FLU body's orientation quaternion (x, y, z, w)."""
    yaw = math.pi / 2 - yaw_ned  # heading from north, clockwise -> from east, counter-clockwise
    r, p = roll, -pitch
    cr, sr, cp, sp, cy, sy = (
        math.cos(r / 2),
        math.sin(r / 2),
        math.cos(p / 2),
        math.sin(p / 2),
        math.cos(yaw / 2),
        math.sin(yaw / 2),
    )
    q = (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)
    return (y_e, x_n, -z_d), q


def ned_velocity_to_flu(vx_n: float, vy_e: float, vz_d: float, yaw_ned: float) -> tuple[float, float, float]:
    """A world NED velocity in the vehicle's heading frame (FLU, roll and pitch left out)."""
    c, s = math.cos(yaw_ned), math.sin(yaw_ned)
    forward = c * vx_n + s * vy_e
    right = -s * vx_n + c * vy_e
    return forward, -right, -vz_d
