"""policy_node: flies the quadrotor with D3QN-SAM or D3QN-CNN and publishes what it attends to.

Wiring only; each job has its module: frames onto the network's input (camera_input), one camera per stack
(camera_identity); a simulator's frames joined with their outcomes, stacked, held for lockstep learning
(simulator_link); a camera alone answered at most control_rate_hz, with a stop when frames stop (camera_control);
the decision, shield, local map and safety layer (pilot, shield, safety); cmd_vel, action, q_values, attention or
Grad-CAM (outputs); what decisions look at (explainer, insight); signed weight pushes (push_receiver); answers counted."""

from __future__ import annotations

import time

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from uav_common import contract
from uav_common.node_runner import in_thread, run
from uav_common.ros_params import NodeOwned, ParameterError
from uav_common.settings import declare_settings
from uav_interfaces.msg import StepOutcome

from . import weights as wio
from .agent import Agent, resolve_device
from .answer_stats import AnswerStats
from .camera_control import CameraControl
from .camera_identity import CameraIdentity
from .camera_input import CameraInput
from .config import RETIRED, PolicySettings
from .explainer import Explainer
from .networks import NetConfig, parameter_count, swap_notes
from .outputs import Outputs
from .pilot import Pilot
from .push import PUSH_QOS, PushService
from .push_receiver import PushReceiver, Refused
from .safety import Interventions, SafetyLayer
from .shield import ShieldFeed
from .simulator_link import SimulatorLink


