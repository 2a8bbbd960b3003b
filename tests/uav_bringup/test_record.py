"""Integration: the installed `record` executable writes rosbag2 bags (MCAP) that read back complete."""

from __future__ import annotations

import os
import subprocess
import time

import numpy as np
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Image
from visualization_msgs.msg import Marker, MarkerArray

from conftest import deep_qos, executable, read_bag
from uav_common import contract


class RecordCounts:
    """What the recorder says on /diagnostics it has written, per topic."""

    def __init__(self, ros):
        self.counts: dict[str, int] = {}
        ros.node.create_subscription(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, self.on, 10)

    def on(self, msg):
        for st in msg.status:
            if st.name == "uav_bringup/record":
                self.counts = {kv.key: kv.value for kv in st.values}

    def of(self, topic: str) -> int:
        return int(self.counts.get(topic, 0))


def odom(k: int) -> Odometry:
    m = Odometry()
    m.header.stamp = contract.stamp_from_seconds(0.5 * k)
    m.header.frame_id = "uav9/odom"
    m.pose.pose.position.x = float(k)
    return m


def start_recorder(ros, bag, *topics, ns="/uav9"):
    return ros.start("uav_bringup", "record", "-r", f"__ns:={ns}", args=["-o", str(bag), "--topics", *topics])


