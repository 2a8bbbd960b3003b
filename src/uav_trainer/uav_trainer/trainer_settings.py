"""trainer_node's parameters, declared once (uav_common.settings): the ROS declarations, params/trainer.yaml and
docs/PARAMETERS.md come from here; and the checks and start-up line that go with them."""

from __future__ import annotations

import dataclasses
from collections import Counter

from rclpy.validate_namespace import validate_namespace

from uav_common.actions import ActionSettings
from uav_common.ros_params import ParameterError
from uav_common.settings import setting

from .training_config import TrainerConfig, reward_description


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

    def actor_namespaces(self) -> list[str]:
        """The actor namespaces as given (one unnamed actor, this node's namespace, when none), or ParameterError."""
        for ns in self.actors:
            try:
                validate_namespace(ns)
            except Exception as e:  # rclpy's InvalidNamespaceException says what is wrong and where
                raise ParameterError(f"parameter 'actors': {ns!r} is no absolute namespace ({e})") from None
        repeated = [ns for ns, n in Counter(self.actors).items() if n > 1]
        if repeated:
            raise ParameterError(f"parameter 'actors': {repeated[0]} is named twice")
        return list(self.actors) or [""]


def describe(cfg: TrainerConfig, training, parameters: int, namespaces: list[str], key_file) -> str:
    """trainer_node's start-up line: what it trains, where, on what reward, from which actors, signed how."""
    if len(namespaces) == 1:
        how = "learning in lockstep with acting"
    else:
        how = (
            f"learning from {len(namespaces)} actors ({', '.join(namespaces)}) asynchronously: each waits for its "
            "own release, and they interleave in arrival order (not bit-reproducible)"
        )
    return (
        f"training {cfg.model} ({parameters} parameters, seed {cfg.seed}) on {training.learner.device} into "
        f"{training.dir}; budget {cfg.total_steps or 'unlimited'} env steps; replay {cfg.replay_capacity} frames; "
        f"reward: {reward_description(cfg)}; {how}; pushes signed with the key in {key_file} (policy_node needs "
        f"accept_pushes:=true push_key_file:={key_file} safety:=false shield:=never)"
    )
