"""policy_node's jobs without ROS: a camera's frames onto the network's input, the camera control loop and its stop
when frames stop, the simulator join and the trainer's release, weight pushes, and the answers counted."""

import math
import time

import numpy as np
import pytest

from uav_common.actions import PAPER_ACTIONS
from uav_policy import weights as wio
from uav_policy.agent import Agent
from uav_policy.answer_stats import AnswerStats
from uav_policy.camera_control import CameraControl
from uav_policy.camera_input import CAMERA_INFO_WAIT_S, CameraInput
from uav_policy.networks import NetConfig, QEnsemble, build_network
from uav_policy.pilot import Pilot
from uav_policy.push import PushService, push_request, write_key
from uav_policy.push_receiver import PushReceiver, Refused
from uav_policy.safety import SafetyLayer, SafetySettings
from uav_policy.simulator_link import SimulatorLink


class Log:
    """rclpy's logger signature, keeping what was said."""

    def __init__(self):
        self.said = []

    def warning(self, message, **_):
        self.said.append(("warning", message))

    def info(self, message, **_):
        self.said.append(("info", message))


def d435(width=640, height=480, hfov=87.0):
    fx = width / 2 / math.tan(math.radians(hfov) / 2)
    return (fx, fx, width / 2, height / 2, width, height)


def test_a_real_cameras_frame_of_another_size_reaches_the_safety_layers_stop_distance_through_its_intrinsics():
    """A 640x480 frame of an 87-degree camera, with a wall 0.4 m ahead on its middle third only: through its
    CameraInfo onto weights trained behind the same camera, the wall stays in the middle of the input and the
    safety layer stops the forward action (stop distance 0.6 m); the same frame stretched before any CameraInfo
    is used too, and said so once. A frame of another size waits for its CameraInfo while a publisher offers one,
    CAMERA_INFO_WAIT_S at most."""
    log, views = Log(), []
    cam = CameraInput(64, 64, 87.0, log, views.append)
    frame = np.full((480, 640), 8.0, np.float32)
    frame[:, 213:427] = 0.4
    assert cam.should_wait(480, 640, 100.0, lambda: True)
    assert not cam.should_wait(64, 64, 100.0, lambda: True)  # the input's own size: never
    assert not cam.should_wait(480, 640, 100.0, lambda: False)  # no CameraInfo publisher
    assert not cam.should_wait(480, 640, 100.0 + CAMERA_INFO_WAIT_S + 0.1, lambda: True)
    assert cam.frames_before_info == 1
    stretched = cam(frame)
    cam(frame)
    assert stretched.shape == (64, 64) and sum("no depth/camera_info yet" in m for _, m in log.said) == 1
    assert cam.on_info(d435(), 87.0) and views == [87.0]
    mapped = cam(frame)
    assert cam.view.coverage == pytest.approx(0.75, abs=0.02)  # a 4:3 frame fills the square input's width
    seen = mapped[10:54]  # the rows the camera covers (the others read as no return)
    assert seen[:, 28:36].max() < 0.5 and seen[:, :16].min() > 7.0  # the wall in the middle, clear beside it
    assert np.isinf(mapped[:4]).all()
    assert cam.problem() is None and not [m for _, m in log.said if "trained with" in m]
    safety = SafetyLayer(SafetySettings(stop_distance_m=0.6), 64, 64, 87.0)
    net = build_network(NetConfig(), seed=0)
    d = Pilot(Agent(net, NetConfig()), PAPER_ACTIONS, 0.5, safety).decide(np.stack([mapped] * 5), mapped)
    assert d.linear_x_mps == 0.0 and ("no forward motion" in d.safety or PAPER_ACTIONS[d.action].linear_x_mps == 0)


def test_a_camera_wider_than_the_weights_is_cropped_and_said_once_and_malformed_info_is_counted():
    log = Log()
    cam = CameraInput(64, 64, 87.0, log, lambda _: None)
    assert not cam.on_info(None, None) and cam.bad_info == 1
    for _ in range(3):
        cam.on_info(d435(hfov=120.0), 120.0)
    warned = [m for _, m in log.said if "trained with a 87 deg camera" in m]
    assert len(warned) == 1 and "cropped" in warned[0]
    assert "camera 120 deg" in cam.problem() and cam.values()["malformed_camera_info"] == 1


