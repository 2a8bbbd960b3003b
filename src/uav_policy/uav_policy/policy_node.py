"""policy_node: flies the quadrotor with D3QN-SAM or D3QN-CNN and publishes what it attends to.

Joins depth/image_raw and step_outcome by stamp (-Inf or NaN restarts the frame stack) and answers each
frame with cmd_vel, action (stamped with the frame), q_values and, for SAM, the attention topics. It flies
the packaged weights, or the 'weights' files as one policy on their mean Q-values. With accept_pushes (train),
~/push_weights swaps in new weights signed with the run's key (uav_policy.push), and with wait_for_trainer a
frame is answered once trainer_node releases it; a flying policy takes nothing from the network.
It warns when depth/camera_info shows another camera than the weights were trained behind.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist, TwistStamped
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParameters
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, Range
from std_msgs.msg import Float32MultiArray

from uav_common import contract
from uav_common.frame_stack import FrameStack, fit_to_network
from uav_common.node_runner import in_thread, run
from uav_common.ros_params import ParameterError
from uav_common.settings import declare_settings

from . import weights as wio
from .agent import Agent, resolve_device
from .attention import attention_map, overlay
from .config import RETIRED, PolicySettings
from .networks import SIZE_FIELDS, NetConfig, QEnsemble, parameter_count
from .push import ReleaseGate, load_key, read_push, verify


class PolicyNode(Node):
    def __init__(self):
        super().__init__("policy_node")
        st = declare_settings(self, PolicySettings, RETIRED)
        model, seed = st.model, st.seed
        self.epsilon = st.epsilon
        self.step_duration_s = st.step_duration_s
        self.publish_overlay = st.publish_overlay
        self.wait_for_trainer, self.wait_timeout_s = st.wait_for_trainer, st.wait_for_trainer_timeout_s
        if self.wait_for_trainer and not st.accept_pushes:
            raise ParameterError("parameter 'wait_for_trainer': frames are released by pushes, so it needs accept_pushes:=true")
        if st.accept_pushes and not st.push_key_file:
            raise ParameterError("parameter 'accept_pushes': needs 'push_key_file', the key pushes are signed with")
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
            sam_readout=st.sam_readout,
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
        self._camera_warned = None
        self.agent = Agent(net, self.cfg, device, seed)

        q = contract.STREAM_QOS
        self.pub_cmd = self.create_publisher(Twist, contract.CMD_VEL_TOPIC, q)
        self.base_frame = contract.vehicle_frame(self.get_namespace(), "base_link")  # what action commands move
        self.pub_action = self.create_publisher(TwistStamped, contract.ACTION_TOPIC, q)
        self.pub_q = self.create_publisher(Float32MultiArray, contract.Q_VALUES_TOPIC, 10)
        self.pub_att = self.create_publisher(Image, contract.ATTENTION_TOPIC, 10)
        self.pub_overlay = self.create_publisher(Image, contract.ATTENTION_OVERLAY_TOPIC, 10)
        self.pub_weights = self.create_publisher(Float32MultiArray, contract.ATTENTION_WEIGHTS_TOPIC, 10)
        self.joiner = contract.StampJoiner(("frame", "outcome"))
        self.create_subscription(Image, contract.DEPTH_TOPIC, lambda m: self._on("frame", m), q)
        self.create_subscription(Range, contract.OUTCOME_TOPIC, lambda m: self._on("outcome", m), q)
        self.create_subscription(CameraInfo, contract.CAMERA_INFO_TOPIC, self._on_camera_info, 10)
        # Pushes are validated on a worker thread so frames keep being answered meanwhile. The
        # service needs its own callback group: a suspended async callback holds its group.
        if self.accept_pushes:
            self.create_service(SetParameters, "~/push_weights", self._on_push, callback_group=MutuallyExclusiveCallbackGroup())
        self.stack = FrameStack(frames)
        self.gate = ReleaseGate(self.wait_timeout_s)  # wait_for_trainer: frames held until released
        if self.wait_for_trainer:
            self.create_timer(min(1.0, self.wait_timeout_s / 4), self._check_held)
        self.last_stamp = None
        self.last_cmd, self.last_cmd_unheard = None, False
        self.q_label = "action:" + ",".join(a.name for a in self.actions)
        self.source = source
        self.acted, self.bad_frames, self.pushes_accepted, self.pushes_rejected = 0, 0, 0, 0
        self.pushes_unauthenticated = 0
        self.act_s = 0.0  # time spent answering frames since the last report (network and publishing)
        self.frames_in = 0  # depth frames received, answered or not
        self._reported = (time.monotonic(), 0, 0, 0)  # (when, acted, bad_frames, frames_in) at the last report
        self.pub_diag = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, 10)
        self.create_timer(1.0, self.publish_diagnostics)
        camera = f", trained with a {self.weights_hfov_deg:g} deg camera" if self.weights_hfov_deg is not None else ""
        lockstep = "answering each frame once trainer_node releases it (lockstep learning); " if self.wait_for_trainer else ""
        att = "attention on attention, attention/overlay, attention/weights"
        att = att if model == "sam" else "cnn has no attention module: the attention topics are not published"
        self.get_logger().info(
            f"model {model} ({parameter_count(net)} parameters, {source}{camera}) on {device}; epsilon {self.epsilon}; "
            f"{lockstep}{att}"
        )

    # -- camera -------------------------------------------------------------------------
    def _on_camera_info(self, msg: CameraInfo) -> None:
        hfov = contract.camera_info_hfov_deg(msg)
        if hfov is None:
            self.get_logger().warning("ignoring malformed depth/camera_info (width or fx)", throttle_duration_sec=10.0)
            return
        self.camera_hfov_deg = hfov
        self._check_camera()

    def _check_camera(self) -> None:
        """Warn once per mismatch between the camera and the camera the weights were trained with."""
        key = wio.camera_mismatch(self.weights_hfov_deg, self.camera_hfov_deg)
        if key is not None and key != self._camera_warned:
            self._camera_warned = key
            self.get_logger().warning(
                f"the weights were trained with a {key[0]:g} deg camera, but depth/camera_info says {key[1]:.1f} deg: "
                f"expect more crashes (run sim_node with hfov_deg:={key[0]:g})"
            )

    # -- frames -------------------------------------------------------------------------
    def _on(self, stream: str, msg) -> None:
        stamp = contract.stamp_ns(msg.header.stamp)
        self.frames_in += stream == "frame" and stamp != self.last_stamp  # a frame said again is not new
        restarts = self.joiner.restarts
        joined = self.joiner.add(stream, stamp, msg)
        if self.joiner.restarts != restarts:
            self._restarted(stream, stamp)
        if joined is not None and self.wait_for_trainer and self.gate.hold(stamp, joined, time.monotonic()):
            pass
        elif joined is not None:
            self._act(joined["frame"], joined["outcome"])
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
            self._act(joined["frame"], joined["outcome"])

    def _act(self, img: Image, outcome: Range) -> None:
        t0 = time.perf_counter()
        stamp = contract.stamp_ns(img.header.stamp)
        try:
            depth = contract.image_to_depth(img)
        except ValueError as e:
            self.bad_frames += 1
            self.get_logger().warning(f"ignoring malformed depth frame: {e}", throttle_duration_sec=2.0)
            return
        net_in = fit_to_network(depth, self.cfg.height, self.cfg.width)
        if contract.outcome_new_episode(outcome) or self.stack.empty:
            state = self.stack.reset(net_in)
        else:
            state = self.stack.push(net_in)
        action, q, w, _ = self.agent.act(state, self.epsilon)
        a = self.actions[action]
        cmd = Twist()
        cmd.linear.x = a.linear_x_mps
        cmd.angular.z = a.yaw_rate_radps(self.step_duration_s)
        stamped = TwistStamped(twist=cmd)
        stamped.header.stamp = img.header.stamp
        stamped.header.frame_id = self.base_frame
        # The record goes out before the command: whatever the simulator acts on is on record.
        self.pub_action.publish(stamped)
        self.last_cmd_unheard = self.pub_cmd.get_subscription_count() == 0
        self.pub_cmd.publish(cmd)
        self.last_stamp, self.last_cmd = stamp, cmd
        self._publish_insight(img, depth, q, w)
        self.acted += 1
        self.act_s += time.perf_counter() - t0

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
            problems.append(f"{new_in} depth frame(s) in the last {now - when:.1f} s and none answered (no step_outcome?)")
        mismatch = wio.camera_mismatch(self.weights_hfov_deg, self.camera_hfov_deg)
        if mismatch is not None:
            problems.append(f"camera {mismatch[1]:g} deg, but the weights were trained with a {mismatch[0]:g} deg camera")
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
            "answers_per_s": f"{new_acts / max(now - when, 1e-6):.1f}",
            "ms_per_answer": f"{1e3 * self.act_s / new_acts:.2f}" if new_acts else "-",
        }
        self.act_s = 0.0
        message = "; ".join(problems) or ("acting" if new_acts else "waiting for depth frames")
        self.pub_diag.publish(contract.diagnostics(self, "uav_policy", "WARN" if problems else "OK", message, vals))

    def _publish_insight(self, img: Image, depth: np.ndarray, q: np.ndarray, w) -> None:
        self.pub_q.publish(contract.q_values_msg(q, self.q_label))
        if w is None:
            return
        amap = attention_map(w, self.agent.net.grid_hw, depth.shape)
        self.pub_att.publish(contract.depth_to_image(amap, img.header.stamp, img.header.frame_id))
        if self.publish_overlay and self.pub_overlay.get_subscription_count() > 0:
            self.pub_overlay.publish(contract.rgb_image(img.header, overlay(depth, amap, self.cfg.max_range_m)))
        if self.pub_weights.get_subscription_count() > 0:
            self.pub_weights.publish(contract.attention_weights_msg(w, self.agent.net.grid_hw))

    # -- weight pushes ------------------------------------------------------------------
    async def _on_push(self, request, response):
        t0 = time.perf_counter()
        result = SetParametersResult(successful=False)
        try:
            push = read_push(request.parameters, wio.MAX_BYTES)
        except ValueError as e:
            push = None
            result.reason = str(e)
        if push is not None:
            try:
                if self.push_key is None:
                    self.push_key = load_key(self.push_key_file)
                verify(self.push_key, push, self.last_push_seq)
                self.last_push_seq = push.seq
            except ValueError as e:  # not from our trainer: nothing of it is taken, no frame is released
                self.pushes_unauthenticated += 1
                self.get_logger().warning(f"weights push refused: {e}", throttle_duration_sec=5.0)
                result.reason = str(e)
                response.results = [result]
                return response
        try:
            if push is None:
                raise ValueError(result.reason)
            blob = push.weights
            if blob is not None:
                # The trainer owns the layer sizes: a push may bring others (the interface must match).
                load = lambda: wio.load_bytes(blob, self.cfg, sizes_from_blob=True)  # noqa: E731
                # A release is awaited by the frame it releases, so it loads here (a few ms): a worker thread's
                # result wakes this executor only at its next event, up to a timer period later.
                net = load() if push.release_stamp_ns is not None else await in_thread(self.executor, load)
                self._swap_in(net, blob)
            if push.epsilon is not None:
                self.epsilon = push.epsilon
            result.successful = True
            result.reason = f"swapped in {len(blob)} bytes in {1e3 * (time.perf_counter() - t0):.1f} ms" if blob else "ok"
        except ValueError as e:  # WeightsError included
            result.reason = str(e)
        # A well-formed push releases its frames even when its weights are refused (they are then answered on
        # the weights and epsilon in use), so a refusal never holds a frame for wait_for_trainer_timeout_s.
        released = push is not None and push.release_stamp_ns is not None
        if not result.successful:
            self.pushes_rejected += 1
            if released:
                result.reason += "; its frame release was applied, acting on the weights and epsilon in use"
            self.get_logger().warning(f"weights push rejected: {result.reason}")
        if released:
            for joined in self.gate.release(push.release_stamp_ns):
                self._act(joined["frame"], joined["outcome"])
        response.results = [result]
        return response

    def _swap_in(self, net: torch.nn.Module, blob: bytes) -> None:
        replaced = self.agent.net
        self.agent.swap(net)
        if isinstance(replaced, QEnsemble):
            self.get_logger().info(f"pushed weights replace the ensemble of {len(replaced.members)} networks")
        if net.cfg != self.cfg:
            sizes = ", ".join(f"{k} {getattr(net.cfg, k)}" for k in SIZE_FIELDS)
            self.get_logger().info(f"pushed weights changed the layer sizes: {sizes} ({parameter_count(net)} parameters)")
        self.cfg = net.cfg
        self.weights_hfov_deg = wio.read_header_camera(blob)
        self._check_camera()
        self.pushes_accepted += 1
        self.source = f"pushed weights ({len(blob)} bytes)"


def main(args=None) -> int:
    return run(PolicyNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
