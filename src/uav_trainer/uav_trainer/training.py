"""The training core shared by the ROS trainer node and the in-process loop (no ROS here).

It owns the replay memory, the learner, the episode statistics and the run directory:
metrics.csv, episodes.csv, TensorBoard events (tb/), curves.png, checkpoints/, the latest
policy weights (policy_<model>.safetensors, loadable by policy_node's `weights`) and machine.jsonl
(one line per start: the processor, torch and the CPU kernels it picked; a seeded run is
bit-reproducible on one machine, but another processor may round differently).
Thread-safe: one thread adds transitions while another calls `learn_once`.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import platform
import threading
import time
from pathlib import Path

import numpy as np
import torch

from uav_policy import weights as wio
from uav_policy.networks import NetConfig
from uav_sim.reward import band_min_depth, clearance_penalty, step_reward

from . import checkpoint
from .episodes import EpisodeStats
from .learner import Learner, LearnerConfig, NonFiniteLoss, linear_epsilon
from .replay import ReplayMemory


@dataclasses.dataclass(frozen=True)
class TrainerConfig:
    model: str = "sam"  # sam | cnn
    seed: int = 0
    device: str = "cpu"
    replay_capacity: int = 50000  # frames kept (each once)
    learning_starts: int = 1000  # transitions collected before the first update
    replay_ratio: float = 0.25  # at most this many updates per environment step
    push_interval_updates: int = 50  # weights go to the policy every N updates
    checkpoint_interval_updates: int = 1000
    epsilon_start: float = 1.0
    epsilon_end: float = 0.05
    epsilon_decay_steps: int = 10000  # environment steps of linear decay
    total_steps: int = 0  # environment steps budget; 0 = unlimited
    # A stop before the budget writes the replay memory with the final checkpoint, and a resume
    # restores it, so learning carries on at once instead of refilling from an empty memory.
    save_replay: bool = True
    clearance_m: float = 0.0  # > 0 adds clearance_penalty (not in the paper's reward); 0 = the paper's reward
    clearance_weight: float = 4.0
    # > 0 subtracts this from the reward of every step that turns (not in the paper's reward): under
    # the paper's reward a policy can circle on the spot, crash rarely and cover nothing.
    turn_penalty: float = 0.0
    turning_actions: tuple[int, ...] = (1, 2)  # action indices that yaw (the paper's a1, a2)
    # > 1: learn from n-step returns (an extension; the paper learns from one step): a crash's
    # penalty reaches the states n steps before it in one update instead of n.
    n_step: int = 1
    # > 0: prioritized replay (an extension; the paper samples uniformly): transitions are drawn with
    # probability ~ |TD error|^priority_alpha, and the importance-weight exponent rises linearly from
    # priority_beta to 1 over priority_beta_steps environment steps. Crashes are rare in the replay
    # memory; this replays the ones the network still gets wrong more often.
    priority_alpha: float = 0.0
    priority_beta: float = 0.4
    priority_beta_steps: int = 30000
    sam_readout: str = "max"  # SAM readout (networks.SAM_READOUTS); flatten is an extension
    # Square network input (px); the paper does not give one. 64 (the default) gives SAM 8 x 8 nodes,
    # 84 (an experiment: Atari's size) 10 x 10. The camera must render at the same size.
    input_size_px: int = 64
    # Depth frames stacked into the state (the paper: 5; more is an experiment). policy_node's
    # frame_stack must match.
    frames: int = NetConfig.frames
    # The conv trunk's output channels, one stride-2 layer each (an experiment; both models share the
    # trunk): the default three layers give SAM 8 x 8 nodes from 64 px, (16, 32) gives 16 x 16.
    conv_channels: tuple[int, ...] = NetConfig.conv_channels
    # SAM's relational module (an experiment; the defaults are the shipped networks'): node feature
    # size, attention heads, relational blocks and the blocks' MLP width.
    d_model: int = NetConfig.d_model
    heads: int = NetConfig.heads
    relational_blocks: int = NetConfig.relational_blocks
    mlp_hidden: int = NetConfig.mlp_hidden
    learner: LearnerConfig = LearnerConfig()


# The longest n-step return accepted (trainer_node's and inprocess's bound): beyond it the bootstrap's
# gamma^n and the off-policy bias of the stored actions dominate.
MAX_N_STEP = 20

# TrainerConfig's fields that size SAM's relational module (the NetConfig fields of the same names).
SAM_SIZES = ("d_model", "heads", "relational_blocks", "mlp_hidden")


MAX_SNAPSHOTS = 1000  # weight snapshots one run may write (each a full weights file)


def snapshot_steps(every: int, first: int, total_steps: int) -> list[int]:
    """The env steps of trainer_node's weight snapshots: every `every` steps from `first` (0: from `every`)
    to below `total_steps`, whose end the final weights file already holds. Raises ValueError, naming the
    parameters, when snapshots are asked for without a budget, or none or over MAX_SNAPSHOTS fall inside it."""
    if every == 0:
        if first:
            raise ValueError("parameter 'save_weights_from_step' needs save_weights_every_steps > 0")
        return []
    if total_steps == 0:
        raise ValueError("parameter 'save_weights_every_steps' needs a step budget (total_steps > 0)")
    steps = range(first or every, total_steps, every)
    if not 1 <= len(steps) <= MAX_SNAPSHOTS:
        raise ValueError(
            f"parameters 'save_weights_every_steps'={every} and 'save_weights_from_step'={first}: {len(steps)} "
            f"snapshots fall below total_steps={total_steps}; between 1 and {MAX_SNAPSHOTS} can be written"
        )
    return list(steps)


def snapshot_file(run_dir, model: str, step: int) -> Path:
    """Where a run writes its weight snapshot of env step `step`."""
    return Path(run_dir) / f"policy_{model}_step{step}.safetensors"


def priority_beta(cfg: TrainerConfig, env_steps: int) -> float:
    """The importance-weight exponent at env_steps: priority_beta rising linearly to 1."""
    if cfg.priority_beta_steps <= 0 or env_steps >= cfg.priority_beta_steps:
        return 1.0
    return cfg.priority_beta + (1.0 - cfg.priority_beta) * env_steps / cfg.priority_beta_steps


def replay_description(cfg: TrainerConfig) -> str:
    """How the learner samples and bootstraps, for logs."""
    sampling = "uniform replay"
    if cfg.priority_alpha > 0.0:
        sampling = (
            f"prioritized replay (alpha {cfg.priority_alpha:g}, beta {cfg.priority_beta:g} -> 1 "
            f"over {cfg.priority_beta_steps} steps)"
        )
    shift = f", states shifted by up to {cfg.learner.augment_shift_px} px" if cfg.learner.augment_shift_px else ""
    return f"{sampling}, {cfg.n_step}-step returns{shift}"


def reward_description(cfg: TrainerConfig) -> str:
    """The training reward in words, for logs: the paper's, and any extension switched on."""
    parts = ["the paper's"]
    if cfg.turn_penalty > 0.0:
        parts.append(f"- {cfg.turn_penalty:g} per turning step")
    if cfg.clearance_m > 0.0:
        parts.append(f"- clearance penalty (up to {cfg.clearance_weight:g} within {cfg.clearance_m:g} m)")
    return " ".join(parts)