def test_a_camera_alone_is_answered_once_per_control_period_and_stopped_when_its_frames_stop():
    """30 frames/s against a 10 Hz control rate: about every third frame is answered at once, the others wait for
    a tick (which answers the newest); without frames for frame_timeout_s a stop is due until frames come back."""
    log = Log()
    c = CameraControl(5, 0.5, 0.1, 0.5, log)
    assert not c.active and c.tick(0.0, stops=True) is None
    answered = 0
    for i in range(30):  # one second of frames
        now = i / 30
        if c.add(now, np.full((64, 64), float(i), np.float32), i, now):
            item, state = c.take()
            assert item == i and state.shape == (5, 64, 64)
            answered += 1
    assert 8 <= answered <= 12 and c.active
    assert c.tick(29 / 30 + 0.11, stops=True) == "answer"  # the last frame came within the period: answered at a tick
    c.take()
    assert c.tick(1.4, stops=True) is None  # 0.43 s without a frame: not yet
    assert c.tick(1.6, stops=False) is None  # no safety layer: never a stop
    assert c.tick(1.6, stops=True) == "stop"
    c.stopped(1.6)
    assert "stop commanded" in c.problem(1.7) and c.tick(1.65, stops=True) is None  # one stop per period
    assert c.tick(1.71, stops=True) == "stop"
    c.add(2.0, np.zeros((64, 64), np.float32), "back", 2.0)
    assert c.problem(2.0) is None and any("are back" in m for _, m in log.said)
    c.add(1.0, np.zeros((64, 64), np.float32), "restart", 2.1)
    assert c.restarts == 1
    assert c.hand_over().shape == (5, 64, 64) and not c.active


def test_the_simulator_link_joins_by_stamp_holds_until_released_and_starts_again_when_stamps_go_back():
    log = Log()
    link = SimulatorLink(5, hold=True, wait_timeout_s=1.0, log=log)
    assert link.add("frame", 10, "f10", 0.0) == (None, False)
    assert link.add("outcome", 10, "o10", 0.0) == (None, False)  # joined, but held for the trainer
    assert link.gate.release(10) == [{"frame": "f10", "outcome": "o10"}]
    link.add("frame", 20, "f20", 0.1)
    link.add("outcome", 20, "o20", 0.1)
    assert link.expired(0.5) == [] and link.expired(1.2) == [{"frame": "f20", "outcome": "o20"}]
    assert link.gate.timed_out == 1 and any("no longer in lockstep" in m for _, m in log.said)
    link.last_stamp = 20
    s1 = link.state(np.ones((4, 4), np.float32), new_episode=True)
    s2 = link.state(np.zeros((4, 4), np.float32), new_episode=False)
    assert s1.shape == (5, 4, 4) and s2[-1].max() == 0 and s2[0].min() == 1
    joined, restarted = link.add("frame", 5, "f5", 2.0)
    assert restarted and joined is None and link.last_stamp is None and link.stack.empty
    assert link.values()["stamp_restarts"] == 1
    free = SimulatorLink(5, hold=False, wait_timeout_s=1.0, log=log)
    free.add("outcome", 7, "o7", 0.0)
    assert free.add("frame", 7, "f7", 0.0) == ({"frame": "f7", "outcome": "o7"}, False)