def test_a_recorded_bag_reads_back_with_its_topics_types_counts_and_stamps(ros, tmp_path):
    n = ros.node
    markers = n.create_publisher(MarkerArray, "/uav9/world/markers", contract.LATCHED_QOS)
    box = Marker(ns="obstacles", id=0, type=Marker.CUBE)
    box.scale.x = 1.5
    markers.publish(MarkerArray(markers=[box]))  # before the recorder exists: latched, it must still arrive
    pub_odom = n.create_publisher(Odometry, "/uav9/odom", deep_qos())
    pub_depth = n.create_publisher(Image, "/uav9/depth/image_raw", deep_qos())
    counts = RecordCounts(ros)
    bag = tmp_path / "flight"
    rec = start_recorder(ros, bag, "odom", "depth/image_raw", "world/markers", "/diagnostics")
    assert ros.spin_until(lambda: pub_odom.get_subscription_count() and pub_depth.get_subscription_count(), 30)
    frames = 120
    for k in range(frames):
        pub_odom.publish(odom(k))
        depth = np.full((8, 8), 1.0 + k, np.float32)
        pub_depth.publish(contract.depth_to_image(depth, contract.stamp_from_seconds(0.5 * k), "uav9/cam"))
    assert ros.spin_until(lambda: counts.of("/uav9/odom") == frames and counts.of("/uav9/depth/image_raw") == frames, 30), (
        f"the recorder reports {counts.counts}"
    )
    assert counts.of("/uav9/world/markers") == 1
    assert ros.stop(rec) == 0, ros.log_of(rec)

    assert sorted(p.name for p in bag.iterdir()) == ["flight.mcap", "metadata.yaml"]
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["storage_identifier"] == "mcap"
    got = read_bag(bag)
    assert got["/uav9/odom"][0] == "nav_msgs/msg/Odometry"
    assert got["/uav9/depth/image_raw"][0] == "sensor_msgs/msg/Image"
    assert got["/uav9/world/markers"][0] == "visualization_msgs/msg/MarkerArray"
    odoms = got["/uav9/odom"][1]
    assert len(odoms) == frames
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in odoms]
    assert stamps[0] == 0 and stamps[-1] == int(0.5e9) * (frames - 1) and stamps == sorted(stamps)
    assert [m.pose.pose.position.x for m in odoms] == [float(k) for k in range(frames)]
    images = got["/uav9/depth/image_raw"][1]
    assert len(images) == frames and images[-1].encoding == "32FC1"
    last = np.frombuffer(bytes(images[-1].data), "<f4")
    assert np.all(last == frames)  # the data itself survives, not only the headers
    assert got["/uav9/world/markers"][1][0].markers[0].scale.x == 1.5
    by_topic = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert by_topic["/uav9/odom"] == frames and by_topic["/uav9/depth/image_raw"] == frames

    # What Foxglove and rosbag2's MCAP plugin read: checked with Foxglove's own MCAP reader.
    from mcap.reader import make_reader

    with open(bag / "flight.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        kinds = {(c.message_encoding, summary.schemas[c.schema_id].encoding) for c in summary.channels.values()}
        assert kinds == {("cdr", "ros2msg")}
        names = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert names["/uav9/odom"] == "nav_msgs/msg/Odometry"
        assert summary.statistics.message_count == meta["message_count"] == len(list(reader.iter_messages()))


def test_a_bag_stopped_by_sigint_mid_stream_is_complete_and_readable(ros, tmp_path):
    pub = ros.node.create_publisher(Odometry, "/uav9/odom", deep_qos())
    counts = RecordCounts(ros)
    bag = tmp_path / "interrupted"
    rec = start_recorder(ros, bag, "odom")
    assert ros.spin_until(lambda: pub.get_subscription_count() > 0, 30)
    k = 0
    while counts.of("/uav9/odom") < 200:  # still streaming when the signal lands
        pub.publish(odom(k))
        k += 1
        ros.executor.spin_once(timeout_sec=0.002)
    assert ros.stop(rec) == 0, ros.log_of(rec)
    odoms = read_bag(bag)["/uav9/odom"][1]
    assert len(odoms) >= 200
    xs = [m.pose.pose.position.x for m in odoms]
    assert xs == [float(i) for i in range(len(xs))], "a gap-free prefix of what was published"
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["message_count"] == len(odoms)
    assert "closed" in ros.log_of(rec)


def test_record_refuses_an_existing_bag_and_names_it(tmp_path):
    (tmp_path / "taken").mkdir()
    r = subprocess.run(
        [str(executable("uav_bringup", "record")), "-o", str(tmp_path / "taken")],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "ROS_DOMAIN_ID": "99", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"},
    )
    assert r.returncode == 2 and "already exists" in r.stderr and "taken" in r.stderr


def test_a_launcher_waits_until_the_recorder_and_the_policy_have_matched_each_other():
    """Discovery matches a subscription on each side at its own time: a recorder that hears the policy's publishers
    may not be heard by them yet, and what the policy says meanwhile reaches no recorder (a flight then lacked its
    first 16 commands). Both sides' reports must say so before the first frame."""
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

    from uav_bringup.record import POLICY_TOPICS, RecorderReports

    class Node:
        def create_subscription(self, msgtype, topic, callback, qos):
            self.callback = callback

    def report(name: str, values: dict) -> DiagnosticArray:
        return DiagnosticArray(
            status=[DiagnosticStatus(name=name, values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]
        )

    node = Node()
    reports = RecorderReports(node)
    topics = [f"/uav2/{t}" for t in POLICY_TOPICS]
    assert not reports.ready(topics)
    node.callback(report("uav_bringup/record", {f"publishers {t}": 1 for t in topics}))
    assert reports.heard == {t: 1 for t in topics} and not reports.ready(topics)
    heard = {f"subscribers {t}": 1 for t in topics}
    node.callback(report("uav_policy", {**heard, f"subscribers {topics[0]}": 0, "subscribers /uav3/action": 1}))
    assert not reports.ready(topics)  # the action's publisher has not matched the recorder yet
    node.callback(report("uav_policy", heard))
    assert reports.ready(topics) and not reports.ready(["/uav5/action"])


def test_at_the_end_a_launcher_waits_until_the_recorder_holds_all_the_policy_published():
    """A reliable message resent after a loss (a busy machine) is lost with its publisher, and at the end of a stream
    no later message shows the gap (a flight's bag lacked its last 17 actions, none counted lost): fly stops the policy
    only once the recorder has written (or counted lost) every decision the policy says it published."""
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

    from uav_bringup.record import RecorderReports

    class Node:
        def create_subscription(self, msgtype, topic, callback, qos):
            self.callback = callback

    class Executor:  # each spin takes the next report said
        def __init__(self, said):
            self.said = list(said)

        def spin_once(self, timeout_sec):
            if self.said:
                node.callback(self.said.pop(0))

    def report(name: str, values: dict) -> DiagnosticArray:
        return DiagnosticArray(
            status=[DiagnosticStatus(name=name, values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]
        )

    policy = report("uav_policy", {"published /uav2/action": 20, "published /uav2/cmd_vel": 20})
    short = report("uav_bringup/record", {"/uav2/action": 17, "/uav2/cmd_vel": 20, "lost /uav2/cmd_vel": 0})
    node = Node()
    reports = RecorderReports(node)
    assert not reports.wait_until_idle(Executor([policy, short, policy, short, policy, short]), timeout_s=0.3)
    assert reports.missing() == {"/uav2/action": 3}, "the recorder idle but 3 actions short: not done, and said"
    whole = report("uav_bringup/record", {"/uav2/action": 19, "lost /uav2/action": 1, "/uav2/cmd_vel": 20})
    node = Node()
    reports = RecorderReports(node)
    assert reports.wait_until_idle(Executor([policy, short, policy, whole, policy, whole]), timeout_s=5.0)
    assert reports.missing() == {}, "written or counted lost: every one accounted for"
    # A paused simulator's final counts, of the topics the recorder takes (not the clock): sent before the recorder
    # heard it counts as accounted for; what is neither written nor counted is missing.
    sim = {"published /uav2/odom": 30, "published /clock": 30}
    running = report("uav_sim", sim | {"paused": "false"})
    recorded = {"publishers /uav2/odom": 1, "/uav2/odom": 28, "before_recording /uav2/odom": 1}
    rec = report("uav_bringup/record", {"/uav2/action": 20, "/uav2/cmd_vel": 20} | recorded)
    node = Node()
    reports = RecorderReports(node)
    assert reports.wait_until_idle(Executor([running, policy, rec, policy, rec]), timeout_s=5.0), "not paused: not asked"
    assert not reports.wait_until_idle(Executor([report("uav_sim", sim | {"paused": "true"}), policy, rec]), timeout_s=0.3)
    assert reports.missing() == {"/uav2/odom": 1}


def test_a_flooded_recorder_counts_every_message_it_lost_exactly(ros, tmp_path):
    """A publisher floods a topic while the recorder does not read (a busy machine): its reader queue overflows. Every
    message the publisher sent after the first that reached the recorder is in the bag or counted lost on its topic,
    exactly (written + lost = sent), from the publishers' sequence numbers; what it sent before is counted apart; the
    counts are in the closing line and the bag's metadata, which attention_figures reads back."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile
    from std_msgs.msg import String

    from uav_bringup.record import Recorder
    from uav_bringup.taps import DEPTH
    from uav_eval.figures import lost_in_bag

    pub = ros.node.create_publisher(String, "/flood", QoSProfile(depth=10 * DEPTH))
    for i in range(5):  # before any recorder: not for the bag, not lost from it
        pub.publish(String(data=f"early {i}"))
    bag = tmp_path / "flood"
    rec = Recorder(bag, ["/flood"], quiet=True, context=ros.context)
    spin = SingleThreadedExecutor(context=ros.context)
    spin.add_node(rec)
    try:
        end = time.monotonic() + 20
        while "/flood" not in rec.tap.types or pub.get_subscription_count() < 1:  # matched both ways
            spin.spin_once(timeout_sec=0.05)
            assert time.monotonic() < end, "the recorder never subscribed"
        pub.publish(String(data="first"))  # the stream's first message reaches it
        while not rec.counts.get("/flood"):
            spin.spin_once(timeout_sec=0.05)
            assert time.monotonic() < end, "the recorder never got the first message"
        sent = 1 + 3 * DEPTH  # then more than its reader queue holds, while it reads nothing
        for i in range(3 * DEPTH):
            pub.publish(String(data=str(i)))
        last, quiet_since = -1, time.monotonic()
        while time.monotonic() - quiet_since < 1.0:  # read until nothing more comes for a second
            spin.spin_once(timeout_sec=0.05)
            if rec.counts["/flood"] != last:
                last, quiet_since = rec.counts["/flood"], time.monotonic()
        written, lost = rec.counts["/flood"], rec.lost.get("/flood", 0)
        assert lost > 0 and written + lost == sent, (written, lost)
        before = rec.accounting.topics["/flood"].before
        assert before >= 5  # the early ones, and any sent while the two matched
        said = []
        rec.pub_diag.publish = said.append  # what it says on /diagnostics: fly's RecorderReports reads these
        rec.publish_diagnostics()
        values = {kv.key: kv.value for kv in said[0].status[0].values}
        assert (values["/flood"], values["lost /flood"], values["before_recording /flood"]) == tuple(
            str(n) for n in (written, lost, before)
        )
    finally:
        rec.close()
        spin.shutdown()
        rec.destroy_node()
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["custom_data"]["lost /flood"] == str(lost) and meta["custom_data"]["written /flood"] == str(written)
    assert sum(t["message_count"] for t in meta["topics_with_message_count"]) == written
    assert lost_in_bag(bag) == {"/flood": lost}
