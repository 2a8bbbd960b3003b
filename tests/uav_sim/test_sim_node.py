"""Integration: the installed sim_node, driven over Fast DDS with rclpy."""

import math

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image

from conftest import deep_qos, run_to_exit, start_up_error
from uav_common import contract
from uav_interfaces.msg import StepOutcome
from uav_sim.sim_node import SimNode


class Recorder:
    """Records every message of the sim's per-step topics by stamp."""

    def __init__(self, ros):
        self.by_topic = {"depth": [], "info": [], "odom": [], "outcome": [], "clock": []}
        n, q = ros.node, deep_qos()
        for key, typ, topic in (
            ("depth", Image, contract.DEPTH_TOPIC),
            ("info", CameraInfo, contract.CAMERA_INFO_TOPIC),
            ("odom", Odometry, contract.ODOM_TOPIC),
            ("outcome", StepOutcome, contract.OUTCOME_TOPIC),
        ):
            n.create_subscription(typ, topic, lambda m, k=key: self.by_topic[k].append(m), q)
        n.create_subscription(Clock, "/clock", lambda m: self.by_topic["clock"].append(m), q)
        self.cmd = n.create_publisher(Twist, contract.CMD_VEL_TOPIC, q)

    def ready(self, ros, timeout_s: float = 20.0) -> bool:
        """The first frame is in on every topic and sim_node listens to our cmd_vel. A message sent before the
        writer matched the reader is lost, and topics are matched one by one: a frame taken on one topic proves
        nothing about another (beside the main job odometry matched after the first step and missed its frame). A
        lockstep sim says its frame again until it is answered, so each topic's message comes."""
        every = lambda: all(self.by_topic.values()) and self.cmd.get_subscription_count() > 0  # noqa: E731
        return ros.spin_until(every, timeout_s)

    def stamps(self, key):
        if key == "clock":
            return [contract.stamp_ns(m.clock) for m in self.by_topic[key]]
        return [contract.stamp_ns(m.header.stamp) for m in self.by_topic[key]]

    def distinct_frames(self):
        return sorted(set(self.stamps("depth")))


def twist(vx=0.0, wz=0.0, vy=0.0):
    t = Twist()
    t.linear.x, t.linear.y, t.angular.z = vx, vy, wz
    return t


def test_lockstep_topics_encodings_and_shared_stamps(ros):
    rec = Recorder(ros)
    # The ideal camera of the wide150 recipe (sim_node's default is the realsense_d435 preset: its frames below).
    ideal = ("-p", "sensor:=ideal", "-p", "hfov_deg:=150.0", "-p", "reward_window_fraction:=0.078")
    ros.start("uav_sim", "sim_node", "-p", "lockstep_republish_s:=0.3", *ideal)
    assert rec.ready(ros), "no depth frame from sim_node"
    ros.spin_for(1.0)
    assert len(rec.distinct_frames()) == 1, "lockstep must not advance without commands"
    for k in range(10):
        rec.cmd.publish(twist(vx=1.0))
        assert ros.spin_until(lambda k=k: len(rec.distinct_frames()) == k + 2, 10), f"step {k + 1} missing"
    ros.spin_for(0.5)
    frames = rec.distinct_frames()
    assert len(frames) == 11, "exactly one step per command"
    steps = [b - a for a, b in zip(frames, frames[1:], strict=False)]
    assert all(s == 500_000_000 for s in steps), "stamps advance by step_duration_s (0.5 s of sim time)"
    for key in ("info", "odom", "outcome", "clock"):
        assert set(rec.stamps(key)) == set(frames), f"{key} stamps differ from the depth stamps"
    img = rec.by_topic["depth"][-1]
    assert (img.encoding, img.width, img.height, img.step) == ("32FC1", 64, 64, 256)
    assert img.header.frame_id == "camera_depth_optical_frame"
    depth = contract.image_to_depth(img)
    assert depth.shape == (64, 64) and float(depth[32, 32]) > 0.0
    info = rec.by_topic["info"][-1]
    # 150 deg horizontal, fx = (64 / 2) / tan(75 deg) = 8.574 px.
    assert abs(info.k[0] - 32.0 / math.tan(math.radians(75.0))) < 1e-9 and info.k[0] == info.k[4]
    assert info.header.frame_id == img.header.frame_id and contract.camera_info_hfov_deg(info) == pytest.approx(150.0)
    # A window of 0.078 of each side: beta is read over columns 29-33 (5 of 64, edges 3 px left
    # and 2 px right of the centre): atan(3 / fx) + atan(2 / fx) = 32.41 deg of arc.
    fov = math.atan(3 / info.k[0]) + math.atan(2 / info.k[0])
    assert rec.by_topic["outcome"][-1].window_fov_rad == pytest.approx(fov) and math.degrees(fov) == pytest.approx(
        32.41, abs=0.01
    )
    odom = rec.by_topic["odom"][-1]
    assert odom.header.frame_id == "odom" and odom.child_frame_id == "base_link"
    assert abs(odom.pose.pose.position.x - (-6.0 + 5.0)) < 1e-3, "10 steps at 1 m/s x 0.5 s from x=-6"
    assert odom.twist.twist.linear.x == 1.0, "odom twist is the body velocity flown in the step"
    outcome = rec.by_topic["outcome"][-1]
    assert outcome.event == StepOutcome.CONTINUES and 0.0 < outcome.beta_m <= outcome.max_range_m


