"""mavlink_bridge: cmd_vel to a PX4 or ArduPilot autopilot over MAVLink, on the pip install (no MAVROS).

    ros2 run uav_bringup mavlink_bridge --ros-args -p url:=udpin:0.0.0.0:14540

Streams the newest command as a body-frame velocity and yaw-rate setpoint at rate_hz (uav_bringup.mavlink does the
frame conversion), zero velocity when cmd_vel has been silent for cmd_timeout_s, and nothing while the autopilot's
heartbeat is lost. It never arms, takes off or switches modes: it says on /diagnostics and in its log what the pilot
must do. With publish_odometry the autopilot's position and attitude come back as `odom` (REP 105).

One vehicle: `target_system` (0: the first autopilot heard, then kept); other systems' messages are ignored and
counted. With `signing_key_file`, MAVLink 2 signing: every message out is signed, every unsigned or wrongly signed
message in refused and counted (docs/REAL_CAMERA.md, "Flying a real vehicle").
"""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node

from uav_common import contract
from uav_common.node_runner import run
from uav_common.ros_params import ParameterError
from uav_common.settings import declare_settings

from . import mavlink

HEARTBEAT_PERIOD_S = 1.0  # this bridge's own heartbeat
DIAGNOSTICS_PERIOD_S = 1.0


