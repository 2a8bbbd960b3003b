"""policy_node: flies the quadrotor with D3QN-SAM or D3QN-CNN and publishes what it attends to.

With a simulator (a step_outcome publisher) it joins depth/image_raw and step_outcome by stamp (-Inf or
NaN restarts the frame stack) and answers each frame. With a depth camera alone it answers the newest
frame at most control_rate_hz times a second, on a stack sampled one step period apart. Answers are
cmd_vel (optionally cmd_vel_stamped), action (the network's choice, stamped with the frame), q_values and
what the decision looks at: for SAM the attention topics, for the CNN its Grad-CAM saliency topics, both
on an absolute scale and measured (uav_policy.insight) on /diagnostics. Frames of any size and encoding
(32FC1, 16UC1) are mapped through depth/camera_info onto the field of view the weights were trained with.
A safety layer (uav_policy.safety) stands between the network and cmd_vel unless turned off. It flies the
packaged weights, or the 'weights' files as one policy on their mean Q-values. With accept_pushes
(train), ~/push_weights swaps in new weights signed with the run's key (uav_policy.push), and with
wait_for_trainer a frame is answered once trainer_node releases it; a flying policy takes nothing from
the network.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist, TwistStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, Range
from std_msgs.msg import Float32MultiArray

from uav_common import contract
from uav_common.frame_stack import CameraView, FrameStack, NetworkInput, SampledStack
from uav_common.node_runner import in_thread, run
from uav_common.ros_params import NodeOwned, ParameterError
from uav_common.settings import declare_settings

from . import weights as wio
from .agent import Agent, resolve_device
from .attention import attention_map, overlay
from .config import RETIRED, PolicySettings
from .insight import Insight, explanation
from .networks import SIZE_FIELDS, NetConfig, QEnsemble, forward_flops, parameter_count
from .pilot import Pilot
from .push import PUSH_QOS, PushService, ReleaseGate, load_key, read_push, verify
from .safety import SafetyLayer

CAMERA_INFO_WAIT_S = 2.0  # how long frames wait for their first CameraInfo (see _wait_for_camera_info)


class PolicyNode(Node):
    def __init__(self, **node_options):  # e.g. context=: built in a test's own context
        super().__init__("policy_node", **node_options)
        st = declare_settings(self, PolicySettings, RETIRED)
        model, seed = st.model, st.seed
        self.epsilon = st.epsilon
        why = "is set by the trainer's pushes" if st.accept_pushes else "is fixed at start-up while flying (-p epsilon:=X)"
        self.epsilon_param = NodeOwned(self, "epsilon", why)
        self.step_duration_s = st.step_duration_s
        self.publish_overlay = st.publish_overlay
        self.wait_for_trainer, self.wait_timeout_s = st.wait_for_trainer, st.wait_for_trainer_timeout_s
        if self.wait_for_trainer and not st.accept_pushes:
            raise ParameterError("parameter 'wait_for_trainer': frames are released by pushes, so it needs accept_pushes:=true")
        if st.accept_pushes and not st.push_key_file:
            raise ParameterError("parameter 'accept_pushes': needs 'push_key_file', the key pushes are signed with")
        if st.accept_pushes and st.safety.safety:
            # The trainer learns from `action`, the network's choice: the vehicle must fly exactly that.
            raise ParameterError(
                "parameter 'safety': a policy that takes pushes (training) flies the network's own actions; "
                "set safety:=false (train does)"
            )
        self.accept_pushes, self.push_key_file = st.accept_pushes, st.push_key_file
        self.push_key: bytes | None = None  # read at the first push (trainer_node may create the file after we start)
        self.last_push_seq = -1
        frames = st.frame_stack
        torch.set_num_threads(st.torch_threads)
        try:
            self.actions = st.actions.table()
        except ValueError as e:
            raise ParameterError(f"parameters 'action_*': {e}") from None
        self.cfg = NetConfig(
            model=model,
            frames=frames,
            height=st.input_height,
            width=st.input_width,
            actions=len(self.actions),
            max_range_m=st.max_range_m,
        )
        try:
            device = resolve_device(st.device)
            files = wio.parse_files(st.weights)
        except ValueError as e:
            raise ParameterError(f"parameter {e}") from None
        try:
            net, source, self.weights_hfov_deg = wio.policy_network(files, self.cfg, seed, self.get_logger().warning)
        except ValueError as e:  # WeightsError included
            raise ParameterError(f"parameter 'weights': {e}") from None
        self.cfg = net.cfg  # with the files' layer sizes
        self.camera_hfov_deg = None  # from depth/camera_info
        self.camera_intrinsics = None  # (fx, fy, cx, cy, width, height) from depth/camera_info
        self.to_input = NetworkInput(self.cfg.height, self.cfg.width)
        self._camera_warned = None
        self._stretch_warned = False
        self.safety = None
        if st.safety.safety:
            hfov = self.weights_hfov_deg if self.weights_hfov_deg is not None else wio.UNRECORDED_HFOV_DEG
            self.safety = SafetyLayer(st.safety, self.cfg.height, self.cfg.width, hfov)
        self.frame_timeout_s = st.safety.frame_timeout_s
        self.control_period_s = 1.0 / st.control_rate_hz
        self.agent = Agent(net, self.cfg, device, seed)
        self.pilot = Pilot(self.agent, self.actions, self.step_duration_s, self.safety)
        self.seconds_per_flop = self._seconds_per_flop() if st.accept_pushes else 0.0

        q = contract.STREAM_QOS
        self.pub_cmd = self.create_publisher(Twist, contract.CMD_VEL_TOPIC, q)
        self.pub_stamped = None
        if st.publish_stamped:
            self.pub_stamped = self.create_publisher(TwistStamped, contract.CMD_VEL_STAMPED_TOPIC, q)
        self.base_frame = contract.vehicle_frame(self.get_namespace(), "base_link")  # what action commands move
        self.pub_action = self.create_publisher(TwistStamped, contract.ACTION_TOPIC, q)
        self.pub_q = self.create_publisher(Float32MultiArray, contract.Q_VALUES_TOPIC, 10)
        self.pub_att = self.create_publisher(Image, contract.ATTENTION_TOPIC, 10)
        self.pub_overlay = self.create_publisher(Image, contract.ATTENTION_OVERLAY_TOPIC, 10)
        self.pub_weights = self.create_publisher(Float32MultiArray, contract.ATTENTION_WEIGHTS_TOPIC, 10)
        self.pub_saliency = self.create_publisher(Image, contract.SALIENCY_TOPIC, 10)
        self.pub_saliency_overlay = self.create_publisher(Image, contract.SALIENCY_OVERLAY_TOPIC, 10)
        self.insight_every = st.insight_every
        self.insight = Insight(net.grid_hw, st.insight_window, seed)
        self.insight_lock = threading.Lock()  # a camera's frames are measured on a worker thread
        self.insight_busy = threading.Lock()  # held while that worker measures
        self.insight_skipped = 0  # camera frames due a measurement that came while the worker was busy
        self.joiner = contract.StampJoiner(("frame", "outcome"))
        # Camera drivers publish best effort; a best-effort reader takes sim_node's reliable frames too.
        self.create_subscription(Image, contract.DEPTH_TOPIC, lambda m: self._on("frame", m), contract.SENSOR_QOS)
        self.create_subscription(Range, contract.OUTCOME_TOPIC, lambda m: self._on("outcome", m), q)
        self.create_subscription(CameraInfo, contract.CAMERA_INFO_TOPIC, self._on_camera_info, contract.SENSOR_QOS)
        self.outcome_topic = self.resolve_topic_name(contract.OUTCOME_TOPIC)
        self.info_topic = self.resolve_topic_name(contract.CAMERA_INFO_TOPIC)
        self.info_wait_since = None  # the first frame that waited for depth/camera_info
        self.frame_awaiting_info = None  # the newest frame that waited for it
        self.frames_before_camera_info = 0
        # Pushes are validated on a worker thread so frames keep being answered meanwhile. The
        # service needs its own callback group: a suspended async callback holds its group. Its request
        # queue (PUSH_QOS) holds a burst of forged pushes, each refused in milliseconds, without losing the trainer's.
        if self.accept_pushes:
            group = MutuallyExclusiveCallbackGroup()
            self.create_service(PushService, "~/push_weights", self._on_push, qos_profile=PUSH_QOS, callback_group=group)
        self.stack = FrameStack(frames)
        self.gate = ReleaseGate(self.wait_timeout_s)  # wait_for_trainer: frames held until released
        if self.wait_for_trainer:
            self.create_timer(min(1.0, self.wait_timeout_s / 4), self._check_held)
        self.last_stamp = None
        self.last_cmd, self.last_cmd_unheard = None, False
        # A camera alone (no step_outcome publisher): frames sampled one step period apart, answered at most
        # control_rate_hz, and a stop when they stop (safety).
        self.sampled = SampledStack(frames, self.step_duration_s)
        self.pending = None  # the newest camera frame not yet answered: (arrival time, Image, depth, input)
        self.last_frame_wall = None  # when the last camera frame came (None: no camera frames)
        self.last_answer_wall = -math.inf  # when the last answered camera frame came (or the last stop went out)
        self.stopping_since = None  # frames stopped: stop commands go out
        self.camera_restarts, self.bad_camera_info = 0, 0
        self.latency_ms = deque(maxlen=1000)  # frame arrival to cmd_vel published
        self.create_timer(self.control_period_s / 2, self._control_tick)
        self.q_label = "action:" + ",".join(a.name for a in self.actions)
        self.source = source
        self.acted, self.bad_frames, self.pushes_accepted, self.pushes_rejected = 0, 0, 0, 0
        self.pushes_unauthenticated = 0
        self.releases_refused = 0  # pushes whose release led every frame seen by too much
        self.act_s = 0.0  # time spent answering frames since the last report (network and publishing)
        self.frames_in = 0  # depth frames received, answered or not
        self._reported = (time.monotonic(), 0, 0, 0)  # (when, acted, bad_frames, frames_in) at the last report
        self.pub_diag = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, 10)
        self.create_timer(1.0, self.publish_diagnostics)
        camera = f", trained with a {self.weights_hfov_deg:g} deg camera" if self.weights_hfov_deg is not None else ""
        safety = (
            f"safety layer on (stop after {self.frame_timeout_s:g} s without camera frames, stop distance "
            f"{st.safety.stop_distance_m:g} m); "
            if self.safety
            else "safety layer off; "
        )
        lockstep = "answering each frame once trainer_node releases it (lockstep learning); " if self.wait_for_trainer else ""
        att = "attention on attention, attention/overlay, attention/weights"
        att = att if model == "sam" else "cnn has no attention module: its Grad-CAM saliency on saliency, saliency/overlay"
        if self.insight_every:
            att += f"; what it looks at measured every {self.insight_every} frame(s) on /diagnostics"
        self.get_logger().info(
            f"model {model} ({parameter_count(net)} parameters, {source}{camera}) on {device}; epsilon {self.epsilon}; "
            f"{safety}{lockstep}{att}"
        )

    # -- camera -------------------------------------------------------------------------
    def _on_camera_info(self, msg: CameraInfo) -> None:
        intrinsics = contract.camera_info_intrinsics(msg)
        if intrinsics is None:
            self.bad_camera_info += 1
            self.get_logger().warning(
                "ignoring malformed depth/camera_info (size or focal length): frames fill the network's input whole",
                throttle_duration_sec=10.0,
            )
            return
        if intrinsics != self.camera_intrinsics:
            self.camera_intrinsics = intrinsics
            self.camera_hfov_deg = contract.camera_info_hfov_deg(msg)
            self._use_camera()
        self._check_camera()
        if self.frame_awaiting_info is not None:
            held, self.frame_awaiting_info = self.frame_awaiting_info, None
            self.frames_in -= 1  # counted when it came
            self._on("frame", held)

    @property
    def trained_hfov_deg(self) -> float | None:
        """The field of view frames are mapped onto: the weights', else (a file that records none, or a
        network not trained yet) the camera's own, so that nothing is cropped; None while neither is known."""
        return self.weights_hfov_deg if self.weights_hfov_deg is not None else self.camera_hfov_deg

    def _use_camera(self) -> None:
        """Map frames and place the safety corridor for the camera and weights now known."""
        hfov = self.trained_hfov_deg
        if self.camera_intrinsics is not None and hfov is not None:
            self.to_input.set_camera(self.camera_intrinsics, hfov)
        if self.safety is not None and hfov is not None:
            self.safety.set_hfov(hfov)

    def _check_camera(self) -> None:
        """Warn once per mismatch between the camera and the camera the weights were trained with."""
        key = wio.camera_mismatch(self.weights_hfov_deg, self.camera_hfov_deg)
        if key is not None and key != self._camera_warned:
            self._camera_warned = key
            fx, fy, cx, cy, w, h = self.camera_intrinsics
            view = CameraView.from_intrinsics(fx, fy, cx, cy, w, h, key[0], self.cfg.height, self.cfg.width)
            how = (
                f"frames are cropped to it (it sees {100 * view.coverage:.0f}% of the trained view)"
                if key[1] > key[0]
                else f"frames cover {100 * view.coverage:.0f}% of the trained view, the rest reads as no return"
            )
            self.get_logger().warning(
                f"the weights were trained with a {key[0]:g} deg camera, but depth/camera_info says {key[1]:.1f} deg: "
                f"{how}; expect more crashes. Weights trained behind this camera fly it better "
                f"(docs/REAL_CAMERA.md)"
            )

    def _to_network(self, depth: np.ndarray) -> np.ndarray:
        """The frame on the network's input: through CameraInfo onto the trained field of view, else whole."""
        hw = self.to_input.hw
        if self.camera_intrinsics is None and depth.shape != hw and not self._stretch_warned:
            self._stretch_warned = True
            self.get_logger().warning(
                f"no depth/camera_info yet: {depth.shape[1]}x{depth.shape[0]} frames fill the "
                f"{hw[1]}x{hw[0]} input whole (their field of view is unknown)"
            )
        return self.to_input(depth)

    # -- frames -------------------------------------------------------------------------
    def _on(self, stream: str, msg) -> None:
        t_in = time.perf_counter()
        stamp = contract.stamp_ns(msg.header.stamp)
        self.frames_in += stream == "frame" and stamp != self.last_stamp  # a frame said again is not new
        if stream == "frame" and self._wait_for_camera_info(msg):
            self.frame_awaiting_info = msg  # answered when its CameraInfo comes (a lockstep sim waits for it)
            return
        if stream == "frame" and not self.wait_for_trainer and self.count_publishers(self.outcome_topic) == 0:
            self._on_camera_frame(msg, stamp, t_in)
            return
        if stream == "frame" and self.last_frame_wall is not None:
            self._simulator_found()
        restarts = self.joiner.restarts
        joined = self.joiner.add(stream, stamp, msg)
        if self.joiner.restarts != restarts:
            self._restarted(stream, stamp)
        if joined is not None and self.wait_for_trainer and self.gate.hold(stamp, joined, time.monotonic()):
            pass
        elif joined is not None:
            self._act(joined["frame"], joined["outcome"], t_in)
        elif stream == "frame" and stamp == self.last_stamp and self.last_cmd_unheard:
            # The simulator said an answered frame again, and our command went out before anyone
            # listened (discovery): answer again. A command that had a reliable listener is only
            # late (a busy machine); answering it twice would advance a lockstep sim two steps.
            self.last_cmd_unheard = self.pub_cmd.get_subscription_count() == 0
            self.pub_cmd.publish(self.last_cmd)

    def _restarted(self, stream: str, stamp: int) -> None:
        """The stamps went back: the simulator restarted (or the last one was a glitch from the future).
        A new frame stack begins; nothing from before is answered or stacked with what comes now."""
        before = self.last_stamp
        self.stack = FrameStack(self.cfg.frames)
        self.last_stamp, self.last_cmd, self.last_cmd_unheard = None, None, False
        held = self.gate.restart()
        self.get_logger().warning(
            f"{stream} stamps went back ({stamp / 1e9:.3f} s after {before / 1e9 if before is not None else 0:.3f} s): "
            f"the source restarted; starting a new frame stack" + (f" ({held} held frames dropped)" if held else ""),
            throttle_duration_sec=5.0,
        )

    def _check_held(self) -> None:
        """wait_for_trainer: a frame the trainer has not released in time is answered anyway, so the vehicle
        never stalls; the run has left lockstep and the warning says so."""
        stamp, released = self.gate.expired(time.monotonic())
        if stamp is not None:
            self.get_logger().warning(
                f"trainer_node did not release the frame at {stamp / 1e9:.1f} s sim time within {self.wait_timeout_s:g} s: "
                f"answering it anyway ({self.gate.timed_out} so far; learning is no longer in lockstep)",
                throttle_duration_sec=10.0,
            )
        for joined in released:
            self._act(joined["frame"], joined["outcome"], time.perf_counter())

    def _wait_for_camera_info(self, img: Image) -> bool:
        """A frame of another size than the network's input is not used before its CameraInfo (it would be
        stretched over the wrong field of view) while a publisher offers one, for CAMERA_INFO_WAIT_S at most:
        a driver that sent its CameraInfo only once, before we listened, still gets flown (stretched)."""
        if self.camera_intrinsics is not None or (img.height, img.width) == (self.cfg.height, self.cfg.width):
            return False
        now = time.monotonic()
        self.info_wait_since = now if self.info_wait_since is None else self.info_wait_since
        if now - self.info_wait_since > CAMERA_INFO_WAIT_S or self.count_publishers(self.info_topic) == 0:
            return False
        self.frames_before_camera_info += 1
        return True

    def _decode(self, img: Image) -> np.ndarray | None:
        try:
            return contract.image_to_depth(img)
        except ValueError as e:
            self.bad_frames += 1
            self.get_logger().warning(f"ignoring malformed depth frame: {e}", throttle_duration_sec=2.0)
            return None

    def _on_camera_frame(self, img: Image, stamp: int, t_in: float) -> None:
        """A camera's frame (no simulator): into the sampled stack; answered now when the control period has
        passed since the last answer (most of it: camera clocks jitter), else at the next control tick."""
        depth = self._decode(img)
        if depth is None:
            return
        net_in = self._to_network(depth)
        if not self.sampled.add(stamp / 1e9, net_in):
            self.camera_restarts += 1
            self.get_logger().warning("depth frame stamps went back: starting a new frame stack", throttle_duration_sec=5.0)
        now = time.monotonic()
        if self.stopping_since is not None:
            self.get_logger().info(f"depth frames are back after {now - self.stopping_since:.1f} s: flying again")
            self.stopping_since = None
        self.last_frame_wall = now
        self.pending = (t_in, now, img, depth, net_in)
        if now - self.last_answer_wall >= 0.8 * self.control_period_s:
            self._answer_pending()

    def _answer_pending(self) -> None:
        t_in, arrived, img, depth, net_in = self.pending
        self.pending = None
        self.last_answer_wall = arrived  # the control period runs from frame to frame, not from answer to frame
        self._decide(img, depth, net_in, self.sampled.state(), t_in)

    def _control_tick(self) -> None:
        """Camera only: answer a frame that came within the control period, and stop when frames stop."""
        if self.last_frame_wall is None:
            return
        now = time.monotonic()
        if self.pending is not None and now - self.last_answer_wall >= self.control_period_s:
            self._answer_pending()
        elif self.safety and self._frames_stopped(now) and now - self.last_answer_wall >= self.control_period_s:
            if self.count_publishers(self.outcome_topic) > 0:  # a lockstep simulator waits for us: never stop it
                self._simulator_found()
                return
            if self.stopping_since is None:
                self.stopping_since = self.last_frame_wall
                self.get_logger().warning(
                    f"no depth frame for {self.frame_timeout_s:g} s: commanding a stop until frames come back"
                )
            self.safety.counts.stops_no_frames += 1
            self.last_answer_wall = now
            self._command(Twist(), self.get_clock().now().to_msg())

    def _simulator_found(self) -> None:
        """The frames answered as a camera's came from a simulator whose step_outcome was discovered after
        them: from now on each frame is answered with its outcome, stacked on those answered so far (one
        per step, as the sampled stack holds them), and no stop command goes out (it would step the
        simulator)."""
        self.last_frame_wall, self.pending, self.stopping_since = None, None, None
        if not self.sampled.empty:
            self.stack.restore(self.sampled.state())
        self.sampled.clear()

    def _frames_stopped(self, now: float) -> bool:
        return now - self.last_frame_wall > self.frame_timeout_s

    def _act(self, img: Image, outcome: Range, t_in: float) -> None:
        """A simulator's frame, joined with its step's outcome: answered at once."""
        stamp = contract.stamp_ns(img.header.stamp)
        if stamp == self.last_stamp:  # already answered (before the simulator's step_outcome was discovered)
            return
        depth = self._decode(img)
        if depth is None:
            return
        net_in = self._to_network(depth)
        if contract.outcome_new_episode(outcome) or self.stack.empty:
            state = self.stack.reset(net_in)
        else:
            state = self.stack.push(net_in)
        self._decide(img, depth, net_in, state, t_in)

    def _decide(self, img: Image, depth: np.ndarray, net_in: np.ndarray, state: np.ndarray, t_in: float) -> None:
        t0 = time.perf_counter()
        d = self.pilot.decide(state, net_in, self.epsilon)
        chosen = Twist()
        chosen.linear.x, chosen.angular.z = self.pilot.command_of(d.action)
        stamped = TwistStamped(twist=chosen)
        stamped.header.stamp = img.header.stamp
        stamped.header.frame_id = self.base_frame
        cmd = chosen
        if d.safety:
            cmd = Twist()
            cmd.linear.x, cmd.angular.z = d.linear_x_mps, d.yaw_rate_radps
            self.get_logger().info(f"safety: {d.safety}", throttle_duration_sec=2.0)
        # The record (the network's choice) goes out before the command: whatever is flown is on record.
        self.pub_action.publish(stamped)
        self._command(cmd, img.header.stamp)
        self.last_stamp = contract.stamp_ns(img.header.stamp)
        self.latency_ms.append(1e3 * (time.perf_counter() - t_in))
        self._publish_insight(img, depth, state, d.action, d.q, d.attention)
        self.acted += 1
        self.act_s += time.perf_counter() - t0

    def _command(self, cmd: Twist, stamp) -> None:
        self.last_cmd_unheard = self.pub_cmd.get_subscription_count() == 0
        self.pub_cmd.publish(cmd)
        if self.pub_stamped is not None:
            out = TwistStamped(twist=cmd)
            out.header.stamp = stamp
            out.header.frame_id = self.base_frame
            self.pub_stamped.publish(out)
        self.last_cmd = cmd

    def publish_diagnostics(self) -> None:
        """1 Hz on /diagnostics: frames answered, malformed frames ignored, weight pushes; WARN while
        malformed frames arrive or the camera differs from the one the weights were trained with."""
        now = time.monotonic()
        when, acted, bad, frames_in = self._reported
        new_acts, new_bad, new_in = self.acted - acted, self.bad_frames - bad, self.frames_in - frames_in
        self._reported = (now, self.acted, self.bad_frames, self.frames_in)
        problems = []
        if new_bad:
            problems.append(f"{new_bad} malformed depth frame(s) ignored in the last {now - when:.1f} s")
        if new_in and not new_acts and not self.gate.held:
            problems.append(f"{new_in} depth frame(s) in the last {now - when:.1f} s and none answered")
        if self.stopping_since is not None:
            problems.append(f"no depth frame for {time.monotonic() - self.stopping_since:.1f} s: stop commanded")
        mismatch = wio.camera_mismatch(self.weights_hfov_deg, self.camera_hfov_deg)
        if mismatch is not None:
            cover = f", covering {100 * self.to_input.view.coverage:.0f}% of it" if self.to_input.view is not None else ""
            problems.append(f"camera {mismatch[1]:g} deg, but the weights were trained with a {mismatch[0]:g} deg camera{cover}")
        lat = np.percentile(self.latency_ms, (50, 99)) if self.latency_ms else None
        counts = self.safety.counts if self.safety else None
        vals = {
            "model": self.cfg.model,
            "weights": self.source,
            "epsilon": self.epsilon,
            "frames_answered": self.acted,
            "malformed_frames": self.bad_frames,
            "pushes_accepted": self.pushes_accepted,
            "pushes_rejected": self.pushes_rejected,
            "pushes_unauthenticated": self.pushes_unauthenticated,
            "frames_received": self.frames_in,
            "frames_without_outcome": self.joiner.dropped["outcome"],
            "outcomes_without_frame": self.joiner.dropped["frame"],
            "duplicate_messages": self.joiner.duplicates,
            "frames_said_again": self.joiner.late,
            "stamp_restarts": self.joiner.restarts,
            "frames_held": len(self.gate.held),
            "released_by_timeout": self.gate.timed_out,
            "releases_refused": self.releases_refused,
            "source": "camera" if self.last_frame_wall is not None else "simulator" if self.acted else "-",
            "camera_restarts": self.camera_restarts,
            "malformed_camera_info": self.bad_camera_info,
            "frames_before_camera_info": self.frames_before_camera_info,
            "camera_coverage": f"{self.to_input.view.coverage:.2f}" if self.to_input.view is not None else "-",
            "safety": "on" if self.safety else "off",
            "safety_interventions": counts.total if counts else 0,
            "safety_stops_no_frames": counts.stops_no_frames if counts else 0,
            "safety_forward_blocked": counts.forward_blocked if counts else 0,
            "safety_speed_limited": counts.speed_limited if counts else 0,
            "safety_yaw_rate_limited": counts.yaw_rate_limited if counts else 0,
            "latency_ms_p50": f"{lat[0]:.2f}" if lat is not None else "-",
            "latency_ms_p99": f"{lat[1]:.2f}" if lat is not None else "-",
            "answers_per_s": f"{new_acts / max(now - when, 1e-6):.1f}",
            "ms_per_answer": f"{1e3 * self.act_s / new_acts:.2f}" if new_acts else "-",
            "explained_by": "attention" if self.cfg.model == "sam" else "saliency (Grad-CAM)",
        }
        with self.insight_lock:
            summary = self.insight.summary()
        if summary is not None:
            vals.update(summary.values())
            vals["insight_skipped"] = self.insight_skipped
        self.act_s = 0.0
        message = "; ".join(problems) or ("acting" if new_acts else "waiting for depth frames")
        self.pub_diag.publish(contract.diagnostics(self, "uav_policy", "WARN" if problems else "OK", message, vals))

    def _publish_insight(self, img: Image, depth: np.ndarray, state: np.ndarray, action: int, q: np.ndarray, w) -> None:
        """q_values; what the decision looks at (SAM's attention, else Grad-CAM saliency), published on an absolute
        scale when wanted, and measured on every insight_every-th frame. The costly part (Grad-CAM, the deletion
        test) runs at once for a simulator's frames and on a worker thread for a camera's, so the next frame is not
        delayed; a camera frame that comes while the worker is busy is not measured (counted)."""
        self.pub_q.publish(contract.q_values_msg(q, self.q_label))
        net = self.agent.net
        measure = self.insight_every > 0 and self.acted % self.insight_every == 0
        if w is not None:  # SAM: the attention is at hand
            self._publish_map(img, depth, action, q, w, "attention", (self.pub_att, self.pub_overlay))
            if self.pub_weights.get_subscription_count() > 0:
                self.pub_weights.publish(contract.attention_weights_msg(w, net.grid_hw))
        pubs = (self.pub_saliency, self.pub_saliency_overlay)
        saliency = w is None and any(p.get_subscription_count() > 0 for p in pubs)
        if not (measure or saliency):
            return  # the CNN's saliency costs a backward pass: only for a subscriber or a measurement

        def job():
            try:
                greedy = int(np.argmax(q))
                rows = explanation(net, state, greedy, w)
                if saliency:
                    self._publish_map(img, depth, action, q, rows, "saliency", pubs)
                if measure:
                    with self.insight_lock:
                        self.insight.observe(net, state, greedy, rows)
            except Exception as e:  # an explanation is never worth the flight
                self.get_logger().warning(f"measuring a decision failed: {e!r}", throttle_duration_sec=10.0)

        if self.last_frame_wall is None:  # a simulator waits for our answer: measure now
            job()
        elif self.insight_busy.acquire(blocking=False):

            def work():
                try:
                    job()
                finally:
                    self.insight_busy.release()

            threading.Thread(target=work, daemon=True).start()
        else:
            self.insight_skipped += 1

    def _publish_map(self, img: Image, depth: np.ndarray, action: int, q: np.ndarray, rows, kind: str, pubs) -> None:
        """The map (32FC1, relative to a uniform share) and, when subscribed, its overlay with the action and Q margin."""
        pub_map, pub_overlay = pubs
        amap = attention_map(rows, self.agent.net.grid_hw, depth.shape, self.to_input.view)
        pub_map.publish(contract.depth_to_image(amap, img.header.stamp, img.header.frame_id))
        if self.publish_overlay and pub_overlay.get_subscription_count() > 0:
            second = np.partition(q, -2)[-2] if len(q) > 1 else q[action]
            label = f"{self.actions[action].name.split('_', 1)[0]} Q {q[action]:.2f}, margin {q[action] - second:+.2f}"
            pub_overlay.publish(contract.rgb_image(img.header, overlay(depth, amap, self.cfg.max_range_m, label, kind)))

    # -- weight pushes ------------------------------------------------------------------
    async def _on_push(self, request, response):
        t0 = time.perf_counter()
        response.success = False
        try:
            push = read_push(request.load_namespace, wio.MAX_BYTES)
        except ValueError as e:
            push = None
            response.message = str(e)
        if push is not None:
            try:
                if self.push_key is None:
                    self.push_key = load_key(self.push_key_file)
                verify(self.push_key, push, self.last_push_seq)
                self.last_push_seq = push.seq
                beyond = None if push.release_stamp_ns is None else self.gate.beyond(push.release_stamp_ns)
                if beyond:  # a trainer that lost track of the stream: nothing of the push is taken
                    self.releases_refused += 1
                    self.get_logger().warning(f"weights push refused: {beyond}", throttle_duration_sec=5.0)
                    response.message = beyond
                    return response
            except ValueError as e:  # not from our trainer: nothing of it is taken, no frame is released
                self.pushes_unauthenticated += 1
                self.get_logger().warning(f"weights push refused: {e}", throttle_duration_sec=5.0)
                response.message = str(e)
                return response
        try:
            if push is None:
                raise ValueError(response.message)
            blob = push.weights
            if blob is not None:
                self._check_cost(blob)
                # The trainer owns the layer sizes: a push may bring others (the interface must match).
                load = lambda: wio.load_bytes(blob, self.cfg, sizes_from_blob=True)  # noqa: E731
                # A release is awaited by the frame it releases, so it loads here (a few ms): a worker thread's
                # result wakes this executor only at its next event, up to a timer period later.
                net = load() if push.release_stamp_ns is not None else await in_thread(self.executor, load)
                self._swap_in(net, blob)
            if push.epsilon is not None:
                self.epsilon = push.epsilon
                self.epsilon_param.set(push.epsilon)  # ros2 param get and /diagnostics agree
            response.success = True
            response.message = f"swapped in {len(blob)} bytes in {1e3 * (time.perf_counter() - t0):.1f} ms" if blob else "ok"
        except ValueError as e:  # WeightsError included
            response.message = str(e)
        # A well-formed push releases its frames even when its weights are refused (they are then answered on
        # the weights and epsilon in use), so a refusal never holds a frame for wait_for_trainer_timeout_s.
        released = push is not None and push.release_stamp_ns is not None
        if not response.success:
            self.pushes_rejected += 1
            if released:
                response.message += "; its frame release was applied, acting on the weights and epsilon in use"
            self.get_logger().warning(f"weights push rejected: {response.message}")
        if released:
            for joined in self.gate.release(push.release_stamp_ns):
                self._act(joined["frame"], joined["outcome"], time.perf_counter())
        return response

    def _seconds_per_flop(self) -> float:
        """This machine's inference time per floating-point operation, timed on the network flown at start
        (the best of five passes): what prices a pushed architecture against the control period."""
        net = self.agent.net
        members = len(net.members) if isinstance(net, QEnsemble) else 1
        state = np.zeros((self.cfg.frames, self.cfg.height, self.cfg.width), np.float32)
        self.agent.q_values(state)  # warm-up
        best = math.inf
        for _ in range(5):
            t0 = time.perf_counter()
            self.agent.q_values(state)
            best = min(best, time.perf_counter() - t0)
        return best / (members * forward_flops(net.cfg))

    def _check_cost(self, blob: bytes) -> None:
        """Refuse (ValueError) weights whose architecture would not answer within the control period here,
        priced from the blob's header before anything of the network is built."""
        cfg = wio.with_sizes_of(self.cfg, wio.read_header_config(blob))
        flops = forward_flops(cfg)
        seconds = flops * self.seconds_per_flop
        if seconds > self.control_period_s:
            raise ValueError(
                f"the pushed architecture ({flops / 1e6:.0f} MFLOP a frame) would take about {1e3 * seconds:.0f} ms a "
                f"frame here, more than the {1e3 * self.control_period_s:.0f} ms control period (control_rate_hz)"
            )

    def _swap_in(self, net: torch.nn.Module, blob: bytes) -> None:
        replaced = self.agent.net
        self.agent.swap(net)
        if isinstance(replaced, QEnsemble):
            self.get_logger().info(f"pushed weights replace the ensemble of {len(replaced.members)} networks")
        if net.cfg != self.cfg:
            sizes = ", ".join(f"{k} {getattr(net.cfg, k)}" for k in SIZE_FIELDS)
            self.get_logger().info(f"pushed weights changed the layer sizes: {sizes} ({parameter_count(net)} parameters)")
        if net.grid_hw != replaced.grid_hw:  # measured maps of another grid do not compare
            with self.insight_lock:
                self.insight = Insight(net.grid_hw, self.insight.frames.maxlen)
        self.cfg = net.cfg
        self.weights_hfov_deg = wio.read_header_camera(blob)
        self.to_input = NetworkInput(self.cfg.height, self.cfg.width)  # the input size or camera may have changed
        self._use_camera()
        self._check_camera()
        self.pushes_accepted += 1
        self.source = f"pushed weights ({len(blob)} bytes)"


def main(args=None) -> int:
    return run(PolicyNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