def test_the_first_frame_waits_for_the_subscribers_asked_for(ros):
    rec = Recorder(ros)  # one subscriber on depth and outcome
    sim = ros.start("uav_sim", "sim_node", "-p", "lockstep_republish_s:=0.3", "-p", "wait_for_subscribers:=2")
    assert ros.spin_until(lambda: "holding the first frame" in ros.log_of(sim), 20), ros.log_of(sim)
    ros.spin_for(2.0)
    rec.cmd.publish(twist(vx=1.0))  # ignored while the frame is held
    from std_srvs.srv import Trigger

    answer = ros.call(ros.node.create_client(Trigger, "/sim_node/reset"), Trigger.Request())
    assert answer.success  # a reset publishes nothing either
    ros.spin_for(1.0)
    assert not rec.by_topic["depth"] and not rec.by_topic["odom"], "a frame was published before 2 subscribers listened"
    second = []
    ros.node.create_subscription(Image, contract.DEPTH_TOPIC, second.append, deep_qos())
    ros.node.create_subscription(StepOutcome, contract.OUTCOME_TOPIC, second.append, deep_qos())
    assert ros.spin_until(lambda: len(second) >= 2 and rec.by_topic["depth"], 20), ros.log_of(sim)
    assert ros.spin_until(lambda: "2 subscribers on depth and outcome: publishing the first frame" in ros.log_of(sim), 10)
    assert contract.stamp_ns(rec.by_topic["depth"][0].header.stamp) == 0, "the held command did not step the sim"
    rec.cmd.publish(twist(vx=1.0))
    assert ros.spin_until(lambda: len(rec.distinct_frames()) == 2, 10), "stepping works once the frame is out"


def test_collision_is_reported_and_the_vehicle_returns_to_start(ros):
    rec = Recorder(ros)
    ros.start("uav_sim", "sim_node", "-p", "lockstep_republish_s:=0.3")
    assert rec.ready(ros)
    for _ in range(40):  # basic: 14 m of open room ahead of the start; 1 m per step
        n = len(rec.distinct_frames())
        rec.cmd.publish(twist(vx=2.0))
        assert ros.spin_until(lambda n=n: len(rec.distinct_frames()) > n, 10)
        if any(contract.outcome_collided(m) for m in rec.by_topic["outcome"]):
            break
    assert ros.spin_until(lambda: any(contract.outcome_collided(m) for m in rec.by_topic["outcome"]), 5)
    crash = next(m for m in rec.by_topic["outcome"] if contract.outcome_collided(m))
    stamp = contract.stamp_ns(crash.header.stamp)
    assert ros.spin_until(lambda: stamp in rec.stamps("odom"), 5), "odom of the crash step missing"
    odom = next(m for m in rec.by_topic["odom"] if contract.stamp_ns(m.header.stamp) == stamp)
    assert abs(odom.pose.pose.position.x - (-6.0)) < 1e-6 and abs(odom.pose.pose.position.y) < 1e-6


