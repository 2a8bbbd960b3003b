"""mavlink_bridge: cmd_vel to an autopilot over MAVLink. A scripted pymavlink peer on localhost UDP plays the autopilot
(heartbeats, LOCAL_POSITION_NED, ATTITUDE) and records every message the bridge sends."""

import math
import os
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

    def __init__(self, port: int, system: int = 1, north_m: float = 1.0, key: bytes | None = None):
        from pymavlink import mavutil

        if key is not None and mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
            os.environ["MAVLINK20"] = "1"  # signing is MAVLink 2's: this process speaks it from here on
            mavutil.set_dialect(mavutil.current_dialect)

        self.link = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=system, source_component=1)
        if key is not None:  # signs what it sends (MAVLink 2); takes what it receives unsigned too
            self.link.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda _mav, _id: True)
        self.north_m = north_m
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
                    m.local_position_ned_send(0, self.north_m, 2.0, -3.0, 0.0, 1.0, 0.0)
                    m.attitude_send(0, 0.0, 0.0, math.pi / 2, 0.0, 0.0, 0.0)
                next_beat = now + 0.2
            msg = self.link.recv_match(blocking=True, timeout=0.05)
            if msg is not None and msg.get_type() != "BAD_DATA":
                self.received.append((time.monotonic(), msg))

    def received_setpoints(self):
        """Every setpoint this autopilot's socket received, whichever system it targets."""
        return [(t, m) for t, m in self.received if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]

    def setpoints(self, since: float = 0.0):
        """The setpoints that target this autopilot."""
        mine = self.link.mav.srcSystem
        return [(t, m) for t, m in self.received_setpoints() if t >= since and m.target_system == mine]

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


def bridge_diagnostics(ros):
    from diagnostic_msgs.msg import DiagnosticArray

    seen = {}

    def take(msg):
        for status in msg.status:
            if status.name.endswith("mavlink_bridge"):
                seen.update({kv.key: kv.value for kv in status.values}, level=status.level)

    ros.node.create_subscription(DiagnosticArray, "/diagnostics", take, 10)
    return seen


def start_bridge(ros, port: int, *params: str):
    args = [f"url:=udpin:127.0.0.1:{port}", "rate_hz:=20.0", "heartbeat_timeout_s:=1.0", *params]
    return ros.start("uav_bringup", "mavlink_bridge", *(x for p in args for x in ("-p", p)))


@pytest.mark.parametrize("target", [1, 0])
def test_two_autopilots_on_one_link_the_bridge_commands_and_reports_one_vehicle(ros, target):
    """Systems 2 and 1 on one UDP link, system 2 heard first: with target_system 1 every setpoint targets 1 and odom is
    vehicle 1's (north 10 m); with the default (0), the first heard, system 2 (north 20 m), and never a switch."""
    port = free_udp_port()
    proc = start_bridge(ros, port, f"target_system:={target}")
    odom = []
    ros.node.create_subscription(Odometry, "odom", odom.append, 10)
    diag = bridge_diagnostics(ros)
    second = Autopilot(port, system=2, north_m=20.0)
    first = None
    try:
        # The bridge hears system 2 alone before system 1 speaks.
        assert ros.spin_until(lambda: second.setpoints() or "is not the commanded vehicle" in ros.log_of(proc), 20)
        first = Autopilot(port, system=1, north_m=10.0)
        want = target or 2
        t0 = time.monotonic()
        late = lambda: [t for t, _ in first.received_setpoints() if t > t0 + 1.0]  # noqa: E731 (both hear every one)
        assert ros.spin_until(lambda: len(late()) >= 20 and len(odom) >= 10, 30), ros.log_of(proc)
        targets = {m.target_system for ap in (first, second) for _, m in ap.received_setpoints()}
        assert targets == {want}, f"setpoints targeted systems {targets}"
        norths = {round(o.pose.pose.position.y, 3) for o in odom}
        assert norths == {10.0 if want == 1 else 20.0}, f"odom mixed vehicles: north {norths}"
        other = 2 if want == 1 else 1
        assert ros.spin_until(lambda: diag.get("other_systems_seen") == str(other), 10), diag
        assert int(diag["other_system_messages_ignored"]) > 10 and diag["target_system"] == str(want)
        assert f"commanding system {want}, component 1" in ros.log_of(proc)
        # The commanded vehicle falls silent: the stream stops; the other vehicle is never taken instead.
        (first if want == 1 else second).beating = False
        assert ros.spin_until(lambda: "heartbeat lost" in ros.log_of(proc), 20), ros.log_of(proc)
        t_lost = time.monotonic()
        ros.spin_for(1.5)
        assert not [m for ap in (first, second) for t, m in ap.received_setpoints() if t > t_lost + 0.2]
    finally:
        second.close()
        if first is not None:
            first.close()


def test_signed_links_refuse_unsigned_and_wrongly_signed_autopilots(ros, tmp_path):
    """signing_key_file: an unsigned autopilot and one signing with another key are refused and counted (no setpoint
    goes to them, no odom comes from them); one with the key is commanded, and what the bridge sends is signed."""
    key = bytes(range(32))
    (tmp_path / "key").write_text(key.hex() + "\n")
    port = free_udp_port()
    proc = start_bridge(ros, port, f"signing_key_file:={tmp_path / 'key'}")
    odom = []
    ros.node.create_subscription(Odometry, "odom", odom.append, 10)
    diag = bridge_diagnostics(ros)
    for who in (dict(), dict(key=bytes(32))):  # unsigned, then signed with another key
        ap = Autopilot(port, **who)
        try:
            counter = "unsigned_refused" if not who else "bad_signature_refused"
            assert ros.spin_until(lambda c=counter: int(diag.get(c, 0)) >= 10, 20), diag
            assert not ap.setpoints() and not odom and diag["target_system"] == "-", "a refused autopilot is never taken"
        finally:
            ap.close()
    ap = Autopilot(port, key=key)
    try:
        assert ros.spin_until(lambda: len(ap.setpoints()) >= 10 and odom, 20), ros.log_of(proc)
        assert ap.link.mav.signing.sig_count >= 10, "the bridge signs what it sends"
        assert "(signed)" in ros.log_of(proc) and diag["signing"] == "on"
    finally:
        ap.close()


def test_a_bad_signing_key_stops_the_bridge_naming_it(tmp_path):
    from conftest import run_to_exit

    (tmp_path / "short").write_bytes(b"0123")
    for path, said in ((tmp_path / "short", "holds 4 bytes"), (tmp_path / "none", "cannot read")):
        r = run_to_exit("uav_bringup", "mavlink_bridge", "-p", f"signing_key_file:={path}")
        assert r.returncode == 2 and "parameter 'signing_key_file'" in r.stderr and said in r.stderr, r.stderr
