"""mavlink_bridge: cmd_vel to an autopilot over MAVLink. A scripted pymavlink peer on localhost UDP plays the autopilot
(heartbeats, LOCAL_POSITION_NED, ATTITUDE) and records every message the bridge sends."""

import math
import socket
import threading
import time

import pytest
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry

from uav_bringup import mavlink

PX4_OFFBOARD = 6 << 16  # PX4's custom_mode: main mode 6 (offboard) in the third byte
MAV_TYPE_QUADROTOR, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 2, 1


def test_rep103_commands_become_mavlink_body_frd_setpoints():
    """Forward stays forward; left (ROS +y) is MAVLink -y; up (ROS +z) is MAVLink -z (down positive); a left,
    counter-clockwise turn (ROS +yaw rate) is a negative MAVLink yaw rate."""
    sp, why = mavlink.to_mavlink((1.0, 0.5, 0.25), 0.4, 3.0, 1.2)
    assert (sp.vx, sp.vy, sp.vz, sp.yaw_rate) == (1.0, -0.5, -0.25, -0.4) and why == ""
    sp, why = mavlink.to_mavlink((9.0, -9.0, 0.0), -5.0, 3.0, 1.2)
    assert (sp.vx, sp.vy, sp.vz, sp.yaw_rate) == (3.0, 3.0, -0.0, 1.2) and why == "clipped to the limits"
    for bad in ((math.nan, 0.0, 0.0, 0.0), (1.0, math.inf, 0.0, 0.0), (1.0, 0.0, 0.0, -math.inf)):
        sp, why = mavlink.to_mavlink(bad[:3], bad[3], 3.0, 1.2)
        assert sp == mavlink.ZERO and why.startswith("non-finite command")
    assert mavlink.VELOCITY_YAW_RATE_MASK == 0b0000_0101_1100_0111 == 1479, "velocity and yaw rate only"


def test_ned_pose_becomes_a_rep105_enu_pose_with_a_flu_body():
    (x, y, z), q = mavlink.ned_to_enu_pose(1.0, 2.0, -3.0, 0.0, 0.0, 0.0)  # 1 m north, 2 m east, 3 m up, facing north
    assert (x, y, z) == (2.0, 1.0, 3.0)
    assert q == pytest.approx((0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4))), "north is +90 deg from east"
    _, q = mavlink.ned_to_enu_pose(0.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2)  # facing east: ENU yaw 0
    assert q == pytest.approx((0.0, 0.0, 0.0, 1.0), abs=1e-12)
    assert mavlink.ned_velocity_to_flu(0.0, 1.0, -0.5, math.pi / 2) == pytest.approx((1.0, 0.0, 0.5)), "east, facing east"
    assert mavlink.ned_velocity_to_flu(0.0, 1.0, 0.0, 0.0) == pytest.approx((0.0, -1.0, 0.0)), "east, facing north: right"