def test_time_limit_ends_episodes_with_its_outcome_and_the_step_budget_sends_no_frame_after_the_last_step(ros):
    rec = Recorder(ros)
    budget = ("-p", "step_budget:=7")
    proc = ros.start("uav_sim", "sim_node", "-p", "max_episode_steps:=3", "-p", "lockstep_republish_s:=0.3", *budget)
    assert rec.ready(ros), ros.log_of(proc)
    for k in range(7):  # basic: 14 m of open room ahead; 0.5 m per step
        n = len(set(rec.stamps("outcome")))
        rec.cmd.publish(twist(vx=1.0))
        assert ros.spin_until(lambda n=n: len(set(rec.stamps("outcome"))) > n, 10), k
    assert ros.spin_until(lambda: min(len(set(rec.stamps(k))) for k in ("odom", "outcome")) >= 8, 5)
    by_stamp = {contract.stamp_ns(m.header.stamp): m for m in rec.by_topic["outcome"]}
    odom = {contract.stamp_ns(m.header.stamp): m.pose.pose.position.x for m in rec.by_topic["odom"]}
    stamps = sorted(by_stamp)[:8]
    limit = StepOutcome.TIME_LIMIT
    assert [by_stamp[s].event for s in stamps] == [0, 0, 0, limit, 0, 0, limit, 0], "the time limit named as the cause"
    assert not any(contract.outcome_collided(by_stamp[s]) for s in stamps)
    assert [odom[s] for s in stamps] == pytest.approx([-6.0, -5.5, -5.0, -6.0, -5.5, -5.0, -6.0, -5.5])
    assert "time limit: episode 0 ended after 3 steps" in ros.log_of(proc)
    rec.cmd.publish(twist(vx=1.0))  # one past the budget: taken, not flown
    assert ros.spin_until(lambda: "step budget of 7 steps flown: holding position" in ros.log_of(proc), 10)
    # The last step's outcome is said again (lockstep_republish_s), its frame never: nothing answers a step beyond.
    assert ros.spin_until(lambda: len(rec.distinct_frames()) == 7, 5), "a frame before the budget's end is missing"
    said = len(rec.by_topic["outcome"])
    assert ros.spin_until(lambda: len(rec.by_topic["outcome"]) > said, 5), "the last outcome is said again"
    assert rec.distinct_frames() == stamps[:7] and len(set(rec.stamps("outcome"))) == 8


