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

With `actors` (namespaces, e.g. [/actor0, /actor1]; `train --actors N` sets them) it learns from several
sim_node/policy_node pairs, each joined on its own: steps go to the actor's lane of one replay memory,
each frame is released to its own policy with its own epsilon (Ape-X's spread), and the updates are the
same per-step ones. The actors interleave in arrival order, so such a run is asynchronous and not
bit-reproducible. An actor not heard from within actor_timeout_s is reported (missing at start-up, lost
later) and training goes on with the others; one that comes (back) later is taken up. Step outcomes
from namespaces not in `actors` are ignored and counted.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import Counter
from pathlib import Path

import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node
from rclpy.validate_namespace import validate_namespace
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

UNWRITTEN_EXIT_CODE = 4  # the run ended, but weights files it names were not written (train says which)
UNKNOWN_SCAN_S = 2.0  # how often the graph is searched for step outcomes from namespaces not in `actors`


@dataclasses.dataclass(frozen=True)
class TrainerNodeSettings:
    """trainer_node's parameters: the training run's, the action table's and the node's own."""

    trainer: TrainerConfig = TrainerConfig()
    actions: ActionSettings = ActionSettings()
    run_dir: str = setting("runs/train", "Output directory: checkpoints, metrics, plots, policy weights")
    resume: bool = setting(True, "Resume from run_dir's latest checkpoint when there is one")
    step_duration_s: float = setting(0.5, "Sim step duration (s); must equal sim_node's", 0.01, 5.0)
    policy_node: str = setting("policy_node", "Name of the policy node to release frames and push weights to")
    actors: tuple[str, ...] = setting(
        (),
        "Namespaces of the actor pairs (sim_node and policy_node) to learn from, e.g. [/actor0, /actor1] (train "
        "--actors N sets them); empty: the one pair in this node's namespace, in lockstep (bit-identical to inprocess)",
    )
    actor_timeout_s: float = setting(
        30.0,
        "An actor not heard from for this long (s) is reported: missing at start-up, lost later; training goes on "
        "with the others and takes it up when it comes (back)",
        1.0,
        3600.0,
    )
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


class Actor:
    """One sim_node/policy_node pair the trainer learns from: its joins, its releases and whether it is alive."""

    def __init__(self, node: TrainerNode, index: int, namespace: str, policy: str, hw: tuple[int, int]):
        self.index, self.ns = index, namespace
        self.label = namespace or "the actor"
        self.policy = f"{namespace}'s policy_node" if namespace else "policy_node"  # in log lines
        topic = lambda name: f"{namespace.rstrip('/')}/{name}" if namespace else name  # noqa: E731 ("/": the root)
        self.outcome_topic = node.resolve_topic_name(topic(contract.OUTCOME_TOPIC))
        self.pairing = TransitionAssembler(
            node.training.sink(index), node.actions, node.step_ns, hw, on_ready=lambda stamp: node._on_ready(self, stamp)
        )
        self.node = node
        q = contract.DEEP_QOS
        node.create_subscription(Image, topic(contract.DEPTH_TOPIC), self.on_frame, q)
        node.create_subscription(Range, topic(contract.OUTCOME_TOPIC), self.on_outcome, q)
        node.create_subscription(TwistStamped, topic(contract.ACTION_TOPIC), lambda m: node._on_action(self, m), q)
        # The camera's field of view goes into every weights file (policy_node warns on a mismatch).
        node.create_subscription(CameraInfo, topic(contract.CAMERA_INFO_TOPIC), node._on_camera_info, 10)
        self.push_client = node.create_client(PushService, topic(f"{policy}/push_weights"))
        # whether policy_node waits for releases, asked once (None: not yet known)
        self.get_param_client = node.create_client(GetParameters, topic(f"{policy}/get_parameters"))
        self.policy_waits: bool | None = None
        self.wait_query = None
        self.push_in_flight = None
        self.in_flight_stamp, self.in_flight_t0 = None, 0.0
        self.go_stamp = None  # the newest frame to release, once the previous push is answered
        self.pushed_updates = None  # the update count of the weights this actor's policy has
        self.last_heard: float | None = None  # monotonic time of its sim's latest message
        self.unanswered_since: float | None = None  # monotonic time its policy was sent a release not answered since
        self.silent: str | None = None  # reported missing or lost: "sim" (said nothing) or "policy" (answered nothing)

    def on_frame(self, msg: Image) -> None:
        self.heard()
        self.pairing.add("frame", msg)

    def on_outcome(self, msg: Range) -> None:
        self.heard()
        self.node._on_outcome(self, msg)

    def heard(self) -> None:
        self.last_heard = time.monotonic()
        if self.silent == "sim":
            self.silent = None
            if self.unanswered_since is not None:  # its policy gets another actor_timeout_s to answer
                self.unanswered_since = self.last_heard
            self.node.get_logger().info(f"{self.label}: its sim_node is heard from, learning from it")


class TrainerNode(Node):
    def __init__(self, **node_options):  # e.g. context=: built in a test's own context
        super().__init__("trainer_node", **node_options)
        st = declare_settings(self, TrainerNodeSettings, RETIRED)
        try:
            self.actions = st.actions.table()
        except ValueError as e:
            raise ParameterError(f"parameters 'action_*': {e}") from None
        namespaces = self._check_actors(st.actors)
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
        # The camera (camera_info) and sim_node's reward window (read back from step_outcome's field_of_view,
        # recorded in the weights files when it is not the paper's), from whichever actor says them.
        self.camera_width_px = None
        self.outcome_fov_rad = None
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
        self.counts.update(actors_missing=0, actors_lost=0, unknown_actor_messages=0)
        self.unknown: dict[str, object] = {}  # step_outcome topics outside `actors`: the subscriptions counting them
        self.push_latency_ms: list[float] = []
        self.exit_code = 0
        self.create_timer(0.05, self._service_tick)
        self.create_timer(st.log_interval_s, self._report)
        self.create_timer(UNKNOWN_SCAN_S, self._scan_for_unknown_actors)
        self._closed = False
        if len(self.actors) == 1:
            how = "learning in lockstep with acting"
        else:
            how = (
                f"learning from {len(self.actors)} actors ({', '.join(namespaces)}) asynchronously: each waits for its "
                "own release, and they interleave in arrival order (not bit-reproducible)"
            )
        self.get_logger().info(
            f"training {self.cfg.model} ({parameter_count(self.training.learner.online)} parameters, seed {self.cfg.seed}) "
            f"on {self.training.learner.device} into {self.training.dir}; "
            f"budget {self.cfg.total_steps or 'unlimited'} env steps; replay {self.cfg.replay_capacity} frames; "
            f"reward: {reward_description(self.cfg)}; {how}; pushes signed with the key in "
            f"{key_file} (policy_node needs accept_pushes:=true push_key_file:={key_file} safety:=false)"
        )

    @staticmethod
    def _check_actors(names: tuple[str, ...]) -> list[str]:
        """The actor namespaces as given (one unnamed actor, this node's namespace, when none), or ParameterError."""
        for ns in names:
            try:
                validate_namespace(ns)
            except Exception as e:  # rclpy's InvalidNamespaceException says what is wrong and where
                raise ParameterError(f"parameter 'actors': {ns!r} is no absolute namespace ({e})") from None
        repeated = [ns for ns, n in Counter(names).items() if n > 1]
        if repeated:
            raise ParameterError(f"parameter 'actors': {repeated[0]} is named twice")
        return list(names) or [""]

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
        for actor in self.actors:
            actor.pairing.set_camera(contract.camera_info_intrinsics(msg), hfov)
        self._update_window()

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

    def _on_outcome(self, actor: Actor, msg: Range) -> None:
        actor.pairing.add("outcome", msg)
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
    def _on_ready(self, actor: Actor, stamp: int) -> None:
        """The step that produced `actor`'s frame `stamp` is stored. Learn what replay_ratio allows now, write due
        snapshots, then release the frame to the actor's policy with the new weights and its epsilon. After the
        budget's last step nothing is released: _service_tick stops the node."""
        for path in self.training.learn_due():
            self.get_logger().info(f"step {self.training.env_steps}: weights snapshot {path}")
        if self.training.failed or self.training.budget_done:
            return
        actor.go_stamp = stamp
        self._send_go(actor)

    def _send_go(self, actor: Actor) -> None:
        if actor.go_stamp is None or actor.push_in_flight is not None or not actor.push_client.service_is_ready():
            return  # _service_tick retries; a push in flight is answered before the next release goes
        updates = self.training.learner.updates
        blob = self.training.weights_blob() if updates != actor.pushed_updates else None
        actor.pushed_updates = updates
        # Larger than any number sent before, also by this run before a restart: the policy refuses replays.
        self.push_seq = max(self.push_seq + 1, time.time_ns())
        epsilon = self.training.epsilon(actor.index)
        request = push_request(blob, epsilon, actor.go_stamp, key=self.push_key, seq=self.push_seq)
        fut = actor.push_client.call_async(request)
        t0 = actor.in_flight_t0 = time.perf_counter()
        if actor.unanswered_since is None:
            actor.unanswered_since = time.monotonic()
        fut.add_done_callback(lambda f, t0=t0, b=blob: self._push_done(actor, f, t0, b is not None))
        actor.push_in_flight, actor.in_flight_stamp, actor.go_stamp = fut, actor.go_stamp, None

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
        for actor in self.actors:
            self._check_alive(actor)
            self._check_policy_waits(actor)
            self._check_release(actor)
            self._send_go(actor)

    def _check_alive(self, actor: Actor) -> None:
        """An actor whose simulator has said nothing, or whose policy has answered no release, for actor_timeout_s
        is reported once (missing at start-up, lost later), and taken up again when it is heard from or answers.
        The others go on; a silent simulator's release is not sent again until it is heard from."""
        if actor.silent:
            return
        now = time.monotonic()
        sim_quiet = now - (actor.last_heard if actor.last_heard is not None else self.started) >= self.actor_timeout_s
        unanswered = actor.unanswered_since is not None and now - actor.unanswered_since >= self.actor_timeout_s
        if not sim_quiet and not unanswered:
            return
        actor.silent = "sim" if sim_quiet else "policy"
        if actor.silent == "policy":
            self.counts["actors_lost"] += 1
            what = f"{actor.label}: its policy_node has answered no release for {self.actor_timeout_s:g} s, counted as lost"
        elif actor.last_heard is None:
            self.counts["actors_missing"] += 1
            what = (
                f"{actor.label}: nothing from its sim_node on {actor.outcome_topic} within {self.actor_timeout_s:g} s of "
                "start-up (is it running, on this ROS_DOMAIN_ID, and discoverable from here? docs/TRAINING.md, 'Many "
                "actors')"
            )
        else:
            self.counts["actors_lost"] += 1
            what = f"{actor.label}: its sim_node has said nothing for {self.actor_timeout_s:g} s, counted as lost"
        others = sum(a.silent is None for a in self.actors)
        goes_on = f"training goes on with {others} other actor(s)" if others else "no actor is heard from: training waits"
        self.get_logger().error(f"{what}; {goes_on}, and takes it up when it comes")

    def _check_release(self, actor: Actor) -> None:
        """A release policy_node has not answered within release_timeout_s is sent again (with the weights), so
        a lost request or a busy policy never stops the run for good."""
        fut = actor.push_in_flight
        if fut is None or actor.silent == "sim" or time.perf_counter() - actor.in_flight_t0 < self.release_timeout_s:
            return
        actor.push_client.remove_pending_request(fut)
        actor.push_in_flight = None
        self.counts["release_retries"] += 1
        self.get_logger().warning(
            f"{actor.policy} did not answer the release of the frame at {actor.in_flight_stamp / 1e9:.1f} s "
            f"sim time within {self.release_timeout_s:g} s: sending it again ({self.counts['release_retries']} so far)"
        )
        if actor.go_stamp is None or actor.go_stamp < actor.in_flight_stamp:
            actor.go_stamp = actor.in_flight_stamp
        actor.pushed_updates = None  # the weights go again too

    def _push_done(self, actor: Actor, fut, t0: float, weights: bool = True) -> None:
        actor.push_in_flight, actor.unanswered_since = None, None
        if actor.silent == "policy":
            actor.silent = None
            self.get_logger().info(f"{actor.label}: its policy_node answers again, learning from it")
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
                    f"{actor.policy} rejected the weights of a release: {res.message}. Stopping: in "
                    "lockstep the policy must act on this node's weights. Give policy_node and trainer_node the same "
                    "model, frame_stack, input size (policy_node input_width and input_height, this node input_size_px) "
                    "and action_* parameters (train does), then run again to resume from the final checkpoint"
                )
                self.exit_code = 3
                self._shutdown()
                return
            self.get_logger().error(f"policy rejected pushed weights: {res.message if res else 'no answer'}")
            actor.pushed_updates = None  # the next release carries the weights again
        self._send_go(actor)

    def _scan_for_unknown_actors(self) -> None:
        """Step outcomes published in a namespace not among the actors are counted, never learnt from."""
        known = {a.outcome_topic for a in self.actors}
        suffix = "/" + contract.OUTCOME_TOPIC
        for topic, _types in self.get_topic_names_and_types():
            if not topic.endswith(suffix) or topic in known or topic in self.unknown:
                continue
            ns = topic[: -len(suffix)] or "/"
            self.get_logger().warning(
                f"ignoring {topic}: namespace {ns} is not among the actors {[a.ns or '(this namespace)' for a in self.actors]} "
                "(its messages are counted on /diagnostics as unknown_actor_messages)"
            )
            self.unknown[topic] = self.create_subscription(Range, topic, self._on_unknown_outcome, contract.DEEP_QOS)

    def _on_unknown_outcome(self, _msg: Range) -> None:
        self.counts["unknown_actor_messages"] += 1

    # -- reporting ----------------------------------------------------------------------
    def _status(self) -> dict:
        t = self.training
        lat = sorted(self.push_latency_ms[-100:])
        pairing = Counter()
        for actor in self.actors:
            pairing.update(actor.pairing.report())
        per_actor = {}
        if len(self.actors) > 1:
            for a in self.actors:
                per_actor[f"steps {a.ns}"] = t.actor_steps[a.index]
                per_actor[f"epsilon {a.ns}"] = f"{t.epsilon(a.index):.3f}"
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
            "actors": len(self.actors),
            "actors_silent": sum(a.silent is not None for a in self.actors),
            **per_actor,
            **pairing,
            **self.counts,
        }

    def _report(self) -> None:
        row = self.training.metrics_row()
        st = self._status()
        failed = self.training.failed
        self.pub_diag.publish(contract.diagnostics(self, "uav_trainer", "ERROR" if failed else "OK", failed or "training", st))
        pct = f" ({100.0 * row['env_steps'] / self.cfg.total_steps:.1f}%)" if self.cfg.total_steps else ""
        unpaired = st["frames_without_action"] + st["frames_without_outcome"] + st["outcomes_or_actions_without_frame"]
        actors = ""
        if len(self.actors) > 1:
            actors = " | actors " + " ".join(f"{a.ns} {self.training.actor_steps[a.index]}" for a in self.actors)
        self.get_logger().info(
            f"steps {row['env_steps']}{pct} updates {row['updates']} episodes {row['episodes']} "
            f"mean len {row['mean_episode_length']:.1f} mean ep reward {row['mean_episode_reward']:.1f} "
            f"eps {row['epsilon']:.3f} loss {row['loss']:.4f} | {row['env_steps_per_s']:.0f} steps/s "
            f"{row['updates_per_s']:.1f} updates/s (ratio {row['updates_per_s'] / max(row['env_steps_per_s'], 1e-9):.2f})"
            f" | unpaired {unpaired} breaks {st['chain_breaks']} "
            f"restarts {st['stamp_restarts']}{actors}"
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
        report = self.training.unwritten_report()
        if report:
            self.get_logger().error(report)
            self.exit_code = self.exit_code or UNWRITTEN_EXIT_CODE
        self.training.close()


def main(args=None) -> int:
    return run(TrainerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
