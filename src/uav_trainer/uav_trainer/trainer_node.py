"""trainer_node: replay memory, learning, weight pushes and checkpoints over ROS 2.

Joins depth/image_raw, step_outcome and the policy's action (TwistStamped) by exact stamp.
Consecutive steps (stamps one step_duration_s apart) make transitions (s, a, r, s', done) with
the reward from uav_sim.reward; anything that does not pair is counted and reported on
/diagnostics and in the log, never guessed.

Learning is in lockstep with acting (policy_node needs wait_for_trainer:=true; train sets it):
after each step is stored, the updates replay_ratio allows run at once, then one push on
policy_node/push_weights carries the new weights, the exact epsilon and the frame's release, so the
policy acts on each frame exactly as the in-process loop does (for a seed, the same episodes and
weights as `inprocess` on the same machine).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, Range

from uav_common import contract
from uav_common.actions import ActionSettings, turning_indices
from uav_common.node_runner import run
from uav_common.ros_params import ParameterError
from uav_common.settings import declare_settings, setting
from uav_policy.agent import resolve_device
from uav_policy.networks import parameter_count
from uav_policy.push import PushService, load_key, push_request, write_key
from uav_policy.weights import HFOV_RANGE_DEG
from uav_sim.reward import center_window_slices, window_fraction_for_fov

from .pairing import TransitionAssembler
from .training import RETIRED, RunDirError, TrainerConfig, Training, reward_description


@dataclasses.dataclass(frozen=True)
class TrainerNodeSettings:
    """trainer_node's parameters: the training run's, the action table's and the node's own."""

    trainer: TrainerConfig = TrainerConfig()
    actions: ActionSettings = ActionSettings()
    run_dir: str = setting("runs/train", "Output directory: checkpoints, metrics, plots, policy weights")
    resume: bool = setting(True, "Resume from run_dir's latest checkpoint when there is one")
    step_duration_s: float = setting(0.5, "Sim step duration (s); must equal sim_node's", 0.01, 5.0)
    policy_node: str = setting("policy_node", "Name of the policy node to release frames and push weights to")
    log_interval_s: float = setting(5.0, "Seconds between progress lines and metrics rows", 0.1, 3600.0)
    push_key_file: str = setting(
        "",
        "The run's key that every push is signed with (policy_node must be given the same file); created, mode 0600, "
        "when missing; empty: run_dir/push.key (train writes a new one there for each run)",
    )
    release_timeout_s: float = setting(
        10.0, "A release policy_node has not answered in this long is logged and sent again", 0.1, 3600.0
    )
    torch_threads: int = setting(1, "Torch intra-op threads for the learner (2 cores are shared)", 1, 256)


class TrainerNode(Node):
    def __init__(self, **node_options):  # e.g. context=: built in a test's own context
        super().__init__("trainer_node", **node_options)
        st = declare_settings(self, TrainerNodeSettings, RETIRED)
        try:
            self.actions = st.actions.table()
        except ValueError as e:
            raise ParameterError(f"parameters 'action_*': {e}") from None
        self.cfg = dataclasses.replace(st.trainer, turning_actions=turning_indices(self.actions))
        try:
            resolve_device(self.cfg.device)
            self.cfg.validate()
        except ValueError as e:
            raise ParameterError(f"parameter {e}") from None
        self.step_ns = int(round(1e9 * st.step_duration_s))
        torch.set_num_threads(st.torch_threads)
        try:
            self.training = Training(self.cfg, st.run_dir, log=self.get_logger().info, resume=st.resume)
        except RunDirError as e:
            raise ParameterError(f"parameter {e}") from None
        policy = st.policy_node

        q = contract.DEEP_QOS
        hw = (self.training.net_cfg.height, self.training.net_cfg.width)
        self.pairing = TransitionAssembler(self.training, self.actions, self.step_ns, hw, on_ready=self._on_ready)
        self.create_subscription(Image, contract.DEPTH_TOPIC, lambda m: self.pairing.add("frame", m), q)
        self.create_subscription(Range, contract.OUTCOME_TOPIC, self._on_outcome, q)
        self.create_subscription(TwistStamped, contract.ACTION_TOPIC, self._on_action, q)
        # The camera's field of view goes into every weights file (policy_node warns on a mismatch), and so
        # does sim_node's reward window when it is not the paper's, read back from step_outcome's field_of_view.
        self.camera_width_px = None
        self.outcome_fov_rad = None
        self.create_subscription(CameraInfo, contract.CAMERA_INFO_TOPIC, self._on_camera_info, 10)
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
        self.push_client = self.create_client(PushService, f"{policy}/push_weights")
        # whether policy_node waits for releases, asked once (None: not yet known)
        self.get_param_client = self.create_client(GetParameters, f"{policy}/get_parameters")
        self.policy_waits: bool | None = None
        self._wait_query = None
        # unreleased_answers: answers to frames this node had not released, i.e. not in lockstep
        self.counts = {"pushes_ok": 0, "pushes_rejected": 0, "unreleased_answers": 0, "release_retries": 0}
        self.push_in_flight = None
        self._in_flight_stamp, self._in_flight_t0 = None, 0.0
        self.push_latency_ms: list[float] = []
        self.exit_code = 0
        self._go_stamp = None  # the newest frame to release, once the previous push is answered
        self._pushed_updates = None  # the update count of the weights the policy has
        self.create_timer(0.05, self._service_tick)
        self.create_timer(st.log_interval_s, self._report)
        self._closed = False
        self.get_logger().info(
            f"training {self.cfg.model} ({parameter_count(self.training.learner.online)} parameters, seed {self.cfg.seed}) "
            f"on {self.training.learner.device} into {self.training.dir}; "
            f"budget {self.cfg.total_steps or 'unlimited'} env steps; replay {self.cfg.replay_capacity} frames; "
            f"reward: {reward_description(self.cfg)}; learning in lockstep with acting; pushes signed with the key in "
            f"{key_file} (policy_node needs accept_pushes:=true push_key_file:={key_file} safety:=false)"
        )

    def _on_camera_info(self, msg: CameraInfo) -> None:
        hfov = contract.camera_info_hfov_deg(msg)
        if hfov is None or not HFOV_RANGE_DEG[0] <= hfov <= HFOV_RANGE_DEG[1]:
            self.get_logger().warning("ignoring malformed depth/camera_info (width or fx)", throttle_duration_sec=10.0)
            return
        hfov = round(hfov, 3)
        if hfov == self.training.camera_hfov_deg and msg.width == self.camera_width_px:
            return  # every step sends it; only a change is news
        if hfov != self.training.camera_hfov_deg:
            self.get_logger().info(f"depth camera: {hfov:g} deg horizontal field of view (recorded in the weights files)")
            self.training.camera_hfov_deg = hfov
        self.camera_width_px = msg.width
        self.pairing.set_camera(contract.camera_info_intrinsics(msg), hfov)
        self._update_window()

    def _check_policy_waits(self) -> None:
        """Ask policy_node once whether it waits for releases; say so loudly when it does not."""
        if self.policy_waits is not None or self._wait_query is not None or not self.get_param_client.service_is_ready():
            return
        self._wait_query = self.get_param_client.call_async(GetParameters.Request(names=["wait_for_trainer"]))
        self._wait_query.add_done_callback(self._policy_waits_known)

    def _policy_waits_known(self, fut) -> None:
        values = fut.result().values if fut.result() else []
        self.policy_waits = bool(values) and values[0].type == ParameterType.PARAMETER_BOOL and values[0].bool_value
        if not self.policy_waits:
            self.get_logger().error(
                "policy_node does not wait for releases (its wait_for_trainer is not true), so it acts before learning "
                "and the run is not in lockstep; give policy_node wait_for_trainer:=true (train does)"
            )

    def _on_action(self, msg: TwistStamped) -> None:
        if contract.stamp_ns(msg.header.stamp) > self.pairing.released:
            self.counts["unreleased_answers"] += 1
            self.get_logger().warning(
                f"policy_node answered a frame this node had not released ({self.counts['unreleased_answers']} so far): learning "
                "is not in lockstep; give policy_node wait_for_trainer:=true (train does)",
                throttle_duration_sec=30.0,
            )
        self.pairing.add("action", msg)

    def _on_outcome(self, msg: Range) -> None:
        self.pairing.add("outcome", msg)
        if msg.field_of_view != self.outcome_fov_rad:
            self.outcome_fov_rad = msg.field_of_view
            self._update_window()

    def _update_window(self) -> None:
        """The reward window sim_node reads beta over, from its arc (step_outcome) and the camera (camera_info)."""
        hfov, width, fov = self.training.camera_hfov_deg, self.camera_width_px, self.outcome_fov_rad
        if hfov is None or not width or fov is None or not 0.0 < fov <= math.radians(hfov) + 1e-3:  # also NaN
            return
        fraction = window_fraction_for_fov(width, hfov, fov)
        paper = center_window_slices(1, width)[1] == center_window_slices(1, width, fraction)[1]
        window = None if paper else fraction
        if window != self.training.reward_window_fraction:
            what = "the paper's 20 %" if paper else f"{fraction:g} of each side, recorded in the weights files"
            self.get_logger().info(f"reward window: {what} ({math.degrees(fov):.1f} deg of arc)")
            self.training.reward_window_fraction = window

    # -- learning ----------------------------------------------------------------------
    def _on_ready(self, stamp: int) -> None:
        """The step that produced frame `stamp` is stored. Learn what replay_ratio allows now, write due
        snapshots, then release the frame to the policy with the new weights and epsilon. After the
        budget's last step nothing is released: _service_tick stops the node."""
        for path in self.training.learn_due():
            self.get_logger().info(f"step {self.training.env_steps}: weights snapshot {path}")
        if self.training.failed or self.training.budget_done:
            return
        self._go_stamp = stamp
        self._send_go()

    def _send_go(self) -> None:
        if self._go_stamp is None or self.push_in_flight is not None or not self.push_client.service_is_ready():
            return  # _service_tick retries; a push in flight is answered before the next release goes
        updates = self.training.learner.updates
        blob = self.training.weights_blob() if updates != self._pushed_updates else None
        self._pushed_updates = updates
        # Larger than any number sent before, also by this run before a restart: the policy refuses replays.
        self.push_seq = max(self.push_seq + 1, time.time_ns())
        request = push_request(blob, self.training.epsilon(), self._go_stamp, key=self.push_key, seq=self.push_seq)
        fut = self.push_client.call_async(request)
        t0 = self._in_flight_t0 = time.perf_counter()
        fut.add_done_callback(lambda f, t0=t0, b=blob: self._push_done(f, t0, b is not None))
        self.push_in_flight, self._in_flight_stamp, self._go_stamp = fut, self._go_stamp, None

    # -- services: pushes and epsilon -----------------------------------------------------
    def _service_tick(self) -> None:
        if self.training.failed and self.exit_code == 0:
            self.get_logger().error(self.training.failed)
            self.exit_code = 3
            self._shutdown()
            return
        if self.training.budget_done and not self._closed:
            self.get_logger().info(f"step budget of {self.cfg.total_steps} reached")
            self._shutdown()
            return
        self._check_policy_waits()
        self._check_release()
        self._send_go()

    def _check_release(self) -> None:
        """A release policy_node has not answered within release_timeout_s is sent again (with the weights), so
        a lost request or a busy policy never stops the run for good."""
        fut = self.push_in_flight
        if fut is None or time.perf_counter() - self._in_flight_t0 < self.release_timeout_s:
            return
        self.push_client.remove_pending_request(fut)
        self.push_in_flight = None
        self.counts["release_retries"] += 1
        self.get_logger().warning(
            f"policy_node did not answer the release of the frame at {self._in_flight_stamp / 1e9:.1f} s sim time within "
            f"{self.release_timeout_s:g} s: sending it again ({self.counts['release_retries']} so far)"
        )
        if self._go_stamp is None or self._go_stamp < self._in_flight_stamp:
            self._go_stamp = self._in_flight_stamp
        self._pushed_updates = None  # the weights go again too

    def _push_done(self, fut, t0: float, weights: bool = True) -> None:
        self.push_in_flight = None
        res = fut.result()
        if res is not None and res.success:
            if weights:
                self.counts["pushes_ok"] += 1
                self.push_latency_ms.append(1e3 * (time.perf_counter() - t0))
        else:
            self.counts["pushes_rejected"] += 1
            if res is not None and self.exit_code == 0:
                # The policy refused the learner's weights: it would act on others for the rest of the run, so
                # no step would be in lockstep (each one held for its wait_for_trainer_timeout_s). Stop now;
                # close() writes the final checkpoint, so the same command resumes once the nodes agree.
                self.get_logger().error(
                    f"policy_node rejected the weights of a release: {res.message}. Stopping: in "
                    "lockstep the policy must act on this node's weights. Give policy_node and trainer_node the same "
                    "model, frame_stack, input size (policy_node input_width and input_height, this node input_size_px) "
                    "and action_* parameters (train does), then run again to resume from the final checkpoint"
                )
                self.exit_code = 3
                self._shutdown()
                return
            self.get_logger().error(f"policy rejected pushed weights: {res.message if res else 'no answer'}")
            self._pushed_updates = None  # the next release carries the weights again
        self._send_go()

    # -- reporting ----------------------------------------------------------------------
    def _status(self) -> dict:
        t = self.training
        lat = sorted(self.push_latency_ms[-100:])
        return {
            "env_steps": t.env_steps,
            "updates": t.learner.updates,
            "episodes": t.stats.episodes,
            "epsilon": f"{t.epsilon():.3f}",
            "loss": f"{t.last_loss:.4f}",
            "replay_transitions": len(t.replay),
            "checkpoint_failures": t.checkpoint_failures,
            "push_latency_p50_ms": f"{lat[len(lat) // 2]:.1f}" if lat else "nan",
            "total_steps": self.cfg.total_steps,
            **self.pairing.report(),
            **self.counts,
        }

    def _report(self) -> None:
        row = self.training.metrics_row()
        st = self._status()
        failed = self.training.failed
        self.pub_diag.publish(contract.diagnostics(self, "uav_trainer", "ERROR" if failed else "OK", failed or "training", st))
        pct = f" ({100.0 * row['env_steps'] / self.cfg.total_steps:.1f}%)" if self.cfg.total_steps else ""
        unpaired = st["frames_without_action"] + st["frames_without_outcome"] + st["outcomes_or_actions_without_frame"]
        self.get_logger().info(
            f"steps {row['env_steps']}{pct} updates {row['updates']} episodes {row['episodes']} "
            f"mean len {row['mean_episode_length']:.1f} mean ep reward {row['mean_episode_reward']:.1f} "
            f"eps {row['epsilon']:.3f} loss {row['loss']:.4f} | {row['env_steps_per_s']:.0f} steps/s "
            f"{row['updates_per_s']:.1f} updates/s (ratio {row['updates_per_s'] / max(row['env_steps_per_s'], 1e-9):.2f})"
            f" | unpaired {unpaired} breaks {st['chain_breaks']} "
            f"restarts {st['stamp_restarts']}"
        )

    def _shutdown(self) -> None:
        rclpy.try_shutdown(context=self.context)

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
        self.training.close()


def main(args=None) -> int:
    return run(TrainerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