def test_random_each_episode_flies_a_new_layout_after_every_crash(ros):
    import itertools

    from uav_sim.world import training_layouts

    rec = Recorder(ros)
    diag = []
    ros.node.create_subscription(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, diag.append, 10)
    proc = ros.start(
        "uav_sim", "sim_node", "-p", "world:=random_each_episode", "-p", "seed:=2", "-p", "start_yaw_jitter_deg:=90.0"
    )
    assert rec.ready(ros), ros.log_of(proc)
    layouts = list(itertools.islice(training_layouts(2), 3))  # random:201000, 201001, 201002
    crashes = []
    for _ in range(80):  # at 1 m per step straight ahead, every room ends within 20 steps
        n = len(rec.distinct_frames())
        rec.cmd.publish(twist(vx=2.0))
        assert ros.spin_until(lambda n=n: len(rec.distinct_frames()) > n, 10)
        crashes = [contract.stamp_ns(m.header.stamp) for m in rec.by_topic["outcome"] if contract.outcome_collided(m)]
        if len(set(crashes)) >= 2:
            break
    assert len(set(crashes)) >= 2, "two crashes expected"
    assert ros.spin_until(lambda: set(crashes) <= set(rec.stamps("odom")), 5)
    # Every layout starts at the run's first heading draw (the seed's), as the shipped weights were trained.
    yaw = math.radians(90.0 * np.random.default_rng(2).uniform(-1, 1))
    first = rec.by_topic["odom"][0].pose.pose
    assert (first.position.x, first.position.y) == pytest.approx(layouts[0].start_xyz_m[:2])
    assert 2 * math.atan2(first.orientation.z, first.orientation.w) == pytest.approx(yaw)
    for k, stamp in enumerate(sorted(set(crashes)), start=1):  # each crash step reports the next layout's start
        pose = next(m for m in rec.by_topic["odom"] if contract.stamp_ns(m.header.stamp) == stamp).pose.pose
        assert (pose.position.x, pose.position.y) == pytest.approx(layouts[k].start_xyz_m[:2], abs=1e-6)
        assert 2 * math.atan2(pose.orientation.z, pose.orientation.w) == pytest.approx(yaw)
    assert ros.spin_until(lambda: any(kv.value == "random:201002" for m in diag for kv in m.status[0].values), 5)
    assert "a new layout every episode, first world 'random:201000'" in ros.log_of(proc)


def test_bad_commands_are_rejected_and_the_node_survives(ros):
    rec = Recorder(ros)
    diags = []
    ros.node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    proc = ros.start("uav_sim", "sim_node", "-p", "lockstep_republish_s:=0.3")
    assert rec.ready(ros)
    for bad in (twist(vx=float("nan")), twist(vx=100.0), twist(wz=float("inf")), twist(vy=-7.0)):
        rec.cmd.publish(bad)
    ros.spin_for(1.0)
    assert len(rec.distinct_frames()) == 1, "an invalid command must not move the vehicle"
    assert proc.poll() is None, "sim_node died on bad input"
    rec.cmd.publish(twist(vx=1.0))
    assert ros.spin_until(lambda: len(rec.distinct_frames()) == 2, 10), "a valid command after bad ones works"
    assert ros.spin_until(
        lambda: any(kv.key == "rejected_commands" and kv.value == "4" for d in diags for s in d.status for kv in s.values),
        5,
    )
    assert "rejected cmd_vel" in ros.log_of(proc)


def test_commands_lost_in_a_flood_are_counted(ros):
    """A lockstep simulator takes one command per step: a flood faster than it steps overwrites the publisher's
    history. Every command is either flown (a step) or counted lost on /diagnostics, none is silent."""
    said = []
    ros.node.create_subscription(
        DiagnosticArray,
        "/diagnostics",
        lambda m: said.extend({kv.key: kv.value for kv in s.values} for s in m.status if s.name == "uav_sim"),
        10,
    )
    pub = ros.node.create_publisher(Twist, contract.CMD_VEL_TOPIC, contract.STREAM_QOS)
    ros.start("uav_sim", "sim_node")
    assert ros.spin_until(lambda: said and said[-1]["cmd_vel_publishers"] == "1", 30), said[-1:]
    before = int(said[-1]["steps"])
    pub.publish(twist(vx=1.0))  # the first command heard starts the count of this publisher's sequence
    assert ros.spin_until(lambda: int(said[-1]["steps"]) == before + 1, 10), said[-1]
    for _ in range(3000):
        pub.publish(twist(vx=1.0))
    accounted = lambda: int(said[-1]["steps"]) - before + int(said[-1]["commands_lost"]) == 3001  # noqa: E731
    assert ros.spin_until(accounted, 30), said[-1]
    assert int(said[-1]["commands_lost"]) > 0 and int(said[-1]["commands_ignored"]) == 0


