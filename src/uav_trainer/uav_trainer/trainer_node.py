"""trainer_node: replay memory, learning, weight pushes and checkpoints over ROS 2.

Joins depth/image_raw, step_outcome, the policy's action (with a teacher sim_node's teacher_label, with the local map its
odom) by exact stamp into transitions (uav_trainer.pairing; reward: uav_sim.reward); nothing is guessed. Learning
is in lockstep with acting (policy_node's wait_for_trainer:=true; train sets it): each stored step's frame is released
on policy_node/push_weights with the exact epsilon, the weights as at the release before (Training.released_weights) and
whether the teacher flies it (Training.teacher_flies); then the updates replay_ratio allows run while the policy acts and
the simulator steps, as in process (for a seed, the same episodes and weights as `inprocess`).

With `actors` (namespaces; `train --actors N` sets them) it learns from several sim_node/policy_node pairs, each joined
on its own into its lane of one replay memory and released with its own epsilon (Ape-X); they interleave in arrival
order (not bit-reproducible). An actor that falls silent is reported and training goes on (uav_trainer.actors); outcomes
from other namespaces are counted and ignored. The camera and reward window go into the weights files (camera_record).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from uav_common import contract
from uav_common.actions import turning_indices
from uav_common.node_runner import run
from uav_common.ros_params import ParameterError
from uav_common.settings import declare_settings
from uav_interfaces.msg import StepOutcome, TeacherLabel
from uav_policy.agent import resolve_device
from uav_policy.networks import parameter_count
from uav_policy.push import PushService, load_key, push_request, write_key

from .actors import REJECTED_WEIGHTS, ActorState
from .camera_record import CameraRecord
from .pairing import TransitionAssembler
from .trainer_settings import TrainerNodeSettings, describe
from .trainer_status import progress_line, status_values
from .training import RunDirError, Training
from .training_config import RETIRED
from .unknown_actors import UnknownActors

UNWRITTEN_EXIT_CODE = 4  # the run ended, but weights files it names were not written (train says which)


class Actor(ActorState):
    """One sim_node/policy_node pair the trainer learns from: its joins, its release client and (actors.ActorState)
    its release chain and whether it is alive."""

    def __init__(self, node: TrainerNode, index: int, namespace: str, policy: str, hw: tuple[int, int]):
        topic = lambda name: f"{namespace.rstrip('/')}/{name}" if namespace else name  # noqa: E731 ("/": the root)
        super().__init__(index, namespace, node.resolve_topic_name(topic(contract.OUTCOME_TOPIC)))
        # With a teacher, sim_node's teacher_label completes each observation (its action, scores and reason).
        teacher = node.cfg.teacher != "none"
        on_ready, sink = lambda stamp: node._on_ready(self, stamp), node.training.sink(index)
        grid = node.training.reason_grid  # with attention_weight: the cells the label's reason is shared over
        maps = node.training.net_cfg.map_grid  # a network with the local map: sim_node's odom completes it too
        self.pairing = TransitionAssembler(
            sink, node.actions, node.step_ns, hw, on_ready=on_ready, teacher=teacher, reason_grid=grid, map_grid=maps
        )
        self.node = node
        q = contract.DEEP_QOS
        if teacher:
            node.create_subscription(TeacherLabel, topic(contract.TEACHER_TOPIC), self.on_teacher, q)
        if maps:
            node.create_subscription(Odometry, topic(contract.ODOM_TOPIC), lambda m: self.pairing.add("odom", m), q)
        node.create_subscription(Image, topic(contract.DEPTH_TOPIC), self.on_frame, q)
        node.create_subscription(StepOutcome, topic(contract.OUTCOME_TOPIC), self.on_outcome, q)
        node.create_subscription(TwistStamped, topic(contract.ACTION_TOPIC), lambda m: node._on_action(self, m), q)
        # The camera's field of view goes into every weights file (policy_node warns on a mismatch).
        node.create_subscription(CameraInfo, topic(contract.CAMERA_INFO_TOPIC), node._on_camera_info, 10)
        self.push_client = node.create_client(PushService, topic(f"{policy}/push_weights"))
        self.get_param_client = node.create_client(GetParameters, topic(f"{policy}/get_parameters"))
        self.policy_waits, self.wait_query = None, None  # whether policy_node waits for releases, asked once

    def on_frame(self, msg: Image) -> None:
        self._heard()
        self.frames_heard += 1
        self.pairing.add("frame", msg)

    def on_outcome(self, msg: StepOutcome) -> None:
        self._heard()
        self.pairing.add("outcome", msg)
        self.node.camera.on_outcome_fov(msg.window_fov_rad)

    def _heard(self) -> None:
        said = self.heard(time.monotonic())
        if said:
            self.node.get_logger().info(said)


class TrainerNode(Node):
    def __init__(self, **node_options):  # e.g. context=: built in a test's own context
        super().__init__("trainer_node", **node_options)
        st = declare_settings(self, TrainerNodeSettings, RETIRED)
        try:
            self.actions = st.actions.table()
        except ValueError as e:
            raise ParameterError(f"parameters 'action_*': {e}") from None
        namespaces = st.actor_namespaces()  # ParameterError for bad namespaces, or a setting ROS cannot train with
        self.cfg = dataclasses.replace(st.trainer, turning_actions=turning_indices(self.actions))
        try:
            resolve_device(self.cfg.device)
            self.cfg.validate()
        except ValueError as e:
            raise ParameterError(f"parameter {e}") from None
        self.step_ns = int(round(1e9 * st.step_duration_s))
        torch.set_num_threads(st.torch_threads)
        try:
            self.training = Training(self.cfg, st.run_dir, log=self.get_logger().info, resume=st.resume, actors=len(namespaces))
        except RunDirError as e:
            raise ParameterError(f"parameter {e}") from None

        hw = (self.training.net_cfg.height, self.training.net_cfg.width)
        self.camera = CameraRecord(self.training, self.get_logger(), self._set_camera)
        self.actors = [Actor(self, i, ns, st.policy_node, hw) for i, ns in enumerate(namespaces)]
        self.pub_diag = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, 10)
        key_file = Path(st.push_key_file or self.training.dir / "push.key")
        try:
            if not key_file.exists():
                write_key(key_file)
            self.push_key = load_key(key_file)
        except (OSError, ValueError) as e:
            raise ParameterError(f"parameter 'push_key_file': {e}") from None
        self.push_seq = 0
        self.release_timeout_s = st.release_timeout_s
        self.actor_timeout_s = st.actor_timeout_s
        self.started = time.monotonic()
        # unreleased_answers: answers to frames this node had not released, i.e. not in lockstep
        self.counts = {"pushes_ok": 0, "pushes_rejected": 0, "unreleased_answers": 0, "release_retries": 0}
        self.counts.update(actors_missing=0, actors_lost=0)
        self.unknown = UnknownActors(self, self.actors, self.counts)
        self.push_latency_ms: list[float] = []
        self.exit_code = 0
        self.create_timer(0.05, self._service_tick)
        self.create_timer(st.log_interval_s, self._report)
        self._closed = False
        parameters = parameter_count(self.training.learner.online)
        self.get_logger().info(describe(self.cfg, self.training, parameters, namespaces, key_file))

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self.camera.on_info(contract.camera_info_hfov_deg(msg), msg.width, contract.camera_info_intrinsics(msg))

    def _set_camera(self, intrinsics, hfov_deg: float) -> None:
        for actor in self.actors:
            actor.pairing.set_camera(intrinsics, hfov_deg)

    def _check_policy_waits(self, actor: Actor) -> None:
        """Ask an actor's policy_node once whether it waits for releases; say so loudly when it does not."""
        if actor.policy_waits is not None or actor.wait_query is not None or not actor.get_param_client.service_is_ready():
            return
        actor.wait_query = actor.get_param_client.call_async(GetParameters.Request(names=["wait_for_trainer"]))
        actor.wait_query.add_done_callback(lambda fut: self._policy_waits_known(actor, fut))

    def _policy_waits_known(self, actor: Actor, fut) -> None:
        values = fut.result().values if fut.result() else []
        actor.policy_waits = bool(values) and values[0].type == ParameterType.PARAMETER_BOOL and values[0].bool_value
        if not actor.policy_waits:
            self.get_logger().error(
                f"{actor.policy} does not wait for releases (its wait_for_trainer is not true), so it acts "
                "before learning and the run is not in lockstep; give policy_node wait_for_trainer:=true (train does)"
            )

    def _on_action(self, actor: Actor, msg: TwistStamped) -> None:
        if contract.stamp_ns(msg.header.stamp) > actor.pairing.released:
            self.counts["unreleased_answers"] += 1
            self.get_logger().warning(
                f"{actor.policy} answered a frame this node had not released "
                f"({self.counts['unreleased_answers']} so far): learning is not in lockstep; give policy_node "
                "wait_for_trainer:=true (train does)",
                throttle_duration_sec=30.0,
            )
        actor.pairing.add("action", msg)

    # -- learning ----------------------------------------------------------------------
    def _on_ready(self, actor: Actor, stamp: int) -> None:
        """`actor`'s step to frame `stamp` is stored: release the frame, then learn (_send_go). After the budget's last
        step nothing is released, the last updates are made and _service_tick stops the node."""
        if self.training.failed or self.training.budget_done:
            self._learn()
        else:
            actor.go_stamp = stamp
            self._send_go(actor)

    def _learn(self) -> None:
        for path in self.training.learn_due():  # the updates replay_ratio allows now, then the snapshots due
            self.get_logger().info(f"step {self.training.env_steps}: weights snapshot {path}")

    def _send_go(self, actor: Actor) -> None:
        """Release the frame with its epsilon and the released weights, then learn. A release that waits (for the push
        in flight or the service) holds the learning back, so every release goes out before its step's updates."""
        if actor.go_stamp is None or actor.in_flight is not None or not actor.push_client.service_is_ready():
            return  # _service_tick retries; a push in flight is answered before the next release goes
        version, blob = self.training.released_weights()  # None below: its policy has them
        blob = blob if actor.weights_due(version) else None
        # Larger than any number sent before, also by this run before a restart: the policy refuses replays.
        self.push_seq = max(self.push_seq + 1, time.time_ns())
        if actor.fly_for is None or actor.fly_for[0] != actor.go_stamp:  # drawn once a frame (a release sent again keeps it)
            actor.fly_for = (actor.go_stamp, self.training.teacher_flies(actor.pairing.teacher_of(actor.go_stamp)))
        fly = actor.fly_for[1]  # the teacher's action when it flies this step, else None
        eps = self.training.epsilon(actor.index)
        request = push_request(blob, eps, actor.go_stamp, key=self.push_key, seq=self.push_seq, fly_action=fly)
        fut = actor.push_client.call_async(request)
        t0 = time.perf_counter()
        actor.sent(fut, time.monotonic())  # in flight before its answer can be heard
        fut.add_done_callback(lambda f, t0=t0, b=blob: self._push_done(actor, f, t0, b is not None))
        self.training.after_release()  # the weights the next release carries, made while this frame is answered
        self._learn()  # while the policy acts and the simulator steps

    # -- services: pushes and epsilon -----------------------------------------------------
    def _service_tick(self) -> None:
        why = self.training.failed or next(filter(None, (a.no_teacher(self.cfg.teacher) for a in self.actors)), None)
        if why and self.exit_code == 0:  # a failed run (3), or one whose simulator has no teacher (2)
            self.get_logger().error(why)
            self.exit_code = 3 if self.training.failed else 2
            rclpy.try_shutdown(context=self.context)
            return
        if self.training.budget_done and not self._closed:
            self.get_logger().info(f"step budget of {self.cfg.total_steps} reached")
            rclpy.try_shutdown(context=self.context)
            return
        now = time.monotonic()
        for actor in self.actors:
            fell_silent = actor.check_alive(now, self.started, self.actor_timeout_s, self.actors)
            if fell_silent:
                self.counts[fell_silent[0]] += 1
                self.get_logger().error(fell_silent[1])
            self._check_policy_waits(actor)
            fut = actor.in_flight
            again = actor.overdue(now, self.release_timeout_s)  # a lost request or a busy policy never stops the run
            if again:
                actor.push_client.remove_pending_request(fut)
                self.counts["release_retries"] += 1
                self.get_logger().warning(f"{again} ({self.counts['release_retries']} so far)")
            self._send_go(actor)

    def _push_done(self, actor: Actor, fut, t0: float, weights: bool = True) -> None:
        said = actor.answered()
        if said:
            self.get_logger().info(said)
        res = fut.result()
        if res is not None and res.success:
            if weights:
                self.counts["pushes_ok"] += 1
                self.push_latency_ms.append(1e3 * (time.perf_counter() - t0))
        else:
            self.counts["pushes_rejected"] += 1
            if res is not None and self.exit_code == 0:  # close() writes the final checkpoint: the command resumes
                self.get_logger().error(REJECTED_WEIGHTS.format(policy=actor.policy, why=res.message))
                self.exit_code = 3
                rclpy.try_shutdown(context=self.context)
                return
            self.get_logger().error(f"policy rejected pushed weights: {res.message if res else 'no answer'}")
            actor.pushed_version = None  # the next release carries the weights again
        self._send_go(actor)

    # -- reporting ----------------------------------------------------------------------
    def _report(self) -> None:
        row = self.training.metrics_row()
        st = status_values(self.training, self.actors, self.counts, self.push_latency_ms)
        failed = self.training.failed
        self.pub_diag.publish(contract.diagnostics(self, "uav_trainer", "ERROR" if failed else "OK", failed or "training", st))
        self.get_logger().info(progress_line(row, st, self.training, self.actors))

    def close(self) -> None:
        """Stop learning and write the final checkpoint and weights (also on Ctrl-C)."""
        if self._closed:
            return
        self._closed = True
        path = self.training.save_checkpoint(final=True)
        if path is not None:
            self.get_logger().info(
                f"final checkpoint {path}; policy weights {self.training.policy_weights_path} "
                f"({self.training.env_steps} env steps, {self.training.learner.updates} updates)"
            )
        elif self.training.failed:
            self.get_logger().error(self.training.failed)
        report = self.training.unwritten_report()
        if report:
            self.get_logger().error(report)
            self.exit_code = self.exit_code or UNWRITTEN_EXIT_CODE
        self.training.close()


def main(args=None) -> int:
    return run(TrainerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
