"""policy_node: flies the quadrotor with D3QN-SAM or D3QN-CNN and publishes what it attends to.

Subscribes depth/image_raw and step_outcome (joined by stamp: an outcome of -Inf (a collision)
or NaN (a time limit or reset) marks the first frame of a new episode, which restarts the frame
stack). For every frame it publishes
cmd_vel, action (TwistStamped carrying the frame's stamp), q_values, and for SAM the attention
topics. New weights arrive on the ~/push_weights service (rcl_interfaces/srv/SetParameters with
one BYTE_ARRAY parameter named 'weights' holding a safetensors blob; uav_policy.push: a push may
also carry epsilon and a release stamp). With wait_for_trainer (lockstep learning, set by train)
it answers a frame only once trainer_node has released it, after learning from the step that
produced it. It also listens to
depth/camera_info and warns when the camera's field of view is not the one the weights were
trained with (a network flies worse behind another camera).

Given several files (-p weights:=a.safetensors,b.safetensors) it flies them as one policy
that acts on the mean of their Q-values (docs/RESULTS.md, round 27: flown so, a run's last
checkpoints crash less than its final network alone). q_values is then the mean; attention/weights
carries each member's heads in turn and the attention maps average over all of them. A weight push
replaces the ensemble. Without the 'weights' parameter it flies the files packaged with uav_policy
(weights/<model>/: ten networks of one training run, flown so).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Twist, TwistStamped
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParameters
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import CameraInfo, Image, Range
from std_msgs.msg import Float32MultiArray, MultiArrayDimension

from uav_common import contract
from uav_common.node_runner import run
from uav_common.ros_params import ParameterError, declare

from . import weights as wio
from .actions import PAPER_ACTIONS, make_actions
from .agent import Agent
from .attention import attention_map, overlay
from .frame_stack import FrameStack, fit_to_network
from .networks import ENSEMBLE_RULES, MAX_FRAMES, SAM_READOUTS, SIZE_FIELDS, NetConfig, QEnsemble, build_network, parameter_count
from .push import read_push


def weights_files(value: str) -> list[str]:
    """The 'weights' parameter as a list of files: [] (the packaged weights), one file, or several
    separated by commas (an ensemble)."""
    files = [f.strip() for f in value.split(",")] if value.strip() else []
    if not all(files):
        raise ParameterError(f"parameter 'weights': an empty file name in the list {value!r}")
    return files


def resolve_device(name: str) -> str:
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise ParameterError("parameter 'device'='cuda' but no CUDA device is available (use 'auto' or 'cpu')")
    return name


class PolicyNode(Node):
    def __init__(self):
        super().__init__("policy_node")
        d = lambda *a, **k: declare(self, *a, **k)  # noqa: E731
        model = d("model", "sam", "Q-network: sam (D3QN-SAM, attention) or cnn (D3QN-CNN)", choices=("sam", "cnn"))
        weights_arg = d(
            "weights",
            "",
            "safetensors weights file, or several separated by commas, flown as one policy (ensemble_rule: the mean of their "
            "Q-values by default; e.g. a run's last checkpoints, scripts/export_checkpoint.py); empty: the packaged weights, "
            "else a seeded random init",
        )
        self.ensemble_rule = d(
            "ensemble_rule",
            "mean",
            "How several 'weights' files act as one: mean (the mean of their Q-values) or min (each action's lowest "
            "Q-value over the files, a pessimistic extension); ignored for one file",
            choices=ENSEMBLE_RULES,
        )
        self.epsilon = d(
            "epsilon", 0.0, "Probability of a random action (exploration); the trainer decays it", 0.0, 1.0, read_only=False
        )
        seed = d("seed", 0, "Seed for the random initialisation and for exploration", 0, 2**31 - 1)
        device = d(
            "device", "auto", "Torch device: auto (cuda when present, else cpu), cpu or cuda", choices=("auto", "cpu", "cuda")
        )
        self.step_duration_s = d("step_duration_s", 0.5, "Duration of one sim step (s); must equal sim_node's", 0.01, 5.0)
        names = d("action_names", [a.name for a in PAPER_ACTIONS], "Action names (q_values layout labels)")
        lin = d("action_linear_x_mps", [a.linear_x_mps for a in PAPER_ACTIONS], "Forward speed of each action (m/s)")
        yaw = d("action_yaw_deg", [a.yaw_deg_per_step for a in PAPER_ACTIONS], "Yaw turned during one step (deg, left +)")
        frames = d("frame_stack", NetConfig.frames, "Depth frames in the state", 1, MAX_FRAMES)
        height = d("input_height", 64, "Network input height (px); frames of another size are resized", 8, 512)
        width = d("input_width", 64, "Network input width (px)", 8, 512)
        max_range = d("max_range_m", 10.0, "Depth normalisation range (m); match sim_node's max_range_m", 0.5, 100.0)
        readout = d(
            "sam_readout",
            "max",
            "SAM readout: max pools the nodes (the paper's design); flatten keeps each node's place (an extension); "
            "must match the weights",
            choices=SAM_READOUTS,
        )
        self.publish_overlay = d("publish_overlay", True, "Publish attention/overlay (rgb8)")
        self.wait_for_trainer = d(
            "wait_for_trainer",
            False,
            "Lockstep learning: answer a frame only once trainer_node releases it over ~/push_weights (after its "
            "updates from the step that produced the frame, with their weights and epsilon), as inprocess acts",
        )
        self.wait_timeout_s = d(
            "wait_for_trainer_timeout_s",
            10.0,
            "wait_for_trainer: a frame held this long is answered anyway, with a warning (the run is then no longer in lockstep)",
            0.1,
            3600.0,
        )
        threads = d("torch_threads", 1, "Torch intra-op threads (batch-1 inference gains nothing from more)", 1, 256)
        torch.set_num_threads(threads)
        try:
            self.actions = make_actions(names, lin, yaw)
        except ValueError as e:
            raise ParameterError(f"parameters 'action_*': {e}") from None
        self.cfg = NetConfig(
            model=model,
            frames=frames,
            height=height,
            width=width,
            actions=len(self.actions),
            max_range_m=max_range,
            sam_readout=readout,
        )
        device = resolve_device(device)
        net, source, self.weights_hfov_deg = self._initial_network(weights_files(weights_arg), seed)
        self.camera_hfov_deg = None  # from depth/camera_info
        self._camera_warned = None
        self.agent = Agent(net, self.cfg, device, seed)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        q = contract.STREAM_QOS
        self.pub_cmd = self.create_publisher(Twist, contract.CMD_VEL_TOPIC, q)
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
        self.create_service(SetParameters, "~/push_weights", self._on_push, callback_group=MutuallyExclusiveCallbackGroup())
        self.stack = FrameStack(frames)
        self.held: list[tuple[int, float, Image, Range]] = []  # wait_for_trainer: (stamp, since, frame, outcome)
        self.released_ns = -1  # wait_for_trainer: frames stamped up to this may be answered
        self.timed_out = 0
        if self.wait_for_trainer:
            self.create_timer(min(1.0, self.wait_timeout_s / 4), self._check_held)
        self.last_stamp = None
        self.last_cmd, self.last_cmd_unheard = None, False
        self.q_label = "action:" + ",".join(a.name for a in self.actions)
        self.source = source
        self.acted, self.bad_frames, self.pushes_accepted, self.pushes_rejected = 0, 0, 0, 0
        self.act_s = 0.0  # time spent answering frames since the last report (network and publishing)
        self._reported = (time.monotonic(), 0, 0)  # (when, acted, bad_frames) at the last report
        self.pub_diag = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, 10)
        self.create_timer(1.0, self.publish_diagnostics)
        self.get_logger().info(
            f"model {model} ({parameter_count(net)} parameters, {source}"
            + (f", trained with a {self.weights_hfov_deg:g} deg camera" if self.weights_hfov_deg is not None else "")
            + f") on {device}; epsilon {self.epsilon}; "
            + ("answering each frame once trainer_node releases it (lockstep learning); " if self.wait_for_trainer else "")
            + (
                "attention on attention, attention/overlay, attention/weights"
                if model == "sam"
                else "cnn has no attention module: the attention topics are not published"
            )
        )

    def _initial_network(self, paths: list[str], seed: int):
        """(network, where it came from, the camera field of view it was trained with or None)."""
        if paths:
            return self._from_files(paths)
        packaged = wio.packaged_weights(self.cfg.model)
        if packaged:
            try:
                net, source, camera = self._from_files([str(p) for p in packaged])
                return net, f"packaged pretrained weights: {source}", camera
            except ParameterError as e:
                self.get_logger().warning(f"packaged weights unusable ({e}); using a random initialisation")
        net = build_network(self.cfg, seed=seed)
        return net, f"no weights given or packaged: seeded random initialisation (seed {seed})", None

    def _from_files(self, paths: list[str]):
        """_initial_network for the 'weights' files: one network, or several as one QEnsemble (they
        must share architecture and camera)."""
        nets = []
        for path in paths:
            try:
                nets.append(self._load_file(path))
            except wio.WeightsError as e:
                raise ParameterError(f"parameter 'weights': {e}{self._size_hint(path)}") from None
        try:
            net = nets[0] if len(nets) == 1 else QEnsemble(nets, self.ensemble_rule)
            cameras = {wio.read_file_camera(p) for p in paths}
        except ValueError as e:  # WeightsError included
            raise ParameterError(f"parameter 'weights': {e}") from None
        if len(cameras) != 1:
            known = sorted(c for c in cameras if c is not None)
            shown = ", ".join(["none recorded"] * (None in cameras) + [f"{c:g} deg" for c in known])
            raise ParameterError(f"parameter 'weights': the files were trained with different cameras ({shown})")
        if len(nets) == 1:
            source = f"weights from {paths[0]}"
        else:
            joined = "mean Q-values" if self.ensemble_rule == "mean" else "lowest Q-value per action"
            folders = {str(Path(f).parent) for f in paths}
            named = ", ".join(paths)
            if len(folders) == 1:  # one run's snapshots, or the packaged files: the folder once
                named = ", ".join(Path(f).name for f in paths) + f" in {folders.pop()}"
            source = f"an ensemble of {len(paths)} weights files acting on their {joined}: {named}"
        return net, source, cameras.pop()

    def _load_file(self, path) -> torch.nn.Module:
        """The file's network, with the layer sizes the file was made with (networks.SIZE_FIELDS: no
        parameter sets them, and pushes may change them). Everything else must match the parameters."""
        net = wio.load_file(path, self.cfg, sizes_from_blob=True)
        self.cfg = net.cfg
        return net

    def _size_hint(self, path: str) -> str:
        """What to set when a weights file was made for another input size or frame stack ('' otherwise)."""
        try:
            made = wio.read_file_config(path)
        except wio.WeightsError:
            return ""
        hint = ""
        if (made.height, made.width) != (self.cfg.height, self.cfg.width):
            hint += (
                f"; the file takes {made.width}x{made.height} frames: set input_height:={made.height} "
                f"input_width:={made.width} (and sim_node's image_width/image_height to match)"
            )
        if made.frames != self.cfg.frames:
            hint += f"; the file stacks {made.frames} frames: set frame_stack:={made.frames}"
        return hint

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
        key = self._camera_mismatch()
        if key is None:
            return
        trained, camera = self.weights_hfov_deg, self.camera_hfov_deg
        if key != self._camera_warned:
            self._camera_warned = key
            self.get_logger().warning(
                f"the weights were trained with a {trained:g} deg camera, but depth/camera_info says {camera:.1f} deg: "
                f"expect more crashes (run sim_node with hfov_deg:={trained:g})"
            )

    def _camera_mismatch(self) -> tuple[float, float] | None:
        """(trained, camera) field of view, rounded, when they differ by more than 0.5 deg."""
        trained, camera = self.weights_hfov_deg, self.camera_hfov_deg
        if trained is None or camera is None or abs(trained - camera) <= 0.5:
            return None
        return round(trained, 1), round(camera, 1)

    def _on_set_parameters(self, params):
        for p in params:
            if p.name == "epsilon":
                v = p.value
                if not isinstance(v, float) or not 0.0 <= v <= 1.0:
                    return SetParametersResult(successful=False, reason="epsilon must be a float in [0, 1]")
                self.epsilon = v
        return SetParametersResult(successful=True)

    # -- frames -------------------------------------------------------------------------
    def _on(self, stream: str, msg) -> None:
        stamp = contract.stamp_ns(msg.header.stamp)
        joined = self.joiner.add(stream, stamp, msg)
        if joined is not None and self.wait_for_trainer and stamp > self.released_ns:
            self.held.append((stamp, time.monotonic(), joined["frame"], joined["outcome"]))
        elif joined is not None:
            self._act(joined["frame"], joined["outcome"])
        elif stream == "frame" and stamp == self.last_stamp and self.last_cmd_unheard:
            # The simulator said an answered frame again, and our command went out before anyone
            # listened (discovery): answer again. A command that had a reliable listener is only
            # late (a busy machine); answering it twice would advance a lockstep sim two steps.
            self.last_cmd_unheard = self.pub_cmd.get_subscription_count() == 0
            self.pub_cmd.publish(self.last_cmd)

    def _answer_released(self) -> None:
        """wait_for_trainer: answer the held frames trainer_node has released, oldest first."""
        while self.held and self.held[0][0] <= self.released_ns:
            _, _, img, outcome = self.held.pop(0)
            self._act(img, outcome)

    def _check_held(self) -> None:
        """wait_for_trainer: a frame the trainer has not released in time is answered anyway (no trainer, or
        one that stopped), so the vehicle never stalls; the run has left lockstep and the warning says so."""
        if self.held and time.monotonic() - self.held[0][1] > self.wait_timeout_s:
            self.timed_out += 1
            self.get_logger().warning(
                f"trainer_node did not release the frame at {self.held[0][0] / 1e9:.1f} s sim time within "
                f"{self.wait_timeout_s:g} s: answering it anyway ({self.timed_out} so far; learning is no longer in lockstep)",
                throttle_duration_sec=10.0,
            )
            self.released_ns = max(self.released_ns, self.held[0][0])
            self._answer_released()

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
        stamped.header.frame_id = "base_link"
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
        when, acted, bad = self._reported
        new_acts, new_bad = self.acted - acted, self.bad_frames - bad
        self._reported = (now, self.acted, self.bad_frames)
        problems = []
        if new_bad:
            problems.append(f"{new_bad} malformed depth frame(s) ignored in the last {now - when:.1f} s")
        mismatch = self._camera_mismatch()
        if mismatch is not None:
            problems.append(f"camera {mismatch[1]:g} deg, but the weights were trained with a {mismatch[0]:g} deg camera")
        st = DiagnosticStatus(
            level=DiagnosticStatus.WARN if problems else DiagnosticStatus.OK,
            name="uav_policy",
            message="; ".join(problems) or ("acting" if new_acts else "waiting for depth frames"),
            hardware_id=self.get_fully_qualified_name(),
        )
        vals = {
            "model": self.cfg.model,
            "weights": self.source,
            "epsilon": self.epsilon,
            "frames_answered": self.acted,
            "malformed_frames": self.bad_frames,
            "pushes_accepted": self.pushes_accepted,
            "pushes_rejected": self.pushes_rejected,
            "frames_held": len(self.held),
            "released_by_timeout": self.timed_out,
            "answers_per_s": f"{new_acts / max(now - when, 1e-6):.1f}",
            "ms_per_answer": f"{1e3 * self.act_s / new_acts:.2f}" if new_acts else "-",
        }
        self.act_s = 0.0
        st.values = [KeyValue(key=k, value=str(v)) for k, v in vals.items()]
        msg = DiagnosticArray(status=[st])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)

    def _publish_insight(self, img: Image, depth: np.ndarray, q: np.ndarray, w) -> None:
        qmsg = Float32MultiArray(data=q.astype(np.float32).tolist())
        qmsg.layout.dim = [MultiArrayDimension(label=self.q_label, size=len(q), stride=len(q))]
        self.pub_q.publish(qmsg)
        if w is None:
            return
        grid = self.agent.net.grid_hw
        amap = attention_map(w, grid, depth.shape)
        self.pub_att.publish(contract.depth_to_image(amap, img.header.stamp, img.header.frame_id))
        if self.publish_overlay and self.pub_overlay.get_subscription_count() > 0:
            rgb = overlay(depth, amap, self.cfg.max_range_m)
            om = Image(
                header=img.header,
                height=rgb.shape[0],
                width=rgb.shape[1],
                encoding="rgb8",
                is_bigendian=0,
                step=3 * rgb.shape[1],
                data=rgb.tobytes(),
            )
            self.pub_overlay.publish(om)
        if self.pub_weights.get_subscription_count() > 0:
            h, n, _ = w.shape
            wm = Float32MultiArray()
            wm.layout.dim = [
                MultiArrayDimension(label="heads", size=h, stride=h * n * n),
                MultiArrayDimension(label=f"query_nodes(grid {grid[0]}x{grid[1]} row-major)", size=n, stride=n * n),
                MultiArrayDimension(label="key_nodes", size=n, stride=n),
            ]
            wm.data = w.astype(np.float32).ravel().tolist()
            self.pub_weights.publish(wm)

    # -- weight pushes ------------------------------------------------------------------
    def _in_thread(self, fn) -> Future:
        """Run fn on a worker thread; the returned future can be awaited in a callback."""
        fut = Future(executor=self.executor)

        def work():
            try:
                fut.set_result(fn())
            except Exception as e:  # handed to the awaiting callback
                fut.set_exception(e)

        threading.Thread(target=work, daemon=True).start()
        return fut

    async def _on_push(self, request, response):
        t0 = time.perf_counter()
        result = SetParametersResult(successful=False)
        push = None
        try:
            push = read_push(request.parameters, wio.MAX_BYTES)
            blob = push.weights
            if blob is not None:
                # The trainer owns the layer sizes: a push may bring others (the interface must match).
                load = lambda: wio.load_bytes(blob, self.cfg, sizes_from_blob=True)  # noqa: E731
                # A release is awaited by the frame it releases, so it loads here (a few ms): a worker thread's
                # result wakes this executor only at its next event, up to a timer period later.
                net = load() if push.release_stamp_ns is not None else await self._in_thread(load)
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
            self.released_ns = max(self.released_ns, push.release_stamp_ns)
            self._answer_released()
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