def test_pause_holds_the_vehicle_and_reports_every_message_it_sent(ros):
    """~/pause: no step and nothing published while paused, and /diagnostics says so at once, with per topic the
    messages sent (a recorder's launcher waits for all of them); resumed, a lockstep frame is said again."""
    from std_srvs.srv import SetBool

    rec, said = Recorder(ros), []
    ros.node.create_subscription(
        DiagnosticArray,
        "/diagnostics",
        lambda m: said.extend({kv.key: kv.value for kv in s.values} for s in m.status if s.name == "uav_sim"),
        10,
    )
    topics = {
        "depth": "/depth/image_raw",
        "info": "/depth/camera_info",
        "odom": "/odom",
        "outcome": "/step_outcome",
        "clock": "/clock",
    }
    ros.start("uav_sim", "sim_node", "-p", "lockstep_republish_s:=0.3")
    assert rec.ready(ros), "no frame from sim_node on every topic"  # each topic matched: nothing later is lost
    pause = ros.node.create_client(SetBool, "/sim_node/pause")

    def paused_counts(steps: int) -> dict:
        """Paused: what sim_node reports it sent and what reached us, per topic (a message sent before its topic
        matched, the first frame's, is in the first only: differences are compared)."""
        n = len(said)  # the report of this pause: sim_node says it before it answers
        assert ros.call(pause, SetBool.Request(data=True)).message == f"paused after {steps} steps"
        assert ros.spin_until(lambda: len(said) > n and said[-1]["paused"] == "true", 10)
        ros.spin_for(1.0)  # what was on its way has arrived (reliable, matched)
        assert len(rec.distinct_frames()) == steps + 1, "a paused simulator stepped"
        return {k: (int(said[-1][f"published {t}"]), len(rec.by_topic[k])) for k, t in topics.items()}

    before = paused_counts(0)
    assert ros.call(pause, SetBool.Request(data=False)).message == "running after 0 steps"
    for k in range(3):
        rec.cmd.publish(twist(vx=1.0))
        assert ros.spin_until(lambda k=k: len(rec.distinct_frames()) == k + 2, 10), f"step {k + 1} missing"
    after = paused_counts(3)
    rec.cmd.publish(twist(vx=1.0))  # ignored, and counted so
    assert ros.spin_until(lambda: said[-1]["commands_ignored"] == "1", 10), said[-1]
    ros.spin_for(1.0)
    assert len(rec.distinct_frames()) == 4, "a paused simulator stepped"
    for k in topics:  # every message sent between the pauses reached us: the frame said on resuming, the 3 steps'
        sent, received = after[k][0] - before[k][0], after[k][1] - before[k][1]  # (and any said again while idle)
        assert sent == received >= 4, (k, before[k], after[k])
        assert int(said[-1][f"published {topics[k]}"]) == after[k][0], "a paused simulator published"
    n = len(rec.by_topic["depth"])
    assert ros.call(pause, SetBool.Request(data=False)).message == "running after 3 steps"
    assert ros.spin_until(lambda: len(rec.by_topic["depth"]) > n, 10), "resumed, the frame is said again"
    assert len(rec.distinct_frames()) == 4
    rec.cmd.publish(twist(vx=1.0))
    assert ros.spin_until(lambda: len(rec.distinct_frames()) == 5, 10), "resumed, a command steps again"


