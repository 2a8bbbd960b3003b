"""The training core shared by the ROS trainer node and the in-process loop (no ROS here).

It owns the replay memory, the learner, the episode statistics and the run directory:
metrics.csv, episodes.csv, TensorBoard events (tb/), curves.png, checkpoints/, the latest
policy weights (policy_<model>.safetensors, loadable by policy_node's `weights`) and machine.jsonl
(one line per start: the processor, torch and the CPU kernels it picked; a seeded run is
bit-reproducible on one machine, but another processor may round differently).
"""

from __future__ import annotations

import csv
import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import torch

from uav_policy import weights as wio
from uav_policy.agent import resolve_device
from uav_policy.networks import NetConfig
from uav_sim.reward import step_reward

from . import checkpoint
from .episodes import EpisodeStats
from .learner import Learner, NonFiniteLoss
from .pairing import ActorSink
from .replay import LanedReplay, ReplayMemory
from .run_logs import METRICS_COLUMNS, plot_curves, record_machine
from .teacher import DaggerDraw
from .training_config import SAM_SIZES, TrainerConfig, linear_epsilon, snapshot_file, snapshot_steps


class RunDirError(ValueError):
    """The run folder cannot be written: the message names it and why."""


class Training:
    """One training run: add transitions as they come, then `learn_due()` after each step. Single-threaded:
    the in-process loop and trainer_node (which learns in lockstep with acting) call it the same way.

    With several `actors` (trainer_node's `actors`), each actor's steps go to a lane of their own in the replay
    memory and to an episode of their own, and each actor explores at its own rate (`epsilon(actor)`)."""

    def __init__(self, cfg: TrainerConfig, run_dir: str | Path, log=print, resume: bool = True, actors: int = 1):
        cfg.validate()
        if actors < 1:
            raise ValueError(f"a training run needs at least one actor, got {actors}")
        self.cfg = cfg
        self.actors = actors
        self.log = log
        self._who_flies = DaggerDraw(cfg.seed)  # teacher_flies
        self.dir = Path(run_dir)
        try:  # refused at once, in one line, rather than as a traceback at the first write
            self.dir.mkdir(parents=True, exist_ok=True)
            probe = self.dir / ".write_test"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as e:
            raise RunDirError(f"run_dir '{self.dir}': cannot write there ({e.strerror or e})") from None
        stale = checkpoint.remove_stale(self.checkpoint_dir)
        if stale:
            log(f"removed {stale} unfinished checkpoint folder(s) an interrupted run left behind")
        self.checkpoint_failures = 0
        self.unwritten: dict[Path, str] = {}  # weights files (snapshots, the policy) whose last write failed, and why
        self._checkpoint_wall = time.monotonic()
        self.net_cfg = NetConfig(
            model=cfg.model,
            sam_readout=cfg.sam_readout,
            height=cfg.input_size_px,
            width=cfg.input_size_px,
            frames=cfg.frames,
            conv_channels=tuple(cfg.conv_channels),
            local_map=cfg.local_map,
            **{name: getattr(cfg, name) for name in SAM_SIZES},
        )
        # The depth camera's field of view, recorded in every weights file written; None until the
        # caller says (inprocess.run from its SimConfig, trainer_node from depth/camera_info).
        self.camera_hfov_deg: float | None = None
        # The reward window, recorded when it is not the paper's 20 % (inprocess.run sets it; over ROS
        # the window is sim_node's and trainer_node reads it back from step_outcome's field of view).
        self.reward_window_fraction: float | None = None
        self._released: tuple[int, bytes] | None = None  # released_weights
        self._released_made = None  # the update count and camera its blob was made with
        torch.manual_seed(cfg.seed)
        self.learner = Learner(
            self.net_cfg, dataclasses.replace(cfg.learner, seed=cfg.seed), resolve_device(cfg.device), cfg.teaching
        )
        shape = (self.net_cfg.height, self.net_cfg.width)
        # With attention_weight, the cells of the attention shown, on which the teacher's reason is kept per frame.
        self.reason_grid = self.learner.online.grid_hw if cfg.pulls_attention else None
        # (a map network attends over the image's cells and then the map's: a reason for each)
        cells = math.prod(self.reason_grid) * (1 + self.net_cfg.local_map) if self.reason_grid else 0
        memory = (cfg.replay_capacity, shape, self.net_cfg.frames, cfg.seed, cells, cfg.local_map)
        self.replay = ReplayMemory(*memory) if actors == 1 else LanedReplay(actors, *memory)
        # The journal keeps one actor's chain; with several, a resume refills the memory.
        self.journal = cfg.save_replay and actors == 1
        if cfg.save_replay and actors > 1:
            log(f"with {actors} actors the replay memory is not journaled: a resume refills it before learning on")
        self._journaled = 0  # replay writes already in the checkpoints' journal
        self.stats = EpisodeStats()
        self.env_steps = 0
        self.actor_steps = [0] * actors  # of env_steps, each actor's (this start's: not checkpointed)
        self.collisions = 0
        self.reward_sum = 0.0
        self.last_loss = float("nan")
        self.last_q = float("nan")
        self.failed: str | None = None
        self.t_start = time.monotonic()
        self.resumed_from = None
        # Updates are allowed replay_ratio per step after _refill steps from (_updates_at_start, _steps_at_start).
        self._updates_at_start, self._steps_at_start = 0, 0
        self._refill = cfg.first_update_after
        if resume:
            self._resume()
        if self.resumed_from is None:  # a fresh memory: an earlier run's journal is not its
            checkpoint.drop_journal(self.checkpoint_dir)
        # The snapshots still to be written (a resumed run keeps those it wrote before).
        self._snapshots_due = [n for n in snapshot_steps(cfg.snapshots, cfg.total_steps) if n > self.env_steps]
        for warning in cfg.budget_warnings():
            self.log(f"warning: {warning}")
        self._record_machine()
        self._open_logs()

    # -- run directory ------------------------------------------------------------------
    @property
    def checkpoint_dir(self) -> Path:
        return self.dir / "checkpoints"

    @property
    def policy_weights_path(self) -> Path:
        return self.dir / f"policy_{self.cfg.model}.safetensors"

    def _record_machine(self) -> None:
        info = record_machine(self.dir, self.env_steps)
        self.log(
            f"machine: {info['processor']}, torch {info['torch']} with {info['cpu_kernels']} kernels, "
            f"{info['torch_threads']} thread(s)"
        )

    def _open_logs(self) -> None:
        new = not (self.dir / "metrics.csv").exists()
        self._metrics = open(self.dir / "metrics.csv", "a", newline="")
        self._metrics_csv = csv.writer(self._metrics)
        if new:
            self._metrics_csv.writerow(METRICS_COLUMNS)
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
        restored = self._restore_replay(path, int(c.get("replay_writes", 0)))
        if len(self.replay) < self._learning_threshold:
            # Too few transitions to learn from (none restored, or a memory collected since an earlier crash):
            # learning waits until the memory holds learning_starts, then keeps replay_ratio from there, with
            # no burst of the updates the pause did not make.
            self._updates_at_start, self._steps_at_start = self.learner.updates, self.env_steps
            self._refill = self._learning_threshold - len(self.replay)
        self.log(
            f"resumed from {path}: {self.learner.updates} updates, {self.env_steps} env steps "
            + (f"(replay memory restored: {restored})" if restored else "(the replay memory refills before learning continues)")
        )

    def _restore_replay(self, path: Path, writes: int) -> str:
        """Rebuild the replay memory from the journal as it was at checkpoint `path` (`writes` frames
        written); a description, or "" if none was restored. A bad, mismatching or broken journal is
        logged and dropped: the run refills instead, and journals afresh."""
        if not self.journal or writes == 0:
            return ""
        try:
            segments = checkpoint.journal_segments(self.checkpoint_dir, path)
            if not segments:
                return ""
            self.replay.load_segments(segments, writes, self.net_cfg.actions)
        except ValueError as e:
            self.log(f"replay memory not restored: {e}")
            checkpoint.drop_journal(self.checkpoint_dir)
            return ""
        self._journaled = self.replay.writes
        lost = writes - self.replay.writes
        return f"{len(self.replay)} transitions" + (f"; the {lost} frames after the journal's end are lost" if lost else "")

    # -- acting side --------------------------------------------------------------------
    def epsilon(self, actor: int = 0) -> float:
        """The exploration rate of `actor` now: the linear schedule (epsilon_start to epsilon_end over the decay
        steps), raised, with several actors, to Ape-X's power 1 + 7 i / (N - 1). Actor 0 follows the schedule,
        the last one explores least (at the schedule's 0.05 end: 0.05 and 0.05^8), all start at 1.0."""
        c = self.cfg
        base = linear_epsilon(self.env_steps, c.epsilon_start, c.epsilon_end, c.decay_steps)
        return base if self.actors == 1 else base ** (1.0 + 7.0 * actor / (self.actors - 1))

    def teacher_flies(self, label: int) -> int | None:
        """The teacher's action `label` (-1: none) when the teacher flies this step instead of the student, else None:
        drawn (one draw a labelled decision, in process as over ROS) with a probability falling from teacher_act_start
        to 0 over the budget."""
        return self._who_flies(label, self.cfg.teacher_act_probability(self.env_steps))

    def _memory(self, actor: int) -> ReplayMemory:
        return self.replay if self.actors == 1 else self.replay.lanes[actor]

    def sink(self, actor: int) -> ActorSink:
        """Where actor `actor`'s steps go (a TransitionAssembler's sink)."""
        return ActorSink(self, actor)

    def add_first(self, frame: np.ndarray, actor: int = 0, grid: np.ndarray | None = None) -> None:
        """A frame that starts a chain (`grid`: its local map, with `local_map`)."""
        self._memory(actor).add_first(frame, grid)

    def add_step(
        self, action: int, beta_m: float, collided: bool, next_frame, actor: int = 0, teacher: int = -1, reason=None, grid=None
    ) -> float:
        """One transition of `actor` (`teacher`: the teacher's action for the frame it left, -1 for none; `reason`: the
        share of each node of the attention its reason covers in that frame, None for none; `grid`: the next frame's
        local map, with `local_map`); the reward comes from the simulator package's reward function. Steps after the
        budget is spent are not recorded (not learnt from, counted or logged)."""
        reward = step_reward(beta_m, collided)
        if self.cfg.turn_penalty > 0.0 and not collided and action in self.cfg.turning_actions:
            reward -= self.cfg.turn_penalty
        if self.budget_done:  # over ROS a step can arrive before trainer_node has shut down: not recorded
            return reward
        self._memory(actor).add_transition(action, reward, collided, next_frame, teacher, reason, grid)
        self.env_steps += 1
        self.actor_steps[actor] += 1
        self.reward_sum += reward
        self.collisions += int(collided)
        self._log_episode(self.stats.step(reward, collided, self.env_steps, actor), "crash")
        return reward

    def add_truncated(self, first_frame: np.ndarray, actor: int = 0, grid: np.ndarray | None = None) -> None:
        """A step that ended its episode without a collision (the simulator's time limit): nothing is
        learnt from it, because its next frame is already the new episode's first (`first_frame`),
        which starts a new chain. Counted as an environment step with reward 0 in the episode stats."""
        if self.budget_done:
            return
        self._memory(actor).add_first(first_frame, grid)
        self.env_steps += 1
        self.actor_steps[actor] += 1
        self._log_episode(self.stats.step(0.0, True, self.env_steps, actor), "time_limit")

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
    @property
    def _learning_threshold(self) -> int:
        """Transitions the memory must hold before an update: learning_starts (less when it cannot hold them)."""
        return min(self.cfg.first_update_after, self.cfg.replay_capacity - 10)

    def can_learn(self) -> bool:
        """Enough transitions since start-up, and updates below replay_ratio x env steps."""
        if self.failed:
            return False
        c = self.cfg
        ready = len(self.replay) >= self._learning_threshold
        allowed = self._updates_at_start + (self.env_steps - self._steps_at_start - self._refill) * c.replay_ratio
        return ready and self.learner.updates < allowed

    def learn_once(self) -> bool:
        """One update if allowed now, with the checkpoint cadence. False if nothing was done."""
        if not self.can_learn():
            return False
        batch = self.replay.sample(self.cfg.learner.batch_size)
        try:
            out = self.learner.update(batch)
        except NonFiniteLoss as e:
            self.failed = (
                f"learning stopped: {e}. The last good checkpoint is kept"
                f" ({checkpoint.latest(self.checkpoint_dir) or 'none written yet'})."
            )
            self.log(self.failed)
            return False
        self.last_loss, self.last_q = out["loss"], out["q_mean"]
        u = self.learner.updates
        if self.tb and u % 10 == 0:
            self.tb.add_scalar("train/loss", out["loss"], u)
            self.tb.add_scalar("train/q_mean", out["q_mean"], u)
        due_by_time = time.monotonic() - self._checkpoint_wall >= self.cfg.checkpoint_interval_s
        if u % self.cfg.checkpoint_interval_updates == 0 or due_by_time:
            self.save_checkpoint()
        return True

    def learn_due(self) -> list[Path]:
        """After each stored step: the updates replay_ratio allows, then the snapshots due; their paths.
        The per-step learning of both the in-process loop and trainer_node."""
        while self.learn_once():
            pass
        written = []
        while self._snapshots_due and self._snapshots_due[0] <= self.env_steps and not self.failed:
            step = self._snapshots_due.pop(0)
            if self.learner.updates == 0:  # an untrained network is no snapshot of anything
                self.log(f"step {step}: no update yet (learning starts after {self.cfg.first_update_after}), no snapshot")
                continue
            path = self.snapshot_path(step)
            try:
                self.save_weights(path)
            except OSError as e:
                self.checkpoint_failures += 1
                self.unwritten[path] = e.strerror or str(e)
                self.log(f"snapshot {path.name} not written ({e.strerror or e}); training goes on")
                continue
            written.append(path)
        return written

    def weights_blob(self) -> bytes:
        return wio.to_bytes(self.learner.online, self.net_cfg, self.camera_hfov_deg, self.reward_window_fraction)

    # -- the weights a frame is answered with ------------------------------------------------
    def released_weights(self) -> tuple[int, bytes]:
        """(version, safetensors blob) of the weights the next released frame is answered with: the learner's as they
        were when the frame before it was released (after_release). A step's updates run while its frame is answered,
        and the weights they make go out with the frame after next, so that no frame waits for them. The version
        grows with each new blob: a policy that has it is not sent it again."""
        if self._released is None:  # the first release: the weights as they are
            self.after_release()
        return self._released

    def after_release(self) -> None:
        """A frame was released: the next release carries the learner's weights as they are now (serialised once per
        update and camera; over ROS while the policy acts and the simulator steps)."""
        made = (self.learner.updates, self.camera_hfov_deg, self.reward_window_fraction)
        if self._released is None or self._released_made != made:
            version = self._released[0] + 1 if self._released else 0
            self._released, self._released_made = (version, self.weights_blob()), made

    # -- outputs ------------------------------------------------------------------------
    def counters(self) -> dict:
        return {
            "env_steps": self.env_steps,
            "episodes": self.stats.episodes,
            "collisions": self.collisions,
            "updates": self.learner.updates,
            "replay_writes": self.replay.writes,
        }

    def save_checkpoint(self, final: bool = False) -> Path | None:
        """A checkpoint, the policy weights and the curves. While the step budget lasts (and save_replay
        is on) it carries the replay memory's frames since the previous one, joining the journal a resume
        rebuilds the memory from; at the end of the budget the journal is removed.

        A write that fails (a full or read-only disk) is logged and counted (`checkpoint_failures`) and
        the previous checkpoint stays `latest`: training goes on. A checkpoint whose replay segment does not
        fit is written without it (the next one carries those frames)."""
        if self.failed:
            return None
        self._checkpoint_wall = time.monotonic()
        if self.budget_done and final:  # what the run no longer needs goes before the last writes
            freed = checkpoint.drop_journal(self.checkpoint_dir)
            if freed:
                self.log(f"the step budget is spent: the replay journal ({freed / 2**20:.0f} MiB) is removed")
        rng = {"replay": checkpoint.rng_state(self.replay.rng)}
        journaling = self.journal and not self.budget_done and self.replay.writes > self._journaled
        segment = self.replay.segment(self._journaled) if journaling else None
        try:
            path = checkpoint.save(self.checkpoint_dir, self.learner, self.counters(), rng, segment)
        except OSError as e:
            path = None
            if segment is None:
                self._checkpoint_failed(e)
            else:
                self.log(f"the checkpoint with the replay segment could not be written ({e.strerror or e}): writing it without")
                segment = None
                try:
                    path = checkpoint.save(self.checkpoint_dir, self.learner, self.counters(), rng)
                except OSError as e2:
                    self._checkpoint_failed(e2)
        if path is None and not final:
            return None
        if segment is not None:
            self._journaled = self.replay.writes
            checkpoint.prune_journal(self.checkpoint_dir, self.replay.writes - self.replay.capacity)
            if final:
                mib = sum(a.nbytes for a in segment.values()) / 2**20
                self.log(
                    f"replay memory saved with the checkpoint: {len(self.replay)} transitions in the journal "
                    f"(this checkpoint wrote the last {mib:.0f} MiB)"
                )
        try:  # the final weights are written even when the final checkpoint could not be
            self.save_weights(self.policy_weights_path)
            self.unwritten.pop(self.policy_weights_path, None)
        except OSError as e:
            self.unwritten[self.policy_weights_path] = e.strerror or str(e)
            self.log(
                f"{'checkpoint ' + path.name + ' written, but ' if path else ''}{self.policy_weights_path.name} not written: {e}"
            )
        try:
            self.plot()
        except OSError as e:
            self.log(f"curves.png not written: {e}")
        return path

    def unwritten_report(self) -> str | None:
        """At the end of a run: which weights files are stale (an earlier write of this run or another) or missing,
        and the checkpoint that stays `latest`; None when every one was written."""
        if not self.unwritten:
            return None
        files = ", ".join(f"{p} ({'stale' if p.is_file() else 'missing'}: {why})" for p, why in sorted(self.unwritten.items()))
        kept = checkpoint.latest(self.checkpoint_dir)
        return f"weights not written: {files}; latest checkpoint: {kept or 'none'}"

    def _checkpoint_failed(self, e: OSError) -> None:
        self.checkpoint_failures += 1
        kept = checkpoint.latest(self.checkpoint_dir)
        self.log(
            f"checkpoint at update {self.learner.updates} not written ({e.strerror or e}); "
            f"{'latest stays ' + kept.name if kept else 'there is no earlier checkpoint'}; training goes on "
            f"({self.checkpoint_failures} failed so far)"
        )
        return None

    def snapshot_path(self, step: int) -> Path:
        return snapshot_file(self.dir, self.cfg.model, step)

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
        return plot_curves(list(self.stats.history), self.cfg.model, self.cfg.seed, self.dir)

    def close(self) -> None:
        self.metrics_row()  # the run's last row: progress readers see where it ended
        for f in (self._metrics, self._episodes):
            f.close()
        if self.tb:
            self.tb.close()
