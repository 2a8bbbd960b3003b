"""trainer_node: replay memory, learning, weight pushes and checkpoints over ROS 2.

Joins depth/image_raw, step_outcome and the policy's action (TwistStamped) by exact stamp.
Consecutive steps (stamps one step_duration_s apart) make transitions (s, a, r, s', done) with
the reward from uav_sim.reward; anything that does not pair is counted and reported on
/diagnostics and in the log, never guessed.

Two ways to learn. Concurrent (this node's default): a learner thread updates the network beside acting;
weights go to the policy over policy_node/push_weights every push_interval_updates, epsilon
through policy_node's parameters. Lockstep (`lockstep_learning`, with policy_node's
wait_for_trainer; train sets both): after each step is stored, the updates replay_ratio allows
run at once, then one push carries the new weights, the exact epsilon and the frame's release,
so the policy acts on each frame exactly as the in-process loop does (for a seed, the same
episodes and weights as `inprocess` on the same machine).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time

import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import TwistStamped
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, Range

from uav_common import contract
from uav_common.node_runner import run
from uav_common.ros_params import ParameterError, declare
from uav_policy.actions import PAPER_ACTIONS, make_actions, turning_indices
from uav_policy.networks import MAX_FRAMES, SAM_READOUTS, SIZE_LIMITS, NetConfig, parameter_count
from uav_policy.push import push_request
from uav_policy.weights import HFOV_RANGE_DEG
from uav_sim.reward import center_window_slices, window_fraction_for_fov

from .learner import MAX_SHIFT_PX, LearnerConfig
from .pairing import TransitionAssembler
from .training import (
    MAX_N_STEP,
    SAM_SIZES,
    TrainerConfig,
    Training,
    replay_description,
    reward_description,
    snapshot_steps,
)

LAG_MIN_UPDATES, LAG_FRACTION = 50, 0.1  # warn when the learner is this far behind replay_ratio


def lag_warning(behind: int, due: int, ratio: float) -> str | None:
    """A warning when the learner is well behind replay_ratio x env steps, or None. Acting does not wait
    for learning over ROS, so on a busy machine a run gets fewer updates than asked and learns less."""
    if behind < max(LAG_MIN_UPDATES, LAG_FRACTION * due):
        return None
    return (
        f"the learner is {behind} updates behind replay_ratio {ratio:g} ({due - behind} of {due} done): acting does "
        "not wait for learning, so this run learns from fewer updates than asked; lower the step rate (train "
        "--max-rate-hz, sim_node max_rate_hz) or give the trainer more CPU"
    )


class TrainerNode(Node):
    def __init__(self):
        super().__init__("trainer_node")
        d = lambda *a, **k: declare(self, *a, **k)  # noqa: E731
        D = TrainerConfig()
        L = LearnerConfig()
        device = d(
            "device", "auto", "Learner device: auto (cuda when present, else cpu), cpu or cuda", choices=("auto", "cpu", "cuda")
        )
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        elif device == "cuda" and not torch.cuda.is_available():
            raise ParameterError("parameter 'device'='cuda' but no CUDA device is available")
        learner = LearnerConfig(
            gamma=d("gamma", L.gamma, "Discount factor", 0.0, 1.0),
            learning_rate=d("learning_rate", L.learning_rate, "Adam learning rate", 1e-7, 1.0),
            batch_size=d("batch_size", L.batch_size, "Transitions per update", 1, 4096),
            grad_clip_norm=d("grad_clip_norm", L.grad_clip_norm, "Max global gradient norm", 0.01, 1e6),
            target_update_interval=d(
                "target_update_interval", L.target_update_interval, "Updates between target-network syncs", 1, 10**7
            ),
            target_tau=d("target_tau", L.target_tau, "1.0: hard copy at each sync; <1: Polyak factor", 0.0001, 1.0),
            huber_delta=d("huber_delta", L.huber_delta, "Huber loss threshold", 0.01, 100.0),
            lr_anneal_updates=d(
                "lr_anneal_updates",
                L.lr_anneal_updates,
                "> 0: lower the learning rate linearly to lr_end_fraction x over this many updates; 0 = constant",
                0,
                10**9,
            ),
            lr_end_fraction=d("lr_end_fraction", L.lr_end_fraction, "Final learning rate / initial when annealing", 0.001, 1.0),
            ema_decay=d(
                "ema_decay",
                L.ema_decay,
                "> 0: also keep a moving average of the weights, written as policy_<model>_ema.safetensors (0 = off)",
                0.0,
                0.99999,
            ),
            augment_shift_px=d(
                "augment_shift_px",
                L.augment_shift_px,
                "> 0: shift each sampled state and next state by up to this many pixels before an update "
                "(random-shift augmentation, an extension; 0 = off, as the paper)",
                0,
                MAX_SHIFT_PX,
            ),
        )
        self.cfg = TrainerConfig(
            model=d("model", D.model, "Q-network: sam or cnn (must match policy_node's model)", choices=("sam", "cnn")),
            seed=d("seed", D.seed, "Seed for initialisation and replay sampling", 0, 2**31 - 1),
            device=device,
            replay_capacity=d("replay_capacity", D.replay_capacity, "Frames kept in replay (each stored once)", 100, 10**7),
            learning_starts=d("learning_starts", D.learning_starts, "Transitions before the first update", 1, 10**8),
            replay_ratio=d("replay_ratio", D.replay_ratio, "Max updates per environment step", 0.001, 64.0),
            push_interval_updates=d(
                "push_interval_updates", D.push_interval_updates, "Push weights to the policy every N updates", 1, 10**7
            ),
            checkpoint_interval_updates=d(
                "checkpoint_interval_updates", D.checkpoint_interval_updates, "Write a checkpoint every N updates", 1, 10**8
            ),
            epsilon_start=d("epsilon_start", D.epsilon_start, "Initial exploration rate", 0.0, 1.0),
            epsilon_end=d("epsilon_end", D.epsilon_end, "Final exploration rate (the paper keeps 0.05)", 0.0, 1.0),
            epsilon_decay_steps=d("epsilon_decay_steps", D.epsilon_decay_steps, "Env steps of linear decay", 0, 10**9),
            total_steps=d("total_steps", D.total_steps, "Env steps budget; 0 = until Ctrl-C", 0, 10**10),
            save_replay=d(
                "save_replay",
                D.save_replay,
                "A stop before the budget also writes the replay memory (8 KiB per frame) with the final checkpoint, "
                "and a resume restores it",
            ),
            clearance_m=d(
                "clearance_m",
                D.clearance_m,
                "Side clearance (m): > 0 adds a penalty for returns nearer than this in the central band of rows "
                "(an extension, not the paper's reward); 0 = the paper's reward",
                0.0,
                10.0,
            ),
            clearance_weight=d(
                "clearance_weight", D.clearance_weight, "Clearance penalty at contact (linear to 0 at clearance_m)", 0.0, 100.0
            ),
            turn_penalty=d(
                "turn_penalty",
                D.turn_penalty,
                "Subtracted from the reward of every turning step (an extension; 0 = the paper's reward)",
                0.0,
                100.0,
            ),
            n_step=d(
                "n_step",
                D.n_step,
                "> 1: learn from n-step returns (an extension; 1 = one-step Q-learning, as the paper)",
                1,
                MAX_N_STEP,
            ),
            priority_alpha=d(
                "priority_alpha",
                D.priority_alpha,
                "> 0: prioritized replay, sampling ~ |TD error|^alpha (an extension; 0 = uniform, as the paper)",
                0.0,
                1.0,
            ),
            priority_beta=d("priority_beta", D.priority_beta, "Prioritized replay: initial importance-weight exponent", 0.0, 1.0),
            priority_beta_steps=d(
                "priority_beta_steps",
                D.priority_beta_steps,
                "Prioritized replay: env steps over which the importance-weight exponent rises to 1",
                0,
                10**10,
            ),
            sam_readout=d(
                "sam_readout",
                D.sam_readout,
                "SAM readout: max (the paper's design) or flatten (an extension); must match policy_node's sam_readout",
                choices=SAM_READOUTS,
            ),
            input_size_px=d(
                "input_size_px", D.input_size_px, "Square network input (px); policy_node's input_height/input_width", 8, 512
            ),
            frames=d("frame_stack", D.frames, "Depth frames in the state; policy_node's frame_stack", 1, MAX_FRAMES),
            conv_channels=tuple(
                d(
                    "conv_channels",
                    list(D.conv_channels),
                    "Conv trunk output channels, one stride-2 layer each (both models; [16, 32] gives SAM 16 x 16 nodes "
                    "from 64 px); policy_node takes the layer sizes from the pushed weights",
                )
            ),
            d_model=d("d_model", D.d_model, "SAM: node feature size, split over the heads", 1, SIZE_LIMITS["d_model"]),
            heads=d("heads", D.heads, "SAM: attention heads", 1, SIZE_LIMITS["heads"]),
            relational_blocks=d(
                "relational_blocks", D.relational_blocks, "SAM: relational blocks", 1, SIZE_LIMITS["relational_blocks"]
            ),
            mlp_hidden=d("mlp_hidden", D.mlp_hidden, "SAM: width of each block's MLP", 1, SIZE_LIMITS["mlp_hidden"]),
            learner=learner,
        )
        try:
            px = self.cfg.input_size_px
            NetConfig(conv_channels=self.cfg.conv_channels, height=px, width=px).validate()
        except ValueError as e:
            raise ParameterError(f"parameter 'conv_channels'={list(self.cfg.conv_channels)}: {e}") from None
        if self.cfg.d_model % self.cfg.heads:
            raise ParameterError(
                f"parameters 'd_model' ({self.cfg.d_model}) and 'heads' ({self.cfg.heads}): d_model must be divisible by heads"
            )
        changed = [k for k in SAM_SIZES if getattr(self.cfg, k) != getattr(D, k)]
        if self.cfg.model == "cnn" and changed:
            raise ParameterError(f"parameters {changed} size SAM's relational module; model 'cnn' has none")
        snapshot_every = d(
            "save_weights_every_steps",
            0,
            "> 0: also write the online network as policy_<model>_step<N>.safetensors every this many env steps, "
            "from save_weights_from_step to below total_steps (snapshots, e.g. a run's last ten flown as one "
            "policy); 0 = off",
            0,
            10**9,
        )
        snapshot_from = d("save_weights_from_step", 0, "The first snapshot's env step (0 = save_weights_every_steps)", 0, 10**10)
        try:
            snapshots = snapshot_steps(snapshot_every, snapshot_from, self.cfg.total_steps)
        except ValueError as e:
            raise ParameterError(str(e)) from None
        run_dir = d("run_dir", "runs/train", "Output directory: checkpoints, metrics, plots, policy weights")
        resume = d("resume", True, "Resume from run_dir's latest checkpoint when there is one")
        self.step_ns = int(round(1e9 * d("step_duration_s", 0.5, "Sim step duration (s); must equal sim_node's", 0.01, 5.0)))
        names = d("action_names", [a.name for a in PAPER_ACTIONS], "Action names (must match policy_node)")
        lin = d("action_linear_x_mps", [a.linear_x_mps for a in PAPER_ACTIONS], "Forward speed of each action")
        yaw = d("action_yaw_deg", [a.yaw_deg_per_step for a in PAPER_ACTIONS], "Yaw per step of each action")
        policy = d("policy_node", "policy_node", "Name of the policy node to push weights and epsilon to")
        self.log_interval_s = d("log_interval_s", 10.0, "Seconds between progress lines and metrics rows", 0.1, 3600.0)
        threads = d("torch_threads", 1, "Torch intra-op threads for the learner (2 cores are shared)", 1, 256)
        self.lockstep = d(
            "lockstep_learning",
            False,
            "Learn in lockstep with acting: after each step, its updates, then release the next frame to the policy "
            "with the new weights and epsilon (policy_node needs wait_for_trainer:=true); false: a learner thread "
            "beside acting, pushing every push_interval_updates",
        )
        try:
            self.actions = make_actions(names, lin, yaw)
        except ValueError as e:
            raise ParameterError(f"parameters 'action_*': {e}") from None
        if len(self.actions) != 4:
            raise ParameterError(f"parameters 'action_*': the networks have 4 outputs, got {len(self.actions)} actions")
        self.cfg = dataclasses.replace(self.cfg, turning_actions=turning_indices(self.actions))
        torch.set_num_threads(threads)
        self.training = Training(self.cfg, run_dir, log=self.get_logger().info, resume=resume)
        self.training.plan_snapshots(snapshots)

        q = contract.DEEP_QOS
        hw = (self.training.net_cfg.height, self.training.net_cfg.width)
        on_ready = self._on_ready if self.lockstep else None
        self.pairing = TransitionAssembler(self.training, self.actions, self.step_ns, hw, on_ready=on_ready)
        self.create_subscription(Image, contract.DEPTH_TOPIC, lambda m: self.pairing.add("frame", m), q)
        self.create_subscription(Range, contract.OUTCOME_TOPIC, self._on_outcome, q)
        self.create_subscription(TwistStamped, contract.ACTION_TOPIC, self._on_action, q)
        # The camera's field of view goes into every weights file (policy_node warns on a mismatch), and so
        # does sim_node's reward window when it is not the paper's, read back from step_outcome's field_of_view.
        self.camera_width_px = None
        self.outcome_fov_rad = None
        self.create_subscription(CameraInfo, contract.CAMERA_INFO_TOPIC, self._on_camera_info, 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, 10)
        self.push_client = self.create_client(SetParameters, f"{policy}/push_weights")
        self.param_client = self.create_client(SetParameters, f"{policy}/set_parameters")
        # lockstep: whether policy_node waits for releases, asked once (None: not yet known)
        self.get_param_client = self.create_client(GetParameters, f"{policy}/get_parameters")
        self.policy_waits: bool | None = None
        self._wait_query = None
        # unreleased_answers (lockstep): answers to frames this node had not released, i.e. not in lockstep
        self.counts = {"pushes_ok": 0, "pushes_rejected": 0, "unreleased_answers": 0}
        self.push_in_flight = None
        self.push_latency_ms: list[float] = []
        self.eps_in_flight = None
        self.eps_sent = None
        self.exit_code = 0
        self._stop = threading.Event()
        self._go_stamp = None  # lockstep: the newest frame to release, once the previous push is answered
        self._pushed_updates = None  # lockstep: the update count of the weights the policy has
        self._learner_thread = threading.Thread(target=self._learn_loop, name="learner", daemon=True)
        if not self.lockstep:
            self._learner_thread.start()
        self.create_timer(0.05, self._service_tick)
        self.create_timer(self.log_interval_s, self._report)
        self._closed = False
        self.get_logger().info(
            f"training {self.cfg.model} ({parameter_count(self.training.learner.online)} parameters, seed {self.cfg.seed}) "
            f"on {device} into {self.training.dir}; "
            f"budget {self.cfg.total_steps or 'unlimited'} env steps; replay {self.cfg.replay_capacity} frames; "
            f"reward: {reward_description(self.cfg)}; {replay_description(self.cfg)}; "
            + ("learning in lockstep with acting" if self.lockstep else "learning beside acting")
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
        self._update_window()

    def _check_policy_waits(self) -> None:
        """Lockstep: ask policy_node once whether it waits for releases; say so loudly when it does not."""
        if self.policy_waits is not None or self._wait_query is not None or not self.get_param_client.service_is_ready():
            return
        self._wait_query = self.get_param_client.call_async(GetParameters.Request(names=["wait_for_trainer"]))
        self._wait_query.add_done_callback(self._policy_waits_known)

    def _policy_waits_known(self, fut) -> None:
        values = fut.result().values if fut.result() else []
        self.policy_waits = bool(values) and values[0].type == ParameterType.PARAMETER_BOOL and values[0].bool_value
        if not self.policy_waits:
            self.get_logger().error(
                "lockstep_learning: policy_node does not wait for releases (its wait_for_trainer is not true), so it acts "
                "before learning and the run is not in lockstep; give policy_node wait_for_trainer:=true (train does), "
                "or this node lockstep_learning:=false"
            )

    def _on_action(self, msg: TwistStamped) -> None:
        if self.lockstep and contract.stamp_ns(msg.header.stamp) > self.pairing.released:
            self.counts["unreleased_answers"] += 1
            self.get_logger().warning(
                f"policy_node answered a frame this node had not released ({self.counts['unreleased_answers']} so far): learning "
                "is not in lockstep; give policy_node wait_for_trainer:=true (train does), or this node "
                "lockstep_learning:=false",
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

    # -- learning -----------------------------------------------------------------------
    def _learn_loop(self) -> None:
        while not self._stop.is_set():
            if self.training.failed or self.training.budget_done:
                return
            self._save_snapshots()
            if not self.training.learn_once():
                time.sleep(0.002)

    def _on_ready(self, stamp: int) -> None:
        """Lockstep: the step that produced frame `stamp` is stored. Learn what replay_ratio allows now,
        write due snapshots, then release the frame to the policy with the new weights and epsilon. After
        the budget's last step nothing is released: _service_tick stops the node."""
        while self.training.learn_once():
            pass
        self._save_snapshots()
        if self.training.failed or self.training.budget_done:
            return
        self._go_stamp = stamp
        self._send_go()

    def _send_go(self) -> None:
        if self._go_stamp is None or self.push_in_flight is not None or not self.push_client.service_is_ready():
            return  # _service_tick retries; a push in flight is answered before the next release goes
        self.training.take_push()  # the release below carries the newest weights whenever they changed
        updates = self.training.learner.updates
        blob = self.training.weights_blob() if updates != self._pushed_updates else None
        self._pushed_updates = updates
        fut = self.push_client.call_async(push_request(blob, self.training.epsilon(), self._go_stamp, as_base64=True))
        self._go_stamp = None
        t0 = time.perf_counter()
        fut.add_done_callback(lambda f, t0=t0, b=blob: self._push_done(f, t0, b is not None))
        self.push_in_flight = fut

    def _save_snapshots(self) -> None:
        for path in self.training.save_due_snapshots():
            self.get_logger().info(f"step {self.training.env_steps}: weights snapshot {path}")

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
        if self.lockstep:
            self._check_policy_waits()
            self._send_go()
            return
        if self.push_in_flight is None and self.push_client.service_is_ready():
            blob = self.training.take_push()
            if blob is not None:
                t0 = time.perf_counter()
                fut = self.push_client.call_async(push_request(blob))
                fut.add_done_callback(lambda f, t0=t0: self._push_done(f, t0))
                self.push_in_flight = fut
        eps = round(self.training.epsilon(), 3)
        if self.eps_in_flight is None and eps != self.eps_sent and self.param_client.service_is_ready():
            p = Parameter(name="epsilon", value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=eps))
            fut = self.param_client.call_async(SetParameters.Request(parameters=[p]))
            fut.add_done_callback(lambda f, e=eps: self._eps_done(f, e))
            self.eps_in_flight = fut

    def _push_done(self, fut, t0: float, weights: bool = True) -> None:
        self.push_in_flight = None
        res = fut.result().results[0] if fut.result() else None
        if res is not None and res.successful:
            if weights:
                self.counts["pushes_ok"] += 1
                self.push_latency_ms.append(1e3 * (time.perf_counter() - t0))
        else:
            self.counts["pushes_rejected"] += 1
            if self.lockstep and res is not None and self.exit_code == 0:
                # The policy refused the learner's weights: it would act on others for the rest of the run, so
                # no step would be in lockstep (each one held for its wait_for_trainer_timeout_s). Stop now;
                # close() writes the final checkpoint, so the same command resumes once the nodes agree.
                self.get_logger().error(
                    f"lockstep_learning: policy_node rejected the weights of a release: {res.reason}. Stopping: in "
                    "lockstep the policy must act on this node's weights. Give policy_node and trainer_node the same "
                    "model, frame_stack, input size (policy_node input_width and input_height, this node input_size_px) "
                    "and action_* parameters (train does), then run again to resume from the final checkpoint"
                )
                self.exit_code = 3
                self._shutdown()
                return
            self.get_logger().error(f"policy rejected pushed weights: {res.reason if res else 'no answer'}")
            self._pushed_updates = None  # lockstep: the next release carries the weights again
        if self.lockstep:
            self._send_go()

    def _eps_done(self, fut, eps: float) -> None:
        self.eps_in_flight = None
        res = fut.result()
        if res is not None and res.results and res.results[0].successful:
            self.eps_sent = eps

    # -- reporting ----------------------------------------------------------------------
    def _status(self, updates_behind: int) -> dict:
        t = self.training
        lat = sorted(self.push_latency_ms[-100:])
        return {
            "env_steps": t.env_steps,
            "updates": t.learner.updates,
            "episodes": t.stats.episodes,
            "epsilon": f"{t.epsilon():.3f}",
            "loss": f"{t.last_loss:.4f}",
            "replay_transitions": len(t.replay),
            "updates_behind": updates_behind,
            "push_latency_p50_ms": f"{lat[len(lat) // 2]:.1f}" if lat else "nan",
            "total_steps": self.cfg.total_steps,
            **self.pairing.report(),
            **self.counts,
        }

    def _report(self) -> None:
        row = self.training.metrics_row()
        behind, due = self.training.learning_lag()
        st = self._status(behind)
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        level = DiagnosticStatus.ERROR if self.training.failed else DiagnosticStatus.OK
        text = self.training.failed or "training"
        status = DiagnosticStatus(level=level, name="uav_trainer", message=text, hardware_id=self.get_fully_qualified_name())
        status.values = [KeyValue(key=k, value=str(v)) for k, v in st.items()]
        msg.status = [status]
        self.pub_diag.publish(msg)
        pct = f" ({100.0 * row['env_steps'] / self.cfg.total_steps:.1f}%)" if self.cfg.total_steps else ""
        unpaired = st["frames_without_action"] + st["frames_without_outcome"] + st["outcomes_or_actions_without_frame"]
        self.get_logger().info(
            f"steps {row['env_steps']}{pct} updates {row['updates']} episodes {row['episodes']} "
            f"mean len {row['mean_episode_length']:.1f} mean ep reward {row['mean_episode_reward']:.1f} "
            f"eps {row['epsilon']:.3f} loss {row['loss']:.4f} | {row['env_steps_per_s']:.0f} steps/s "
            f"{row['updates_per_s']:.1f} updates/s (ratio {row['updates_per_s'] / max(row['env_steps_per_s'], 1e-9):.2f})"
            f" | unpaired {unpaired} breaks {st['chain_breaks']} "
            f"out-of-order {st['out_of_order']}"
        )
        warning = lag_warning(behind, due, self.cfg.replay_ratio)
        if warning:
            self.get_logger().warning(warning, throttle_duration_sec=60.0)

    def _shutdown(self) -> None:
        rclpy.try_shutdown(context=self.context)

    def close(self) -> None:
        """Stop learning and write the final checkpoint and weights (also on Ctrl-C)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._learner_thread.is_alive():
            self._learner_thread.join(timeout=30)
        self._save_snapshots()  # steps the learner thread did not see before the budget stopped it
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