def test_realtime_watchdog_stops_the_vehicle(ros):
    rec = Recorder(ros)
    proc = ros.start(
        "uav_sim", "sim_node", "-p", "mode:=realtime", "-p", "step_duration_s:=0.05", "-p", "watchdog_timeout_s:=0.5"
    )
    said = lambda line: ros.log_of(proc).count(line)  # noqa: E731
    stopped, released = "watchdog stops the vehicle", "cmd_vel is back: watchdog released"
    assert ros.spin_until(lambda: said(stopped) == 1, 20), "no command yet: the watchdog holds the vehicle"
    assert rec.ready(ros) and ros.spin_until(lambda: rec.by_topic["odom"], 20)
    odom = rec.by_topic["odom"]
    x0 = odom[-1].pose.pose.position.x
    for _ in range(20):  # fly forward at 1 m/s, a command per step
        rec.cmd.publish(twist(vx=1.0))
        ros.spin_for(0.05)
    assert ros.spin_until(lambda: said(released) == 1, 20)
    assert ros.spin_until(lambda: odom[-1].pose.pose.position.x > x0 + 0.3, 20), "realtime mode did not follow cmd_vel"
    assert ros.spin_until(lambda: said(stopped) == 2, 20)  # our commands stopped
    n = len(odom)
    assert ros.spin_until(lambda: len(odom) >= n + 10, 20), "realtime keeps stepping at a fixed rate without commands"
    # Odometry carries the command each step executed: after the last one of ours, only the watchdog's hover.
    held = odom[max(i for i, m in enumerate(odom) if m.twist.twist.linear.x == 1.0) + 1 :]
    assert len(held) >= 10 and all(m.twist.twist.linear.x == 0.0 for m in held), [m.twist.twist.linear.x for m in held]
    assert len({m.pose.pose.position.x for m in held}) == 1, "vehicle still moving after the watchdog timeout"
    rec.cmd.publish(twist(vx=1.0))
    assert ros.spin_until(lambda: said(released) == 2, 20)
    assert ros.spin_until(lambda: odom[-1].pose.pose.position.x > held[-1].pose.pose.position.x, 20)


def test_bad_parameters_fail_at_start_with_a_clear_message(tmp_path):
    # The process's exit path once; the other bad parameters with the node built in this process.
    r = run_to_exit("uav_sim", "sim_node", "-p", "world:=atlantis")
    assert r.returncode == 2 and "[FATAL] parameter 'world'" in r.stderr and "atlantis" in r.stderr
    assert "Traceback" not in r.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: uav_sim_world/1\nroom: {length_m: -3}\n")
    err = start_up_error(SimNode, "-p", f"world:={bad}")
    assert "length_m" in err
    err = start_up_error(SimNode, "-p", "mode:=warp")
    assert "parameter 'mode'" in err
    err = start_up_error(SimNode, "-p", "max_range_m:=1000.0")
    assert "max_range_m" in err
    err = start_up_error(SimNode, "-p", "max_episode_steps:=-1")
    assert "max_episode_steps" in err
    err = start_up_error(SimNode, "-p", "random_start_fraction:=1.5")
    assert "random_start_fraction" in err


def test_params_file_is_accepted(ros):
    from conftest import ROOT

    rec = Recorder(ros)
    proc = ros.start("uav_sim", "sim_node", "--params-file", str(ROOT / "params" / "sim.yaml"), "-p", "world:=complex")
    # The node logs its start-up line after publishing the first frame: wait for both.
    assert ros.spin_until(lambda: rec.by_topic["depth"] and "world 'complex'" in ros.log_of(proc), 20), ros.log_of(proc)


def test_mix_world_every_flies_the_mixed_world_between_layouts(ros):
    from uav_sim.world import load_world

    rec = Recorder(ros)
    args = ("-p", "world:=random_each_episode", "-p", "mix_world:=complex", "-p", "mix_world_every:=2")
    proc = ros.start("uav_sim", "sim_node", *args, "-p", "max_episode_steps:=2")
    assert rec.ready(ros), ros.log_of(proc)
    for _ in range(6):  # three episodes of two steps: a layout, complex, a layout
        n = len(rec.distinct_frames())
        rec.cmd.publish(twist())
        assert ros.spin_until(lambda n=n: len(rec.distinct_frames()) > n, 10)
    by_stamp = {contract.stamp_ns(m.header.stamp): m.pose.pose.position for m in rec.by_topic["odom"]}
    starts = [by_stamp[s] for s in sorted(by_stamp)]
    complex_start = load_world("complex").start_xyz_m[:2]
    assert (starts[2].x, starts[2].y) == pytest.approx(complex_start)  # the time limit's step reports the next start
    assert (starts[0].x, starts[0].y) != pytest.approx(complex_start)
    assert "a new layout every episode ('complex' every 2 episodes), first world 'random:" in ros.log_of(proc)