class MavlinkBridge(Node):
    def __init__(self, **node_options):
        super().__init__("mavlink_bridge", **node_options)
        self.st = st = declare_settings(self, mavlink.BridgeSettings)
        try:
            key = mavlink.read_signing_key(st.signing_key_file) if st.signing_key_file else None
        except ValueError as e:
            raise ParameterError(f"parameter 'signing_key_file': {e}") from None
        try:
            self.mav = mavlink.connect(st.url, st.baud, st.source_system, st.source_component, mavlink2=key is not None)
        except ValueError as e:
            raise ParameterError(f"parameter 'url': {e}") from None
        self.signing = mavlink.sign(self.mav, key) if key is not None else None
        self.autopilot = mavlink.Autopilot(st.target_system, st.target_component)
        self.foreign_told: set[int] = set()
        self.start = time.monotonic()
        self.command = mavlink.ZERO
        self.last_cmd: float | None = None
        self.sent = self.zeros_sent = self.bad_commands = 0
        self.streaming = False
        self.advice = ""
        self.yaw_ned = 0.0
        self.frame_odom = contract.vehicle_frame(self.get_namespace(), "odom")
        self.frame_base = contract.vehicle_frame(self.get_namespace(), "base_link")
        if st.stamped:
            self.create_subscription(TwistStamped, contract.CMD_VEL_STAMPED_TOPIC, lambda m: self._on_cmd(m.twist), 10)
        else:
            self.create_subscription(Twist, contract.CMD_VEL_TOPIC, self._on_cmd, 10)
        self.pub_odom = self.create_publisher(Odometry, contract.ODOM_TOPIC, 10) if st.publish_odometry else None
        self.pub_diag = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, 10)
        self.create_timer(1.0 / st.rate_hz, self._tick)
        self.create_timer(HEARTBEAT_PERIOD_S, lambda: mavlink.send_heartbeat(self.mav.mav))
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._diagnose)
        which = f"system {st.target_system}" if st.target_system else "the first autopilot heard"
        self.get_logger().info(
            f"MAVLink on {st.url}{' (signed)' if self.signing else ''}: waiting for the heartbeat of {which}; "
            f"setpoints at {st.rate_hz:g} Hz from "
            f"{contract.CMD_VEL_STAMPED_TOPIC if st.stamped else contract.CMD_VEL_TOPIC} (zero after {st.cmd_timeout_s:g} s "
            "without a command). This bridge never arms or switches modes."
        )

    def _on_cmd(self, twist: Twist) -> None:
        linear = (twist.linear.x, twist.linear.y, twist.linear.z)
        sp, why = mavlink.to_mavlink(linear, twist.angular.z, self.st.max_linear_mps, self.st.max_yaw_rate_radps)
        if why.startswith("non-finite"):
            self.bad_commands += 1
            self.get_logger().warning(why, throttle_duration_sec=5.0)
        self.command, self.last_cmd = sp, time.monotonic()

    def _receive(self, now: float) -> None:
        """Everything the autopilot sent since the last tick."""
        while True:
            try:
                msg = self.mav.recv_match(blocking=False)
            except (OSError, ValueError) as e:  # a garbled packet or a dropped link: pymavlink reconnects
                self.get_logger().warning(f"MAVLink receive: {e}", throttle_duration_sec=5.0)
                return
            if msg is None:
                return
            kind = msg.get_type()
            if kind == "HEARTBEAT":
                if self.autopilot.heard(msg, now):
                    advice = self.autopilot.advice()
                    if advice != self.advice:
                        self.advice = advice
                        self.get_logger().info(advice)
            elif kind in ("ATTITUDE", "LOCAL_POSITION_NED") and self.autopilot.ours(msg):
                if kind == "ATTITUDE":
                    self.attitude = (msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed)
                    self.yaw_ned = msg.yaw
                elif self.pub_odom is not None:
                    self._publish_odometry(msg)
            for system in set(self.autopilot.foreign) - self.foreign_told:
                self.foreign_told.add(system)
                self.get_logger().warning(
                    f"MAVLink system {system} is not the commanded vehicle (system {self.autopilot.system or '-'}): "
                    "its messages are ignored"
                )

    def _tick(self) -> None:
        now = time.monotonic()
        self._receive(now)
        alive = self.autopilot.alive(now, self.st.heartbeat_timeout_s)
        if alive != self.streaming:
            self.streaming = alive
            if alive:
                ap = self.autopilot
                self.get_logger().info(
                    f"{ap.name} heard: commanding system {ap.system}, component {ap.component}; streaming setpoints"
                )
            else:
                self.get_logger().error(
                    f"{self.autopilot.name} heartbeat lost for {self.st.heartbeat_timeout_s:g} s: "
                    "setpoints stopped until it is heard again"
                )
        if not alive:
            return
        fresh = self.last_cmd is not None and now - self.last_cmd <= self.st.cmd_timeout_s
        sp = self.command if fresh else mavlink.ZERO
        mavlink.send_setpoint(self.mav.mav, self.autopilot.system, self.autopilot.component, sp, mavlink.boot_ms(self.start))
        self.sent += 1
        self.zeros_sent += not fresh

    def _publish_odometry(self, msg) -> None:
        roll, pitch, yaw, rs, ps, ys = getattr(self, "attitude", (0.0, 0.0, self.yaw_ned, 0.0, 0.0, 0.0))
        (x, y, z), q = mavlink.ned_to_enu_pose(msg.x, msg.y, msg.z, roll, pitch, yaw)
        odom = Odometry()
        odom.header.stamp = self.get_clock().now().to_msg()
        odom.header.frame_id, odom.child_frame_id = self.frame_odom, self.frame_base
        odom.pose.pose.position.x, odom.pose.pose.position.y, odom.pose.pose.position.z = x, y, z
        o = odom.pose.pose.orientation
        o.x, o.y, o.z, o.w = q
        v = odom.twist.twist.linear
        v.x, v.y, v.z = mavlink.ned_velocity_to_flu(msg.vx, msg.vy, msg.vz, yaw)
        w = odom.twist.twist.angular
        w.x, w.y, w.z = rs, -ps, -ys
        self.pub_odom.publish(odom)

    def _diagnose(self) -> None:
        now = time.monotonic()
        ap = self.autopilot
        age = "-" if ap.last_heartbeat is None else f"{now - ap.last_heartbeat:.1f}"
        level, message = "OK", self.advice or "waiting for the autopilot's heartbeat"
        if ap.last_heartbeat is None:
            level = "WARN"
        elif not self.streaming:
            level, message = "ERROR", f"{ap.name} heartbeat lost: not streaming"
        elif not (ap.armed and ap.mode.upper() == mavlink.CONTROL_MODES.get(ap.autopilot)):
            level = "WARN"
        values = {
            "url": self.st.url,
            "autopilot": ap.name if ap.heartbeats else "-",
            "mode": ap.mode,
            "armed": str(ap.armed).lower(),
            "heartbeat_age_s": age,
            "streaming": str(self.streaming).lower(),
            "setpoints_sent": self.sent,
            "zero_setpoints_sent": self.zeros_sent,
            "non_finite_commands": self.bad_commands,
            "target_system": ap.system or "-",
            "target_component": ap.component or "-",
            "other_systems_seen": ap.foreign_systems,
            "other_system_messages_ignored": sum(ap.foreign.values()),
            "signing": "on" if self.signing else "off",
            "unsigned_refused": self.signing.unsigned if self.signing else 0,
            "bad_signature_refused": self.signing.bad_signature if self.signing else 0,
            "last_command_frd": ", ".join(
                f"{v:.2f}" for v in (self.command.vx, self.command.vy, self.command.vz, self.command.yaw_rate)
            ),
        }
        self.pub_diag.publish(contract.diagnostics(self, "uav_bringup/mavlink_bridge", level, message, values))

    def close(self) -> None:
        """Zero velocity once more on the way out (the autopilot then holds, or leaves offboard on its own timeout)."""
        if self.streaming:
            mavlink.send_setpoint(
                self.mav.mav, self.autopilot.system, self.autopilot.component, mavlink.ZERO, mavlink.boot_ms(self.start)
            )
        self.mav.close()


def main(args=None) -> int:
    return run(MavlinkBridge, args)


if __name__ == "__main__":
    raise SystemExit(main())