def test_pushes_are_taken_only_signed_in_sequence_releasing_nothing_too_far_and_priced_before_they_are_built(tmp_path):
    key_file = write_key(tmp_path / "push.key")
    key = bytes.fromhex(key_file.read_text().strip())
    link = SimulatorLink(5, hold=True, wait_timeout_s=10.0, log=Log())
    r = PushReceiver(str(key_file), link.gate, 5.0, Log(), 4)  # a period no loaded machine's pass comes near
    with pytest.raises(Refused, match="signature does not match"):
        r.authenticate(push_request(None, 0.5, key=b"k" * 32, seq=1))
    assert r.authenticate(push_request(None, 0.5, key=key, seq=1)).epsilon == 0.5
    with pytest.raises(Refused):  # played again
        r.authenticate(push_request(None, 0.5, key=key, seq=1))
    link.add("frame", 1_000, "f", 0.0)
    link.add("outcome", 1_000, "o", 0.0)
    with pytest.raises(Refused, match="beyond the newest frame"):
        r.authenticate(push_request(None, None, release_stamp_ns=20_000_000_000, key=key, seq=2))
    with pytest.raises(ValueError, match="an empty push"):
        r.authenticate(PushService.Request())
    assert (r.unauthenticated, r.releases_refused) == (2, 1)
    # A release may say that a teacher answers its frame: an action of the table, signed with the rest.
    with pytest.raises(ValueError, match="'fly_action' 4 is not an action"):
        r.authenticate(push_request(None, None, release_stamp_ns=1_000, key=key, seq=3, fly_action=4))
    forged = push_request(None, None, release_stamp_ns=1_000, key=key, seq=4, fly_action=1)
    forged.fly_action = 2
    with pytest.raises(Refused, match="signature"):
        r.authenticate(forged)
    push = r.authenticate(push_request(None, None, release_stamp_ns=1_000, key=key, seq=5, fly_action=2))
    assert push.fly_action == 2 and link.gate.fly_action_for(1_000) is None, "not before it is released"
    link.gate.release(push.release_stamp_ns, push.fly_action)
    assert link.gate.fly_action_for(1_000) == 2 and link.gate.fly_action_for(2_000) is None, "its own frame only"
    with pytest.raises(ValueError, match="come with 'release_stamp_ns'"):
        r.authenticate(push_request(None, 0.5, key=key, seq=6, fly_action=1))
    r.time_inference(Agent(build_network(NetConfig(), seed=0), NetConfig()))
    assert r.seconds_per_flop > 0
    blob = wio.to_bytes(build_network(NetConfig(), seed=0), NetConfig())
    r.check_cost(blob, NetConfig())  # the network flown answers within the period
    first = r.load(blob, NetConfig(), reuse=True)  # no spare yet: built
    r.retire(first)
    assert r.load(blob, NetConfig(), reuse=False) is not first and r.spare is None  # the worker may still read it
    r.retire(first)
    assert r.load(blob, NetConfig(), reuse=True) is first  # written over: a copy, not a build
    r.retire(QEnsemble([first, build_network(NetConfig(), seed=1)]))
    assert r.spare is None
    r.control_period_s = 1e-9
    with pytest.raises(ValueError, match="control period"):
        r.check_cost(blob, NetConfig())
    assert "frame release was applied" in r.reject("bad weights", released=True) and r.values()["pushes_rejected"] == 1


def test_the_answers_are_counted_with_their_latency_and_a_silent_policy_is_a_problem():
    s = AnswerStats()
    s.received = 3
    t = time.perf_counter()
    s.answer(t - 0.010, t - 0.005, t)
    problems, values = s.report(time.monotonic(), waiting=False)
    assert problems == [] and values["frames_answered"] == 1 and float(values["latency_ms_p50"]) == pytest.approx(10, abs=0.5)
    s.received, s.malformed = 5, 1
    problems, values = s.report(time.monotonic(), waiting=False)
    assert len(problems) == 2 and "none answered" in problems[1] and values["ms_per_answer"] == "-"
    s.received = 6
    assert s.report(time.monotonic(), waiting=True)[0] == []  # frames held for the trainer on purpose


def test_camera_frames_lost_on_the_way_are_counted_from_the_publishers_sequence_numbers():
    s = AnswerStats()
    asked = []
    one = lambda: asked.append(1) or 1  # noqa: E731
    for seq in (1, 2, 3, 6, 7, 10):  # 4, 5, 8 and 9 lost
        s.arrived(seq, one)
    assert s.lost == 4 and len(asked) == 2  # the graph is asked only at a gap
    problems, values = s.report(time.monotonic(), waiting=False)
    assert values["frames_lost"] == 4 and any("4 depth frame(s) lost on the way" in p for p in problems)
    s.arrived(1, one)  # the camera driver restarted: its numbers start again
    s.arrived(2, one)
    s.arrived(5, lambda: 2)  # two publishers interleave their numbers: no gap can be told
    s.arrived(None, one)  # no sequence number (another middleware): nothing counted
    s.arrived(9, one)
    problems, values = s.report(time.monotonic(), waiting=False)
    assert values["frames_lost"] == 4 and not any("lost" in p for p in problems)