@pytest.mark.parametrize(
    "args, message",
    [
        (("mix_world_every:=3",), "parameter 'mix_world_every' (3)"),
        (("world:=random_each_episode", "mix_world_every:=1"), "parameter 'mix_world_every' (1)"),
        (("world:=random_each_episode", "mix_world_every:=2", "mix_world:=nowhere"), "parameter 'mix_world'"),
        (("layout_partitions:=true",), "parameter 'layout_partitions' was removed"),
    ],
)
def test_bad_mix_world_parameters_fail_at_start_up(args, message):
    err = start_up_error(SimNode, *[x for a in args for x in ("-p", a)])
    assert message in err, err


def test_world_markers_match_the_world_file_and_frames_carry_the_namespace(ros):
    """Markers (latched: a late subscriber gets them) of every obstacle at its size and yaw, in the
    namespaced odom frame; the trajectory follows the flight."""
    from nav_msgs.msg import Path
    from visualization_msgs.msg import Marker, MarkerArray

    from uav_sim.world import load_world

    world = load_world("complex")
    cmd = ros.node.create_publisher(Twist, "/uav1/cmd_vel", deep_qos())
    odoms, paths, markers = [], [], []
    ros.node.create_subscription(Odometry, "/uav1/odom", odoms.append, deep_qos())
    ros.node.create_subscription(Path, "/uav1/trajectory", paths.append, 10)
    ros.start("uav_sim", "sim_node", "-r", "__ns:=/uav1", "-p", "world:=complex")
    assert ros.spin_until(lambda: odoms and cmd.get_subscription_count() > 0, 30)
    # Subscribed after the world went out: transient local delivers it all the same.
    ros.node.create_subscription(MarkerArray, "/uav1/world/markers", markers.append, contract.LATCHED_QOS)
    assert ros.spin_until(lambda: markers, 10), "no world markers for a late subscriber"
    ms = markers[-1].markers
    assert ms[0].action == Marker.DELETEALL
    obstacles = [m for m in ms if m.ns == "obstacles"]
    assert len(obstacles) == len(world.obstacles) == 9
    assert len([m for m in ms if m.ns == "walls"]) == 4
    for m, o in zip(obstacles, world.obstacles, strict=True):
        assert m.header.frame_id == "uav1/odom"
        assert (m.pose.position.x, m.pose.position.y, m.pose.position.z) == pytest.approx((o.x_m, o.y_m, o.height_m / 2))
        if o.shape == "box":
            assert m.type == Marker.CUBE
            assert (m.scale.x, m.scale.y, m.scale.z) == pytest.approx((o.size_x_m, o.size_y_m, o.height_m))
        else:
            assert m.type == Marker.CYLINDER
            assert (m.scale.x, m.scale.y, m.scale.z) == pytest.approx((2 * o.radius_m, 2 * o.radius_m, o.height_m))
        yaw = 2 * math.atan2(m.pose.orientation.z, m.pose.orientation.w)
        assert math.degrees(yaw) == pytest.approx(o.yaw_deg, abs=1e-6)
    walls = [m for m in ms if m.ns == "walls"]
    assert max(m.scale.x for m in walls) == pytest.approx(world.length_m + 0.2)  # the walls enclose the room
    assert (odoms[-1].header.frame_id, odoms[-1].child_frame_id) == ("uav1/odom", "uav1/base_link")
    for k in range(6):
        cmd.publish(twist(vx=1.0))
        assert ros.spin_until(lambda k=k: len({contract.stamp_ns(o.header.stamp) for o in odoms}) >= k + 2, 10)
        ros.spin_for(0.25)  # the trajectory goes out at most every 0.2 s
    assert paths and paths[-1].header.frame_id == "uav1/odom"
    xs = [p.pose.position.x for p in paths[-1].poses]
    assert len(xs) >= 5 and xs == sorted(xs) and xs[-1] > xs[0], "the path follows the forward flight"