class PolicyNode(Node):
    def __init__(self, **node_options):  # e.g. context=: built in a test's own context
        super().__init__("policy_node", **node_options)
        st = declare_settings(self, PolicySettings, RETIRED)
        st.check()
        log = self.get_logger()
        self.epsilon = st.epsilon
        why = "is set by the trainer's pushes" if st.accept_pushes else "is fixed at start-up while flying (-p epsilon:=X)"
        self.epsilon_param = NodeOwned(self, "epsilon", why)
        self.wait_for_trainer, self.simulator = st.wait_for_trainer, st.source == "simulator"
        torch.set_num_threads(st.torch_threads)
        try:
            self.actions = st.actions.table()
        except ValueError as e:
            raise ParameterError(f"parameters 'action_*': {e}") from None
        size = dict(frames=st.frame_stack, height=st.input_height, width=st.input_width, max_range_m=st.max_range_m)
        cfg = NetConfig(model=st.model, actions=len(self.actions), local_map=st.local_map, **size)
        try:
            device = resolve_device(st.device)
            files = wio.parse_files(st.weights)
        except ValueError as e:
            raise ParameterError(f"parameter {e}") from None
        try:
            net, self.source, hfov = wio.policy_network(files, cfg, st.seed, log.warning)
        except ValueError as e:  # WeightsError included
            raise ParameterError(f"parameter 'weights': {e}") from None
        self.cfg = net.cfg  # with the files' layer sizes
        trained = hfov if hfov is not None else wio.UNRECORDED_HFOV_DEG
        self.safety = SafetyLayer(st.safety, self.cfg.height, self.cfg.width, trained) if st.safety.safety else None
        on_view = self.safety.set_hfov if self.safety else lambda _hfov: None
        self.camera = CameraInput(self.cfg.height, self.cfg.width, hfov, log, on_view)
        period = 1.0 / st.control_rate_hz
        self.control = CameraControl(st.frame_stack, st.step_duration_s, period, st.safety.frame_timeout_s, log)
        mapped = st.shield.shield != "never" or self.cfg.local_map  # the shield's, or the network's input
        self.shield = ShieldFeed(self.actions, st.step_duration_s, st.shield, log, self.cfg.local_map) if mapped else None
        joins = st.shield.shield == "always" or self.cfg.local_map  # a simulator's frames wait for their stamp's odom
        self.link = SimulatorLink(st.frame_stack, st.wait_for_trainer, st.wait_for_trainer_timeout_s, log, joins)
        self.identity = CameraIdentity(st.camera_switch_s, log, stacks=(self.control, self.link))  # one camera a stack
        self.agent = Agent(net, self.cfg, device, st.seed)
        self.pilot = Pilot(self.agent, self.actions, st.step_duration_s, self.safety)
        self.receiver = PushReceiver(st.push_key_file, self.link.gate, period, log, len(self.actions))
        if st.accept_pushes:
            self.receiver.time_inference(self.agent)
        self.explainer = Explainer(net.grid_hw, st.insight_every, st.insight_window, st.seed, log)
        self.out = Outputs(self, self.actions, st.publish_stamped, st.publish_overlay, st.max_range_m)
        self.stats = AnswerStats()
        self.pub_diag = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, 10)
        # Camera drivers publish best effort; a best-effort reader takes sim_node's reliable frames too.
        self.create_subscription(Image, contract.DEPTH_TOPIC, self._on_frame, contract.SENSOR_QOS)
        self.create_subscription(StepOutcome, contract.OUTCOME_TOPIC, lambda m: self._on("outcome", m), contract.STREAM_QOS)
        self.create_subscription(CameraInfo, contract.CAMERA_INFO_TOPIC, self._on_camera_info, contract.SENSOR_QOS)
        if self.shield:
            self.create_subscription(Odometry, contract.ODOM_TOPIC, self._on_odom, contract.SENSOR_QOS)
        topics = (contract.OUTCOME_TOPIC, contract.CAMERA_INFO_TOPIC, contract.DEPTH_TOPIC)
        self.outcome_topic, self.info_topic, self.depth_topic = map(self.resolve_topic_name, topics)
        self.frame_awaiting_info = None  # the newest frame that waited for depth/camera_info
        # Pushes are validated on a worker thread, in their own callback group (a suspended callback holds its group).
        if st.accept_pushes:
            group = MutuallyExclusiveCallbackGroup()
            self.create_service(PushService, "~/push_weights", self._on_push, qos_profile=PUSH_QOS, callback_group=group)
        if self.wait_for_trainer:
            self.create_timer(min(1.0, st.wait_for_trainer_timeout_s / 4), self._check_held)
        self.create_timer(period / 2, self._control_tick)
        self.create_timer(1.0, self.publish_diagnostics)
        log.info(st.describe(parameter_count(net), self.source, device, hfov))

    def _on_camera_info(self, msg: CameraInfo) -> None:
        intrinsics = contract.camera_info_intrinsics(msg)
        if not self.camera.on_info(intrinsics, contract.camera_info_hfov_deg(msg) if intrinsics else None):
            return
        if self.frame_awaiting_info is not None:
            held, self.frame_awaiting_info = self.frame_awaiting_info, None
            self.stats.received -= 1  # counted when it came
            self._on("frame", held)

    def _on_odom(self, msg: Odometry) -> None:
        if self.shield.odometry(msg.header.stamp, contract.odometry_pose(msg)) and self.shield.joins(self.control.active):
            self._on("odom", msg)

    def _on_frame(self, msg: Image, info: dict) -> None:
        self.stats.arrived(info.get("publication_sequence_number"), lambda: self.count_publishers(self.depth_topic))
        self._on("frame", msg)

    def _on(self, stream: str, msg) -> None:
        t_in = time.perf_counter()
        stamp = contract.stamp_ns(msg.header.stamp)
        if stream == "frame":
            if not self.identity.admit(msg.header.frame_id, time.monotonic()):
                return  # another camera's frame on this topic
            self.stats.received += stamp != self.link.last_stamp  # a frame said again is not new
            offered = lambda: self.count_publishers(self.info_topic) > 0  # noqa: E731
            if self.camera.should_wait(msg.height, msg.width, time.monotonic(), offered):
                self.frame_awaiting_info = msg  # answered when its CameraInfo comes (a lockstep sim waits for it)
                return
            if not (self.wait_for_trainer or self.simulator) and self.count_publishers(self.outcome_topic) == 0:
                self._on_camera_frame(msg, stamp, t_in)
                return
            if self.control.active:
                self._simulator_found()
        joined, restarted = self.link.add(stream, stamp, msg, time.monotonic())
        if restarted:
            self.out.forget()
        if joined is not None:
            self._act(joined, t_in)
        elif stream == "frame" and stamp == self.link.last_stamp:
            self.out.say_again()

    def _check_held(self) -> None:
        for joined in self.link.expired(time.monotonic()):
            self._act(joined, time.perf_counter())

    def _on_camera_frame(self, img: Image, stamp: int, t_in: float) -> None:
        """A camera's frame (no simulator): answered now, or at a control tick (uav_policy.camera_control)."""
        depth = self.stats.decode(img, self.get_logger())
        if depth is not None:
            net_in = self.camera(depth)
            if self.control.add(stamp / 1e9, net_in, (t_in, img, depth, net_in), time.monotonic()):
                self._answer_pending()

    def _answer_pending(self) -> None:
        (t_in, img, depth, net_in), state = self.control.take()
        self._decide(img, depth, net_in, state, t_in)

    def _control_tick(self) -> None:
        now = time.monotonic()
        due = self.control.tick(now, stops=self.safety is not None)
        if due == "answer":
            self._answer_pending()
        elif due == "stop":
            if self.count_publishers(self.outcome_topic) > 0:  # a lockstep simulator waits for us: never stop it
                self._simulator_found()
                return
            self.safety.counts.stops_no_frames += 1
            self.control.stopped(now)
            self.out.command(Twist(), self.get_clock().now().to_msg())

    def _simulator_found(self) -> None:
        """Frames answered as a camera's came from a simulator: from now on each is answered with its outcome."""
        state = self.control.hand_over()
        if state is not None:
            self.link.stack.restore(state)

    def _act(self, joined: dict, t_in: float) -> None:
        """A simulator's frame, joined with its step's outcome (and odometry, with a shield): answered at once."""
        img, outcome, odom = joined["frame"], joined["outcome"], joined.get("odom")
        if contract.stamp_ns(img.header.stamp) == self.link.last_stamp:
            return  # already answered (before the simulator's step_outcome was discovered)
        depth = self.stats.decode(img, self.get_logger())
        if depth is not None:
            net_in = self.camera(depth)
            new = contract.outcome_new_episode(outcome)
            state = self.link.state(net_in, new)
            self._decide(img, depth, net_in, state, t_in, (contract.odometry_pose(odom) if odom else None, new))

    def _decide(self, img: Image, depth: np.ndarray, net_in: np.ndarray, state: np.ndarray, t_in: float, sim=()) -> None:
        t0 = time.perf_counter()
        stamp = contract.stamp_ns(img.header.stamp)
        if self.shield:  # auto: on for a camera's frames (a drone), off for a simulator's
            self.pilot.shield = self.shield.frame(depth, self.camera.intrinsics, stamp, *sim, camera=self.control.active)
            state = self.shield.with_map(state, self.cfg.map_grid) if self.cfg.local_map else state
        fly = self.link.gate.fly_action_for(stamp)  # a teacher's, in training
        d = self.pilot.decide(state, net_in, self.epsilon, instead=fly)
        if d.safety or d.shield:
            self.get_logger().info(f"{d.shield or d.safety}", throttle_duration_sec=2.0)
        self.out.decision(img, d, self.pilot.command_of)
        t_out = time.perf_counter()
        self.link.last_stamp = contract.stamp_ns(img.header.stamp)
        net = self.agent.net
        grid = state[-1] if self.cfg.local_map else None  # the map channel: drawn top-down with its attention
        saliency = self.out.explained(img, depth, d, net.grid_hw, self.camera.view, grid)
        inline = not self.control.active  # a simulator waits for our answer: measure now
        self.explainer.explain(net, state, d.q, d.attention, self.stats.answered, saliency, inline)
        self.stats.answer(t_in, t0, t_out)

    async def _on_push(self, request, response):
        t0 = time.perf_counter()
        response.success = False
        try:
            push = self.receiver.authenticate(request)
        except Refused as e:  # nothing of it is taken, no frame is released
            response.message = str(e)
            return response
        except ValueError as e:
            push, response.message = None, str(e)
        if push is not None:
            try:
                blob = push.weights
                if blob is not None:
                    reuse = not self.explainer.busy.locked()  # the worker may still measure the network replaced
                    load = lambda: self.receiver.load(blob, self.cfg, reuse)  # noqa: E731
                    # A release is awaited by the frame it releases, so it loads here (a few ms): a worker thread's
                    # result wakes this executor only at its next event, up to a timer period later.
                    net = load() if push.release_stamp_ns is not None else await in_thread(self.executor, load)
                    self._swap_in(net, blob)
                if push.epsilon is not None:
                    self.epsilon = push.epsilon
                response.success = True
                response.message = f"swapped in {len(blob)} bytes in {1e3 * (time.perf_counter() - t0):.1f} ms" if blob else "ok"
            except ValueError as e:  # WeightsError included
                response.message = str(e)
        released = push is not None and push.release_stamp_ns is not None
        if not response.success:
            response.message = self.receiver.reject(response.message, released)
        if released:
            for joined in self.link.gate.release(push.release_stamp_ns, push.fly_action):
                self._act(joined, time.perf_counter())
        if response.success and push.epsilon is not None:  # after the answer: ros2 param get and /diagnostics agree
            self.epsilon_param.set(push.epsilon)
        return response

    def _swap_in(self, net: torch.nn.Module, blob: bytes) -> None:
        replaced = self.agent.net
        self.agent.swap(net)
        self.receiver.retire(replaced)
        for line in swap_notes(replaced, net, self.cfg):
            self.get_logger().info(line)
        self.explainer.regrid(net.grid_hw)
        self.cfg = net.cfg
        self.camera.set_weights(self.cfg.height, self.cfg.width, wio.read_header_camera(blob))
        self.receiver.accepted += 1
        self.source = f"pushed weights ({len(blob)} bytes)"

    def publish_diagnostics(self) -> None:
        """1 Hz: frames answered or ignored, pushes; ERROR while another camera's frames come, WARN on other problems."""
        now = time.monotonic()
        problems, answers = self.stats.report(now, waiting=bool(self.link.gate.held))
        problems += [p for p in (self.identity.problem(now), self.control.problem(now), self.camera.problem()) if p]
        vals = {
            "model": self.cfg.model,
            "weights": self.source,
            "epsilon": self.epsilon,
            **answers,
            **self.receiver.values(),
            **self.link.values(),
            "source": "camera" if self.control.active else "simulator" if self.stats.answered else "-",
            "camera_restarts": self.control.restarts,
            **self.camera.values(),
            **self.identity.values(),
            **(self.safety.counts if self.safety else Interventions()).values(on=self.safety is not None),
            **(self.shield.values(self.pilot.shield is not None) if self.shield else {"shield": "off"}),
            "explained_by": "attention" if self.cfg.model == "sam" else "saliency (Grad-CAM)",
            **self.explainer.values(),
            **self.out.listeners(),  # a recorder waits until we hear it too (uav_bringup.record)
        }
        message = "; ".join(problems) or ("acting" if self.stats.recent else "waiting for depth frames")
        level = "ERROR" if self.identity.problem(now) else "WARN" if problems else "OK"
        self.pub_diag.publish(contract.diagnostics(self, "uav_policy", level, message, vals))


def main(args=None) -> int:
    return run(PolicyNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
