"""Integration: a Foxglove WebSocket client connects to the installed live_view, lists its channels and
receives the stack's messages, which decode as the ROS 2 messages that were published."""

from __future__ import annotations

import json
import re
import struct
import time

from nav_msgs.msg import Odometry

from conftest import deep_qos
from uav_common import contract

# foxglove-sdk speaks the Foxglove WebSocket protocol under its current name (the app offers both).
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


def test_a_foxglove_client_lists_the_channels_and_receives_odometry(ros):
    from rosbags.typesys import Stores, get_typestore
    from websockets.sync.client import connect

    pub = ros.node.create_publisher(Odometry, "/uav3/odom", deep_qos())
    view = ros.start("uav_bringup", "live_view", "-r", "__ns:=/uav3", args=["--port", "0"])
    port = []

    def announced():
        found = re.search(r"live view on ws://127\.0\.0\.1:(\d+)", ros.log_of(view))
        port[:] = [int(found.group(1))] if found else []
        return bool(port) or view.poll() is not None

    assert ros.spin_until(announced, 60) and port, ros.log_of(view)
    assert ros.spin_until(lambda: pub.get_subscription_count() > 0, 30)
    with connect(f"ws://127.0.0.1:{port[0]}", subprotocols=SUBPROTOCOLS, open_timeout=20) as ws:
        assert ws.subprotocol in SUBPROTOCOLS
        channels = {}
        while "/uav3/odom" not in channels:
            msg = json.loads(ws.recv(timeout=20))
            if msg["op"] == "advertise":
                channels.update({c["topic"]: c for c in msg["channels"]})
        odom = channels["/uav3/odom"]
        assert (odom["encoding"], odom["schemaName"], odom["schemaEncoding"]) == ("cdr", "nav_msgs/msg/Odometry", "ros2msg")
        assert "geometry_msgs/PoseWithCovariance pose" in odom["schema"]
        for topic in ("/uav3/depth/image_raw", "/uav3/attention/overlay", "/uav3/world/markers", "/uav3/q_values"):
            assert topic in channels, f"{topic} is not served: {sorted(channels)}"
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": odom["id"]}]}))
        # Until the server forwards a probe (stamp 0), the subscription may not have reached it: no fixed wait.
        probe = Odometry()
        probe.header.frame_id = "uav3/odom"
        first = None
        end = time.monotonic() + 30
        while first is None and time.monotonic() < end:
            pub.publish(probe)
            ros.executor.spin_once(timeout_sec=0.01)
            try:
                frame = ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            first = frame if isinstance(frame, bytes) else None
        assert first is not None, "the live view forwarded nothing within 30 s of the subscription"
        for k in range(5):
            m = Odometry()
            m.header.stamp = contract.stamp_from_seconds(1.0 + k)
            m.header.frame_id = "uav3/odom"
            m.pose.pose.position.y = 2.0 * k
            pub.publish(m)
        store = get_typestore(Stores.ROS2_JAZZY)
        got = []
        while len(got) < 5:
            ros.executor.spin_once(timeout_sec=0.01)
            frame = ws.recv(timeout=20)
            if isinstance(frame, str):
                continue  # status or further advertisements
            opcode, sub_id, _log_time = struct.unpack_from("<BIQ", frame)
            assert (opcode, sub_id) == (1, 7)
            m = store.deserialize_cdr(frame[13:], "nav_msgs/msg/Odometry")
            if m.header.stamp.sec > 0:  # probes still in flight are not the five
                got.append(m)
    assert [m.header.stamp.sec for m in got] == [1, 2, 3, 4, 5]
    assert [m.pose.pose.position.y for m in got] == [0.0, 2.0, 4.0, 6.0, 8.0]
    assert got[0].header.frame_id == "uav3/odom"
    assert ros.stop(view) == 0, ros.log_of(view)


def test_the_foxglove_layout_shows_only_topics_the_live_view_serves_and_every_panel_is_placed():
    from conftest import ROOT
    from uav_bringup.taps import DEFAULT_TOPICS, STACK_TOPICS, typestore

    layout = json.loads((ROOT / "src/uav_bringup/foxglove/uav_stack.json").read_text())
    panels = layout["configById"]
    served = {"/" + t.lstrip("/") for t in DEFAULT_TOPICS}
    used = set()
    for cfg in panels.values():
        used |= set(cfg.get("topics", {}))
        image = cfg.get("imageMode", {}).get("imageTopic")
        used |= {image} if image else set()
        used |= {p["value"].split(".")[0] for p in cfg.get("paths", [])}
        used |= {cfg[k].split(".")[0] for k in ("topicPath", "topicToRender") if k in cfg}
    assert used and used <= served, f"the layout shows topics nobody serves: {sorted(used - served)}"
    assert {"/world/markers", "/odom", "/trajectory", "/attention/overlay", "/depth/image_raw", "/q_values"} <= used
    # Every plotted path names a field of its topic's message type (the stack's own types included).
    types = {"/" + t.lstrip("/"): m for t, m in STACK_TOPICS.items()}
    for cfg in panels.values():
        for path in cfg.get("paths", []):
            topic, _, field = path["value"].partition(".")
            names = {name for name, _ in typestore().fielddefs[types[topic]][1]}
            assert field.split("[")[0].split(".")[0] in names, f"{path['value']}: no such field of {types[topic]}"

    def placed(node):
        return {node} if isinstance(node, str) else placed(node["first"]) | placed(node["second"])

    assert placed(layout["layout"]) == set(panels), "every configured panel is on screen, and only those"