class Autopilot:
    """A scripted autopilot: heartbeats while `beating`, position and attitude, and a record of what it receives."""

    def __init__(self, port: int):
        from pymavlink import mavutil

        self.link = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
        self.received: list[tuple[float, object]] = []
        self.beating = True
        self.running = True
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        next_beat = 0.0
        while self.running:
            now = time.monotonic()
            if now >= next_beat:
                if self.beating:
                    m = self.link.mav
                    m.heartbeat_send(
                        MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PX4_OFFBOARD, 4
                    )
                    m.local_position_ned_send(0, 1.0, 2.0, -3.0, 0.0, 1.0, 0.0)
                    m.attitude_send(0, 0.0, 0.0, math.pi / 2, 0.0, 0.0, 0.0)
                next_beat = now + 0.2
            msg = self.link.recv_match(blocking=True, timeout=0.05)
            if msg is not None and msg.get_type() != "BAD_DATA":
                self.received.append((time.monotonic(), msg))

    def setpoints(self, since: float = 0.0):
        return [(t, m) for t, m in self.received if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED" and t >= since]

    def close(self):
        self.running = False
        self.thread.join(timeout=5)
        self.link.close()


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_bridge_streams_converted_setpoints_stops_safely_and_never_takes_control(ros):
    port = free_udp_port()
    proc = ros.start(
        "uav_bringup",
        "mavlink_bridge",
        "-p",
        f"url:=udpin:127.0.0.1:{port}",
        "-p",
        "rate_hz:=20.0",
        "-p",
        "cmd_timeout_s:=0.3",
        "-p",
        "heartbeat_timeout_s:=1.0",
    )
    pub = ros.node.create_publisher(Twist, "cmd_vel", 10)
    odom = []
    ros.node.create_subscription(Odometry, "odom", odom.append, 10)
    ap = Autopilot(port)
    try:
        cmd = Twist()
        cmd.linear.x, cmd.angular.z = 1.5, 0.5  # forward, turning left

        def drive(until, timeout_s=20.0):
            end = time.monotonic() + timeout_s
            while time.monotonic() < end and not until():
                pub.publish(cmd)
                ros.spin_for(0.05)
            return until()

        moving = lambda: [m for _, m in ap.setpoints() if m.vx == 1.5]  # noqa: E731
        assert drive(lambda: len(moving()) >= 40), ros.log_of(proc)
        sp = moving()[-1]
        assert (sp.coordinate_frame, sp.type_mask) == (mavlink.MAV_FRAME_BODY_NED, 1479)
        assert (sp.vy, sp.vz) == (0.0, 0.0) and sp.yaw_rate == pytest.approx(-0.5), "a left turn is a negative yaw rate"
        assert (sp.target_system, sp.target_component) == (1, 1)
        times = [t for t, m in ap.setpoints() if m.vx == 1.5][-40:]
        rate = (len(times) - 1) / (times[-1] - times[0])
        assert 10.0 < rate < 30.0, f"{rate:.1f} setpoints/s streamed at rate_hz 20"
        # NaN never reaches the autopilot: it becomes a stop.
        cmd.linear.x = math.nan
        t_nan = time.monotonic()
        assert drive(lambda: len([m for _, m in ap.setpoints(t_nan) if m.vx == 0.0]) >= 5)
        assert all(math.isfinite(m.vx) and math.isfinite(m.yaw_rate) for _, m in ap.setpoints())
        # cmd_vel stops: zero velocity within cmd_timeout_s, streamed on.
        t_stop = time.monotonic()
        assert ros.spin_until(lambda: len(ap.setpoints(t_stop + 0.5)) >= 5, 20)
        late = ap.setpoints(t_stop + 0.5)
        assert all((m.vx, m.vy, m.vz, m.yaw_rate) == (0.0, 0.0, 0.0, 0.0) for _, m in late)
        # The autopilot's state comes back as odometry in REP 105 frames.
        assert ros.spin_until(lambda: odom, 10)
        p = odom[-1].pose.pose.position
        assert (p.x, p.y, p.z) == pytest.approx((2.0, 1.0, 3.0)) and odom[-1].header.frame_id == "odom"
        # A lost heartbeat: said in the log, and the stream stops.
        ap.beating = False
        assert ros.spin_until(lambda: "heartbeat lost" in ros.log_of(proc), 20), ros.log_of(proc)
        t_lost = time.monotonic()
        ros.spin_for(1.0)
        assert ap.setpoints(t_lost + 0.2) == [], "no setpoints while the autopilot is not heard"
        kinds = {m.get_type() for _, m in ap.received}
        assert {"SET_POSITION_TARGET_LOCAL_NED", "HEARTBEAT"} <= kinds
        assert not kinds & {"COMMAND_LONG", "COMMAND_INT", "SET_MODE"}, f"the bridge tried to take control: {kinds}"
        log = ros.log_of(proc)
        assert "PX4 in OFFBOARD, disarmed: the pilot must arm (the bridge never does)" in log, log
    finally:
        ap.close()


def test_a_bad_url_stops_the_bridge_at_start_up_naming_it():
    from conftest import run_to_exit

    r = run_to_exit("uav_bringup", "mavlink_bridge", "-p", "url:=udpin:999.1.1.1:14540")
    assert r.returncode == 2 and "parameter 'url'" in r.stderr, r.stderr
    r = run_to_exit("uav_bringup", "mavlink_bridge", "-p", "rate_hz:=1.0")
    assert r.returncode == 2 and "rate_hz" in r.stderr, r.stderr