def machine_info() -> dict:
    """What decides a run's floating-point results beyond the code, seed and packages."""
    processor = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            processor = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), processor)
    except OSError:
        pass
    return {
        "processor": processor or platform.machine(),
        "machine": platform.machine(),
        "cpu_kernels": torch.backends.cpu.get_cpu_capability(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "torch_threads": torch.get_num_threads(),
    }


class Training:
    def __init__(self, cfg: TrainerConfig, run_dir: str | Path, log=print, resume: bool = True):
        if not 1 <= cfg.n_step <= MAX_N_STEP:
            raise ValueError(f"n_step must lie in [1, {MAX_N_STEP}], got {cfg.n_step}")
        if not 0.0 <= cfg.priority_alpha <= 1.0 or not 0.0 <= cfg.priority_beta <= 1.0 or cfg.priority_beta_steps < 0:
            raise ValueError(
                "priority_alpha and priority_beta must lie in [0, 1] and priority_beta_steps be >= 0, got "
                f"{cfg.priority_alpha}, {cfg.priority_beta}, {cfg.priority_beta_steps}"
            )
        self.cfg = cfg
        self.log = log
        self.dir = Path(run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.net_cfg = NetConfig(
            model=cfg.model,
            sam_readout=cfg.sam_readout,
            height=cfg.input_size_px,
            width=cfg.input_size_px,
            frames=cfg.frames,
            conv_channels=tuple(cfg.conv_channels),
            **{name: getattr(cfg, name) for name in SAM_SIZES},
        )
        # The depth camera's field of view, recorded in every weights file written; None until the
        # caller says (inprocess.run from its SimConfig, trainer_node from depth/camera_info).
        self.camera_hfov_deg: float | None = None
        # The reward window, recorded when it is not the paper's 20 % (inprocess.run sets it; over ROS
        # the window is sim_node's and trainer_node reads it back from step_outcome's field of view).
        self.reward_window_fraction: float | None = None
        torch.manual_seed(cfg.seed)
        self.learner = Learner(self.net_cfg, dataclasses.replace(cfg.learner, seed=cfg.seed), cfg.device)
        self.replay = ReplayMemory(
            cfg.replay_capacity, (self.net_cfg.height, self.net_cfg.width), self.net_cfg.frames, seed=cfg.seed
        )
        self.stats = EpisodeStats()
        self.lock = threading.Lock()
        self.env_steps = 0
        self.collisions = 0
        self.reward_sum = 0.0
        self.last_loss = float("nan")
        self.last_q = float("nan")
        self.failed: str | None = None
        self._pending_push: bytes | None = None
        self._snapshots_due: list[int] = []  # plan_snapshots: env steps whose weights are still to be written
        self.t_start = time.monotonic()
        self.resumed_from = None
        self._updates_at_start, self._steps_at_start = 0, 0
        if resume:
            self._resume()
        self._record_machine()
        self._pending_push = self.weights_blob()  # the policy acts with the learner's weights from the start
        self._open_logs()

    # -- run directory ------------------------------------------------------------------
    @property
    def checkpoint_dir(self) -> Path:
        return self.dir / "checkpoints"

    @property
    def policy_weights_path(self) -> Path:
        return self.dir / f"policy_{self.cfg.model}.safetensors"

    @property
    def ema_weights_path(self) -> Path:
        return self.dir / f"policy_{self.cfg.model}_ema.safetensors"

    def _record_machine(self) -> None:
        info = machine_info()
        line = {"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "env_steps": self.env_steps, **info}
        with open(self.dir / "machine.jsonl", "a") as f:
            f.write(json.dumps(line) + "\n")
        self.log(
            f"machine: {info['processor']}, torch {info['torch']} with {info['cpu_kernels']} kernels, "
            f"{info['torch_threads']} thread(s)"
        )

    def _open_logs(self) -> None:
        new = not (self.dir / "metrics.csv").exists()
        self._metrics = open(self.dir / "metrics.csv", "a", newline="")
        self._metrics_csv = csv.writer(self._metrics)
        if new:
            self._metrics_csv.writerow(
                [
                    "wall_s",
                    "env_steps",
                    "updates",
                    "episodes",
                    "mean_episode_length",
                    "mean_episode_reward",
                    "loss",
                    "q_mean",
                    "epsilon",
                    "env_steps_per_s",
                    "updates_per_s",
                ]
            )
        path = self.dir / "episodes.csv"
        header = ""
        if path.exists():
            with open(path) as f:
                header = f.readline().strip()
        # `end`: crash or time_limit. A run resumed from before that column keeps its four.
        self._episode_end_column = not header or header.endswith(",end")
        self._episodes = open(path, "a", newline="")
        self._episodes_csv = csv.writer(self._episodes)
        if not header:
            self._episodes_csv.writerow(["episode", "env_step", "length", "reward", "end"])
        try:
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(self.dir / "tb"))
        except Exception as e:  # tensorboard is optional at run time
            self.log(f"TensorBoard disabled: {e}")
            self.tb = None
        self._rate_mark = (time.monotonic(), self.env_steps, self.learner.updates)

    def _resume(self) -> None:
        path = checkpoint.latest(self.checkpoint_dir)
        if path is None:
            return
        meta = checkpoint.load(path, self.learner)
        c = meta["counters"]
        self.env_steps = int(c.get("env_steps", 0))
        self.stats.episodes = int(c.get("episodes", 0))
        self.collisions = int(c.get("collisions", 0))
        if "replay" in meta.get("rng", {}):
            checkpoint.set_rng_state(self.replay.rng, meta["rng"]["replay"])
        self.resumed_from = path
        restored = self._restore_replay(path)
        if not restored:
            # Learning waits for learning_starts new transitions, then keeps replay_ratio from here.
            self._updates_at_start, self._steps_at_start = self.learner.updates, self.env_steps
        self.log(
            f"resumed from {path}: {self.learner.updates} updates, {self.env_steps} env steps "
            + (f"(replay memory restored: {restored})" if restored else "(the replay memory refills before learning continues)")
        )

    def _restore_replay(self, path: Path) -> str:
        """Load the checkpoint's replay memory if it has one and it fits; a description, or "" if none was
        restored. A bad or mismatching file is logged and skipped: the run refills instead."""
        try:
            state = checkpoint.load_replay(path)
            if state is None:
                return ""
            self.replay.load_state(state, self.net_cfg.actions)
        except ValueError as e:
            self.log(f"replay memory not restored: {e}")
            return ""
        return f"{len(self.replay)} transitions"

    # -- acting side --------------------------------------------------------------------
    def epsilon(self) -> float:
        c = self.cfg
        return linear_epsilon(self.env_steps, c.epsilon_start, c.epsilon_end, c.epsilon_decay_steps)

    def add_first(self, frame: np.ndarray) -> None:
        with self.lock:
            self.replay.add_first(frame)

    def add_step(self, action: int, beta_m: float, collided: bool, next_frame: np.ndarray) -> float:
        """One transition; the reward comes from the simulator package's reward function. Steps after the
        budget is spent are not recorded (not learnt from, counted or logged)."""
        reward = step_reward(beta_m, collided)
        if self.cfg.clearance_m > 0.0 and not collided:  # after a collision next_frame is the next episode's
            reward += clearance_penalty(band_min_depth(next_frame), self.cfg.clearance_m, self.cfg.clearance_weight)
        if self.cfg.turn_penalty > 0.0 and not collided and action in self.cfg.turning_actions:
            reward -= self.cfg.turn_penalty
        with self.lock:
            if self.budget_done:  # over ROS a step can arrive before trainer_node has shut down: not recorded
                return reward
            self.replay.add_transition(action, reward, collided, next_frame)
            self.env_steps += 1
            self.reward_sum += reward
            self.collisions += int(collided)
            ended = self.stats.step(reward, collided, self.env_steps)
        self._log_episode(ended, "crash")
        return reward

    def add_truncated(self, first_frame: np.ndarray) -> None:
        """A step that ended its episode without a collision (the simulator's time limit): nothing is
        learnt from it, because its next frame is already the new episode's first (`first_frame`),
        which starts a new chain. Counted as an environment step with reward 0 in the episode stats."""
        with self.lock:
            if self.budget_done:
                return
            self.replay.add_first(first_frame)
            self.env_steps += 1
            ended = self.stats.step(0.0, True, self.env_steps)
        self._log_episode(ended, "time_limit")

    def _log_episode(self, ended: tuple[int, float] | None, end: str) -> None:
        if not ended:
            return
        row = [self.stats.episodes, self.env_steps, ended[0], f"{ended[1]:.3f}"]
        self._episodes_csv.writerow(row + [end] if self._episode_end_column else row)
        self._episodes.flush()
        if self.tb:
            self.tb.add_scalar("episode/length", ended[0], self.env_steps)
            self.tb.add_scalar("episode/reward", ended[1], self.env_steps)

    @property
    def budget_done(self) -> bool:
        return self.cfg.total_steps > 0 and self.env_steps >= self.cfg.total_steps

    # -- learning side ------------------------------------------------------------------
    def _updates_due(self) -> tuple[bool, float]:
        """(enough transitions since start-up, the updates replay_ratio x env steps allows so far)."""
        with self.lock:
            ready = len(self.replay) >= min(self.cfg.learning_starts, self.cfg.replay_capacity - 10)
            fresh_steps = self.env_steps - self._steps_at_start - self.cfg.learning_starts
        return ready, self._updates_at_start + fresh_steps * self.cfg.replay_ratio

    def can_learn(self) -> bool:
        """Enough transitions since start-up, and updates below replay_ratio x env steps."""
        if self.failed:
            return False
        ready, allowed = self._updates_due()
        return ready and self.learner.updates < allowed

    def learning_lag(self) -> tuple[int, int]:
        """(updates the learner is short of replay_ratio x env steps, updates due since learning began).
        In process acting waits for learning, so this stays 0; over ROS acting runs on and the learner
        can fall behind on a busy machine."""
        ready, allowed = self._updates_due()
        due = int(allowed) - self._updates_at_start
        if not ready or due <= 0:
            return 0, 0
        return max(0, int(allowed) - self.learner.updates), due

    def learn_once(self) -> bool:
        """One update if allowed now; handles push and checkpoint cadence. False if nothing done."""
        if not self.can_learn():
            return False
        c = self.cfg
        with self.lock:
            beta = priority_beta(c, self.env_steps)
            batch = self.replay.sample(c.learner.batch_size, c.n_step, c.learner.gamma, c.priority_alpha, beta)
        try:
            out = self.learner.update(batch)
        except NonFiniteLoss as e:
            self.failed = (
                f"learning stopped: {e}. The last good checkpoint is kept"
                f" ({checkpoint.latest(self.checkpoint_dir) or 'none written yet'})."
            )
            self.log(self.failed)
            return False
        if c.priority_alpha > 0.0:
            with self.lock:
                self.replay.update_priorities(batch["index"], batch["writes"], out["td_abs"])
        self.last_loss, self.last_q = out["loss"], out["q_mean"]
        u = self.learner.updates
        if self.tb and u % 10 == 0:
            self.tb.add_scalar("train/loss", out["loss"], u)
            self.tb.add_scalar("train/q_mean", out["q_mean"], u)
        if u % self.cfg.push_interval_updates == 0:
            self._pending_push = self.weights_blob()
        if u % self.cfg.checkpoint_interval_updates == 0:
            self.save_checkpoint()
        return True

    def take_push(self) -> bytes | None:
        blob, self._pending_push = self._pending_push, None
        return blob

    def weights_blob(self) -> bytes:
        return wio.to_bytes(self.learner.online, self.net_cfg, self.camera_hfov_deg, self.reward_window_fraction)

    # -- outputs ------------------------------------------------------------------------
    def counters(self) -> dict:
        return {
            "env_steps": self.env_steps,
            "episodes": self.stats.episodes,
            "collisions": self.collisions,
            "updates": self.learner.updates,
        }

    def save_checkpoint(self, final: bool = False) -> Path | None:
        """A checkpoint, the policy weights and the curves. `final` (a stop) also writes the replay
        memory when save_replay is on and the step budget is not used up, so a resume carries on."""
        if self.failed:
            return None
        with_replay = final and self.cfg.save_replay and not self.budget_done
        with self.lock:
            counters = self.counters()
            rng = {"replay": checkpoint.rng_state(self.replay.rng)}
            replay = self.replay.state() if with_replay else None
        path = checkpoint.save(self.checkpoint_dir, self.learner, counters, rng, replay)
        if replay is not None:
            mib = sum(a.nbytes for a in replay.values()) / 2**20
            self.log(f"replay memory saved with the checkpoint: {len(self.replay)} transitions, {mib:.0f} MiB")
        self.save_weights(self.policy_weights_path)
        if self.learner.ema is not None:
            self.save_weights(self.ema_weights_path, self.learner.ema)
        self.plot()
        return path

    def snapshot_path(self, step: int) -> Path:
        return snapshot_file(self.dir, self.cfg.model, step)

    def plan_snapshots(self, steps) -> None:
        """Write the online network as snapshot_path(N) once the run reaches env step N, for each N in
        `steps` it has not passed yet (a resumed run keeps the snapshots it wrote before)."""
        self._snapshots_due = sorted({int(n) for n in steps if int(n) > self.env_steps})

    def save_due_snapshots(self) -> list[Path]:
        """Write the planned snapshots whose env step has been reached; returns their paths. In process
        this is called right after the step's updates; over ROS from the learner thread between updates,
        so a snapshot holds the updates done when the learner saw its step."""
        written = []
        while self._snapshots_due and self._snapshots_due[0] <= self.env_steps and not self.failed:
            path = self.snapshot_path(self._snapshots_due.pop(0))
            self.save_weights(path)
            written.append(path)
        return written

    def save_weights(self, path, net=None) -> None:
        """Write `net` (default: the online network) as a policy weights file, atomically, with this run's
        camera and (when not the paper's) reward window."""
        net = self.learner.online if net is None else net
        wio.save_file(net, self.net_cfg, path, self.camera_hfov_deg, self.reward_window_fraction)

    def metrics_row(self) -> dict:
        now = time.monotonic()
        t, s, u = self._rate_mark
        dt = max(now - t, 1e-9)
        self._rate_mark = (now, self.env_steps, self.learner.updates)
        row = {
            "wall_s": round(now - self.t_start, 2),
            "env_steps": self.env_steps,
            "updates": self.learner.updates,
            "episodes": self.stats.episodes,
            "mean_episode_length": self.stats.mean_length(),
            "mean_episode_reward": self.stats.mean_reward(),
            "loss": self.last_loss,
            "q_mean": self.last_q,
            "epsilon": self.epsilon(),
            "env_steps_per_s": (self.env_steps - s) / dt,
            "updates_per_s": (self.learner.updates - u) / dt,
        }
        self._metrics_csv.writerow([f"{v:.4f}" if isinstance(v, float) else v for v in row.values()])
        self._metrics.flush()
        if self.tb:
            for k in ("mean_episode_length", "mean_episode_reward", "epsilon", "env_steps_per_s", "updates_per_s"):
                if not math.isnan(row[k]):
                    self.tb.add_scalar(f"progress/{k}", row[k], self.env_steps)
            self.tb.flush()
        return row

    def plot(self) -> Path | None:
        """curves.png: mean episode length and reward against environment steps (paper Figs. 3-4)."""
        hist = list(self.stats.history)
        if len(hist) < 2:
            return None
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        steps = np.array([h[0] for h in hist])
        k = max(1, min(20, len(hist) // 5))
        smooth = lambda x: np.convolve(x, np.ones(k) / k, mode="valid")  # noqa: E731
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
        for ax, col, label in ((axes[0], 1, "mean episode length (steps)"), (axes[1], 2, "mean episode reward")):
            vals = np.array([h[col] for h in hist], dtype=float)
            ax.plot(steps, vals, alpha=0.25, lw=0.8)
            ax.plot(steps[k - 1 :], smooth(vals), lw=1.8)
            ax.set_xlabel("environment steps")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        fig.suptitle(f"D3QN-{self.cfg.model.upper()} training, seed {self.cfg.seed} (moving mean of {k} episodes)")
        fig.tight_layout()
        out = self.dir / "curves.png"
        tmp = self.dir / ".curves.png.tmp.png"
        fig.savefig(tmp, dpi=100)
        plt.close(fig)
        tmp.replace(out)
        return out

    def close(self) -> None:
        for f in (self._metrics, self._episodes):
            f.close()
        if self.tb:
            self.tb.close()
