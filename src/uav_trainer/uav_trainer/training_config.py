"""The training run's settings (trainer_node's parameters and the in-process flags, declared once), its snapshot
schedule and file names, and the reward's description (no ROS)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from uav_common.settings import setting
from uav_policy.net_config import MAX_FRAMES, SAM_READOUTS, SIZE_LIMITS, NetConfig

from .teacher import TeacherConfig


@dataclasses.dataclass(frozen=True)
class LearnerConfig:
    gamma: float = setting(0.99, "Discount factor", 0.0, 1.0)
    learning_rate: float = setting(2.5e-4, "Adam learning rate", 1e-7, 1.0)
    batch_size: int = setting(32, "Transitions per update", 1, 4096)
    grad_clip_norm: float = setting(10.0, "Max global gradient norm", 0.01, 1e6)
    target_update_interval: int = setting(250, "Updates between target-network syncs", 1, 10**7)
    target_tau: float = setting(1.0, "1.0: hard copy at each sync; < 1: Polyak averaging factor", 0.0001, 1.0)
    huber_delta: float = setting(1.0, "Huber loss threshold", 0.01, 100.0)
    seed: int = 0  # TrainerConfig's seed (not a setting of its own)


def linear_epsilon(step: int, start: float, end: float, decay_steps: int) -> float:
    """Linear decay from start to end over decay_steps environment steps, then constant."""
    if decay_steps <= 0 or step >= decay_steps:
        return end
    frac = min(max(step, 0) / decay_steps, 1.0)
    return start + frac * (end - start)


DEVICES = ("auto", "cpu", "cuda")


@dataclasses.dataclass(frozen=True)
class TrainerConfig:
    """Everything a training run learns with (trainer_node's parameters, the in-process trainer's flags)."""

    model: str = setting("sam", "Q-network: sam or cnn (must match policy_node's model)", choices=("sam", "cnn"))
    seed: int = setting(0, "Seed for initialisation, replay sampling and exploration", 0, 2**31 - 1)
    device: str = setting("auto", "Learner device: auto (cuda when present, else cpu), cpu or cuda", choices=DEVICES)
    total_steps: int = setting(0, "Environment steps budget; 0 = until stopped", 0, 10**10)
    replay_capacity: int = setting(50000, "Frames kept in the replay memory (each stored once; 64x64: 8 KiB)", 100, 10**7)
    learning_starts: int = setting(
        0, "Transitions collected before the first update; 0 = a thirtieth of total_steps (1000 without a budget)", 0, 10**8
    )
    replay_ratio: float = setting(
        0.25, "Updates per environment step (0.25: one per four steps, DQN's train_freq 4)", 0.001, 64.0
    )
    checkpoint_interval_updates: int = setting(1000, "Write a checkpoint every N updates", 1, 10**8)
    checkpoint_interval_s: float = setting(
        120.0, "Also write one when this long (s) has passed since the last (from the first update on)", 1.0, 10**6
    )
    epsilon_start: float = setting(1.0, "Initial exploration rate", 0.0, 1.0)
    epsilon_end: float = setting(0.05, "Final exploration rate (the paper keeps 0.05)", 0.0, 1.0)
    epsilon_decay_steps: int = setting(
        0,
        "Environment steps of the linear decay from epsilon_start to epsilon_end; 0 = a third of total_steps (10000 "
        "without a budget)",
        0,
        10**9,
    )
    save_replay: bool = setting(
        True,
        "Checkpoints journal the replay memory (each the frames since the one before), so a resume after a stop "
        "or a crash learns on at once; the journal is removed once the step budget is spent",
    )
    turn_penalty: float = setting(
        0.0,
        "Subtracted from the reward of every turning step (not in the paper's reward: under it a policy can circle on "
        "the spot, crash rarely and cover nothing); 0 = the paper's reward",
        0.0,
        100.0,
    )
    snapshots: int = setting(
        0,
        "Weight snapshots policy_<model>_step<N>.safetensors, one every thirtieth of total_steps, the last one a "
        "thirtieth before the end (9: a run's last ten files, flown as one policy with the final weights); 0 = none",
        0,
        29,
    )
    sam_readout: str = setting(
        "max",
        "SAM readout (uav_policy/networks.py): max pools the nodes (the paper); flatten keeps their places; attend, "
        "query (the shipped recipe) and topk form the Q-values from the attention shown; policy_node takes "
        "it from the weights",
        choices=SAM_READOUTS,
    )
    input_size_px: int = setting(64, "Square network input and camera image (px); policy_node's input_height/width", 8, 512)
    frames: int = setting(
        NetConfig.frames, "Depth frames in the state (the paper's 5); policy_node's", 1, MAX_FRAMES, name="frame_stack"
    )
    local_map: bool = setting(
        False,
        "The network also sees the local map: the measured depth of the last frames placed by odometry, weather "
        "filtered (uav_common.local_map), as a last input channel beside the depth frames; it then needs odom",
    )
    conv_channels: tuple[int, ...] = setting(
        NetConfig.conv_channels,
        "Conv trunk output channels, one stride-2 layer each (both models; [16, 32] gives SAM 16 x 16 nodes from 64 px)",
    )
    d_model: int = setting(NetConfig.d_model, "SAM: node feature size, split over the heads", 1, SIZE_LIMITS["d_model"])
    heads: int = setting(NetConfig.heads, "SAM: attention heads", 1, SIZE_LIMITS["heads"])
    relational_blocks: int = setting(NetConfig.relational_blocks, "SAM: relational blocks", 1, SIZE_LIMITS["relational_blocks"])
    mlp_hidden: int = setting(NetConfig.mlp_hidden, "SAM: width of each relational block's MLP", 1, SIZE_LIMITS["mlp_hidden"])
    learner: LearnerConfig = LearnerConfig()
    teaching: TeacherConfig = TeacherConfig()
    turning_actions: tuple[int, ...] = (1, 2)  # the action indices that yaw (from the action table; not a setting)

    @property
    def first_update_after(self) -> int:
        """Transitions before the first update: learning_starts, or a thirtieth of the budget."""
        return self.learning_starts or max(1, (self.total_steps or NOMINAL_BUDGET) // 30)

    @property
    def teacher(self) -> str:
        """The teacher's planner (none: pure RL); its settings are `teaching`'s (uav_trainer.teacher)."""
        return self.teaching.teacher

    @property
    def pulls_attention(self) -> bool:
        """attention_weight acts: SAM's attention is pulled onto the teacher's reason (the CNN has none)."""
        return self.teaching.pulls_attention(self.model)

    def teacher_act_probability(self, step: int) -> float:
        """The chance that the teacher flies step `step`: teacher_act_start falling to 0 over the budget."""
        if not self.teaching.teaches:
            return 0.0
        return linear_epsilon(step, self.teaching.teacher_act_start, 0.0, self.total_steps or NOMINAL_BUDGET)

    @property
    def decay_steps(self) -> int:
        """Environment steps of the epsilon decay: epsilon_decay_steps, or a third of the budget."""
        return self.epsilon_decay_steps or max(1, (self.total_steps or NOMINAL_BUDGET) // 3)

    def budget_warnings(self) -> list[str]:
        """What a budget too short for explicitly given schedules would silently do."""
        out = []
        if self.total_steps and self.epsilon_decay_steps > self.total_steps:
            end = linear_epsilon(self.total_steps, self.epsilon_start, self.epsilon_end, self.epsilon_decay_steps)
            out.append(
                f"epsilon_decay_steps={self.epsilon_decay_steps} is longer than total_steps={self.total_steps}: epsilon "
                f"ends at {end:.3f}, not {self.epsilon_end:g} (0, the default, decays over a third of the budget)"
            )
        if self.total_steps and self.learning_starts >= self.total_steps:
            out.append(
                f"learning_starts={self.learning_starts} is not below total_steps={self.total_steps}: the run makes no "
                "update (0, the default, starts after a thirtieth of the budget)"
            )
        return out

    def validate(self) -> None:
        """ValueError naming the settings that cannot go together."""
        px = self.input_size_px
        try:
            NetConfig(conv_channels=tuple(self.conv_channels), height=px, width=px)
        except ValueError as e:
            raise ValueError(f"'conv_channels'={list(self.conv_channels)}: {e}") from None
        if self.d_model % self.heads:
            raise ValueError(f"'d_model' ({self.d_model}) must be divisible by 'heads' ({self.heads})")
        changed = [k for k in SAM_SIZES if getattr(self, k) != getattr(TrainerConfig, k)]
        if self.model == "cnn" and changed:
            raise ValueError(f"{changed} size SAM's relational module; model 'cnn' has none")
        snapshot_steps(self.snapshots, self.total_steps)
        if self.pulls_attention and (self.teacher == "none" or self.sam_readout != "query"):
            raise ValueError(
                f"'attention_weight'={self.teaching.attention_weight:g} needs a teacher (its reason) and sam_readout "
                f"'query' (got teacher {self.teacher!r}, sam_readout {self.sam_readout!r})"
            )


# Without a step budget the schedules are those of a run of this many steps (the shipped recipe's).
NOMINAL_BUDGET = 30000

# trainer_node parameters retired, and what replaces them: a node given one stops and says so.
RETIRED = {
    "lockstep_learning": "trainer_node always learns in lockstep with acting (concurrent learning trained weaker policies)",
    "push_interval_updates": "every frame release carries the weights of the release before (lockstep learning)",
    "save_weights_every_steps": "use 'snapshots' (how many, one every thirtieth of total_steps)",
    "save_weights_from_step": "use 'snapshots' (how many, one every thirtieth of total_steps)",
    **{
        name: "an experiment that did not help (docs/RESULTS.md, 'What was tried')"
        for name in ("n_step", "priority_alpha", "priority_beta", "priority_beta_steps", "clearance_m", "clearance_weight")
        + ("ema_decay", "lr_anneal_updates", "lr_end_fraction", "attention_entropy_weight", "feature_norm", "augment_shift_px")
        + ("consistency_weight", "sam_positions")
    },
}

# TrainerConfig's fields that size SAM's relational module (the NetConfig fields of the same names).
SAM_SIZES = ("d_model", "heads", "relational_blocks", "mlp_hidden")


def snapshot_steps(snapshots: int, total_steps: int) -> list[int]:
    """The env steps of a run's weight snapshots: `snapshots` of them one every thirtieth of the budget, the
    last a thirtieth before its end (30 000 steps, 9: 21 000 ... 29 000); ValueError without a budget."""
    if not snapshots:
        return []
    if total_steps < 30:
        raise ValueError(f"'snapshots'={snapshots} needs a step budget of at least 30 (total_steps={total_steps})")
    every = total_steps // 30
    return list(range(total_steps - snapshots * every, total_steps, every))


def snapshot_file(run_dir, model: str, step: int) -> Path:
    """Where a run writes its weight snapshot of env step `step`."""
    return Path(run_dir) / f"policy_{model}_step{step}.safetensors"


def reward_description(cfg: TrainerConfig) -> str:
    """The training reward in words, for logs."""
    return "the paper's" + (f" - {cfg.turn_penalty:g} per turning step" if cfg.turn_penalty > 0.0 else "")
