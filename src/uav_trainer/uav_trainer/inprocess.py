"""Training without ROS: the same simulator, networks, replay, learner and run directory as the
ROS trainer, in one synchronous loop (act one step, then learn while replay_ratio allows).

Bit-for-bit reproducible for a seed, so benchmarks, hyperparameter searches and the shipped
weights use it; the ROS trainer runs the same pieces concurrently. Example:

    python -m uav_trainer.inprocess --model sam --steps 30000 --seed 0 --run-dir runs/inproc_sam_seed0
"""

from __future__ import annotations

import argparse
import copy
import csv
import dataclasses
import time

import torch

from uav_policy.actions import PAPER_ACTIONS, turning_indices
from uav_policy.agent import Agent
from uav_policy.frame_stack import FrameStack
from uav_policy.networks import MAX_FRAMES, SAM_READOUTS, NetConfig
from uav_sim.simulator import RewardWindowError, SimConfig, Simulator, reward_floor_problem
from uav_sim.vehicle import BodyTwist
from uav_sim.world import load_world, training_layouts

from .learner import MAX_SHIFT_PX, LearnerConfig
from .training import MAX_N_STEP, SAM_SIZES, TrainerConfig, Training, replay_description, reward_description

VALIDATION_WORLDS = ("random:200", "random:201", "random:202", "random:203", "random:204")


class Validation:
    """Model selection on held-out layouts: every `every` env steps (once epsilon has reached its
    end) the greedy network flies `steps` steps in each validation world from random start
    headings; the best so far (fewest crashes, then highest mean reward) is written atomically to
    policy_<model>_best.safetensors, and every score to validation.csv.

    The validation worlds are procedural layouts that neither training (seeds >= 1000) nor the
    held-out test worlds (random:101..103) use, so selecting on them leaves the test worlds unseen.
    """

    def __init__(
        self,
        training: Training,
        every: int,
        worlds=VALIDATION_WORLDS,
        steps: int = 500,
        log=print,
        hfov_deg=90.0,
        reward_window_fraction=None,
    ):
        if every < 1 or steps < 1 or not worlds:
            raise ValueError(f"validation needs every >= 1, steps >= 1 and a world, got {every}, {steps}, {worlds}")
        self.training, self.every, self.worlds, self.steps, self.log = training, every, tuple(worlds), steps, log
        self.hfov_deg, self.reward_window_fraction = hfov_deg, reward_window_fraction  # as training flies
        self.best: tuple[int, float] | None = None
        self.path = training.dir / f"policy_{training.cfg.model}_best.safetensors"
        path = training.dir / "validation.csv"
        if path.exists():  # a resumed run keeps competing with the best it already saved
            kept = [(int(r["crashes"]), float(r["mean_reward"])) for r in csv.DictReader(open(path)) if r["best"] == "1"]
            self.best = min(kept, key=lambda b: (b[0], -b[1]), default=None)
        self._csv = open(path, "a", newline="")
        self._rows = csv.writer(self._csv)
        if self._csv.tell() == 0:
            self._rows.writerow(["env_steps", "updates", "crashes", "steps", "mean_reward", "best"])

    def __call__(self, training: Training) -> None:
        c = training.cfg
        if training.env_steps % self.every or training.env_steps < c.epsilon_decay_steps:
            return
        from .evaluate import evaluate_inprocess

        net = copy.deepcopy(training.learner.online).cpu()  # the flights must not move or switch the learner's network
        results = [
            evaluate_inprocess(
                c.model,
                "",
                w,
                self.steps,
                seed=i,
                net=net,
                net_cfg=training.net_cfg,
                start_yaw_jitter_deg=180.0,
                hfov_deg=self.hfov_deg,
                reward_window_fraction=self.reward_window_fraction,
            )
            for i, w in enumerate(self.worlds)
        ]
        crashes = sum(r.crashes for r in results)
        reward = sum(r.mean_reward for r in results) / len(results)
        better = self.best is None or (crashes, -reward) < (self.best[0], -self.best[1])
        if better:
            self.best = (crashes, reward)
            training.save_weights(self.path)
        self._rows.writerow(
            [training.env_steps, training.learner.updates, crashes, self.steps * len(self.worlds), f"{reward:.4f}", int(better)]
        )
        self._csv.flush()
        self.log(
            f"validation at step {training.env_steps}: {crashes} crashes, mean reward {reward:.3f}{' (best)' if better else ''}"
        )

    def close(self) -> None:
        self._csv.close()


class PushedActing:
    """Acting as policy_node does beside the ROS trainer (an experiment, round 41): the agent flies a
    copy of the online network, replaced whenever the learner's update count reaches a multiple of
    `every` (trainer_node's push_interval_updates), instead of the newest network. Until the first
    interval's push it flies the initial network, which trainer_node pushes at start-up. The push's delivery
    (about 40 ms over ROS, one or two steps at 30 steps/s) is not modelled: the copy acts from the next
    step. A resumed run starts from a copy of the resumed network."""

    def __init__(self, agent: Agent, learner, every: int):
        if every < 1:
            raise ValueError(f"a push interval must be >= 1 update, got {every}")
        self.agent, self.learner, self.every = agent, learner, every
        self.pushes = learner.updates // every
        agent.swap(copy.deepcopy(learner.online))

    def after_learning(self) -> None:
        n = self.learner.updates // self.every
        if n != self.pushes:
            self.pushes = n
            self.agent.swap(copy.deepcopy(self.learner.online))


def run(
    cfg: TrainerConfig,
    run_dir: str,
    world: str = "basic",
    start_yaw_jitter_deg: float = 180.0,
    log_every: int = 1000,
    log=print,
    resume: bool = False,
    on_step=None,
    layout_per_episode: bool = False,
    validation=None,
    hfov_deg: float = SimConfig.hfov_deg,
    redraw_heading: bool = False,
    max_episode_steps: int = 0,
    save_weights_at=(),
    random_start_fraction: float = 0.0,
    reward_window_fraction: float = SimConfig.reward_window_fraction,
    world_every: int = 0,
    partitions: bool = False,
    act_on_pushes: int = 0,
) -> Training:
    """Train until the budget; `on_step(training)` may return True to stop early.

    With `layout_per_episode`, every episode flies a new procedural layout (seeds 1000 and up,
    so `random:0..999` stay held out) instead of `world`, and every episode starts at the same
    heading (the seed's first draw), as for the shipped weights; `redraw_heading` draws a new one
    every episode (it trained worse: docs/RESULTS.md, round 5). sim_node's
    `world:=random_each_episode` does the same, with `redraw_start_heading`.

    `max_episode_steps` > 0 ends an episode that survives that long (a time limit, learnt from as
    a cut, not a crash: Training.add_truncated) so that training keeps meeting new layouts and
    starts once the policy has learnt to survive.

    `world_every` = K >= 2, with `layout_per_episode`, flies `world` as every K-th episode between
    the layouts (an extension: the paper trains in Basic only, round 6 on layouts only).
    `partitions`, with `layout_per_episode`, trains on layouts where half of the boxes are 2-3 m
    partitions (world.procedural_world; an extension, round 17).

    `random_start_fraction` > 0 starts that share of episodes at a random free place and heading
    in the room (SimConfig.random_start_fraction) instead of the layout's start pose.

    `reward_window_fraction` sizes the reward's central window (SimConfig; the paper's 0.2). A
    camera whose window sees the floor nearer than delta is refused (RewardWindowError) before
    anything is written: every step would be punished and the run could only learn to crash.

    `save_weights_at` lists env steps at which the online network is also written to
    policy_<model>_step<N>.safetensors (snapshots along one run, e.g. to measure longer training
    without retraining the shorter budget: the first N steps of a longer run are the N-step run).

    `act_on_pushes` = N > 0 acts on a copy of the network taken every N updates, as policy_node acts on
    the ROS trainer's pushes (PushedActing; an experiment, round 41); 0 acts on the newest network.
    """
    snapshots = frozenset(int(n) for n in save_weights_at)
    if world_every and not layout_per_episode:
        raise ValueError("world_every mixes the world into the layouts: it needs layout_per_episode")
    if partitions and not layout_per_episode:
        raise ValueError("partitions changes the training layouts: it needs layout_per_episode")
    if any(n < 1 or n > cfg.total_steps for n in snapshots):
        raise ValueError(f"save_weights_at must lie in [1, total_steps={cfg.total_steps}], got {sorted(snapshots)}")
    sim_cfg = SimConfig(
        seed=cfg.seed,
        start_yaw_jitter_deg=start_yaw_jitter_deg,
        hfov_deg=hfov_deg,
        max_episode_steps=max_episode_steps,
        random_start_fraction=random_start_fraction,
        reward_window_fraction=reward_window_fraction,
        image_width=cfg.input_size_px,  # the camera renders at the network's input size
        image_height=cfg.input_size_px,
    )
    sim_cfg.validate()
    layouts = None
    if layout_per_episode:
        layouts = training_layouts(cfg.seed, load_world(world) if world_every else None, world_every, partitions)
    first = next(layouts) if layouts else load_world(world)
    floor = reward_floor_problem(sim_cfg, first.start_xyz_m[2])
    if floor:  # before anything is written: the run could only learn to crash
        raise RewardWindowError(floor)
    training = Training(cfg, run_dir, log=log, resume=resume)
    training.plan_snapshots(snapshots)
    training.camera_hfov_deg = hfov_deg  # recorded in every weights file this run writes
    paper_window = reward_window_fraction == SimConfig.reward_window_fraction
    training.reward_window_fraction = None if paper_window else reward_window_fraction  # likewise, when not the paper's
    window = "" if paper_window else f", window {reward_window_fraction:g}"
    log(f"training {cfg.model}, seed {cfg.seed}: reward {reward_description(cfg)}{window}; {replay_description(cfg)}")
    validator = validation(training) if validation is not None else None
    if layouts:
        sim = Simulator(first, sim_cfg, next_worlds=layouts, redraw_heading=redraw_heading)
    else:
        sim = Simulator(first, sim_cfg)
    agent = Agent(training.learner.online, training.net_cfg, cfg.device, seed=cfg.seed)
    pushed = PushedActing(agent, training.learner, act_on_pushes) if act_on_pushes else None
    if pushed:
        log(f"acting on a copy of the network pushed every {act_on_pushes} updates, as policy_node beside trainer_node")
    stack = FrameStack(training.net_cfg.frames)
    r = sim.observe()
    state = stack.reset(r.depth_m)
    training.add_first(r.depth_m)
    dt = sim.config.step_duration_s
    t0 = time.perf_counter()
    try:
        while not training.budget_done and not training.failed:
            action = agent.act(state, training.epsilon())[0]
            a = PAPER_ACTIONS[action]
            r = sim.step(BodyTwist(a.linear_x_mps, yaw_rate_radps=a.yaw_rate_radps(dt)))
            if r.truncated:
                training.add_truncated(r.depth_m)
            else:
                training.add_step(action, r.beta_m, r.collided, r.depth_m)
            state = stack.reset(r.depth_m) if r.collided or r.truncated else stack.push(r.depth_m)
            while training.learn_once():
                pass
            if pushed:
                pushed.after_learning()
            if validator is not None:
                validator(training)
            for path in training.save_due_snapshots():
                log(f"step {training.env_steps}: weights snapshot {path}")
            if on_step is not None and on_step(training):
                break
            if training.env_steps % log_every == 0:
                row = training.metrics_row()
                log(
                    f"step {row['env_steps']:7d}  eps {row['epsilon']:.3f}  loss {row['loss']:.4f}  "
                    f"episodes {row['episodes']:5d}  mean len {row['mean_episode_length']:7.1f}  "
                    f"mean ep reward {row['mean_episode_reward']:8.1f}  "
                    f"{training.env_steps / (time.perf_counter() - t0):6.1f} steps/s  "
                    f"{row['updates_per_s']:5.1f} updates/s"
                )
    finally:
        if random_start_fraction > 0:
            log(f"random starts: {sim.random_starts} of {sim.episode + 1} episodes")
        sim.close()
        if validator is not None:
            validator.close()
        training.save_checkpoint(final=True)
        training.close()
    return training


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", choices=("sam", "cnn"), default="sam")
    ap.add_argument("--steps", type=int, default=30000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--world", default="basic")
    ap.add_argument("--run-dir", default=None, help="default: runs/inproc_<model>_seed<seed>")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--learning-rate", type=float, default=LearnerConfig.learning_rate)
    ap.add_argument("--epsilon-decay-steps", type=int, default=TrainerConfig.epsilon_decay_steps)
    ap.add_argument("--learning-starts", type=int, default=TrainerConfig.learning_starts)
    ap.add_argument("--replay-ratio", type=float, default=TrainerConfig.replay_ratio)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument(
        "--no-save-replay",
        action="store_true",
        help="an interrupted run (Ctrl-C) does not write its replay memory (8 KiB per frame) with the final checkpoint",
    )
    ap.add_argument(
        "--layout-per-episode", action="store_true", help="experiment: a new procedural layout every episode instead of --world"
    )
    ap.add_argument(
        "--clearance-m",
        type=float,
        default=TrainerConfig.clearance_m,
        help="experiment: side-clearance penalty distance (0 = the paper's reward)",
    )
    ap.add_argument("--clearance-weight", type=float, default=TrainerConfig.clearance_weight)
    ap.add_argument(
        "--validate-every",
        type=int,
        default=0,
        help="model selection: every N env steps after the epsilon decay, fly the held-out validation layouts "
        f"({', '.join(VALIDATION_WORLDS)}) and keep the best network as policy_<model>_best.safetensors (0 = off)",
    )
    ap.add_argument(
        "--redraw-heading",
        action="store_true",
        help="experiment, with --layout-per-episode: draw a new start heading every episode (default: every "
        "layout starts at the seed's first heading draw, as for the shipped weights; redrawing trained worse)",
    )
    ap.add_argument(
        "--max-episode-steps",
        type=int,
        default=0,
        help="experiment: end an episode that survives this many steps (a time limit, not a crash) and start "
        "the next (with --layout-per-episode: in a new layout); 0 = episodes end only in crashes (the paper)",
    )
    ap.add_argument(
        "--save-weights-at",
        type=int,
        nargs="+",
        default=(),
        metavar="STEP",
        help="also write the network at these env steps to policy_<model>_step<STEP>.safetensors",
    )
    ap.add_argument(
        "--reward-window-fraction",
        type=float,
        default=SimConfig.reward_window_fraction,
        metavar="F",
        help="experiment: the reward's central window as a share of each image side (the paper's 0.2); a camera "
        "wider than 120 degrees needs a smaller one, or the floor enters it and training is refused",
    )
    ap.add_argument(
        "--random-start-fraction",
        type=float,
        default=0.0,
        metavar="F",
        help="experiment: start this share of training episodes at a random free place and heading in the room "
        "instead of the layout's start pose (0 = always the start pose, as the paper)",
    )
    ap.add_argument(
        "--world-every",
        type=int,
        default=0,
        metavar="K",
        help="experiment, with --layout-per-episode: every K-th training episode (K >= 2) flies --world instead of "
        "a new layout (0 = layouts only)",
    )
    ap.add_argument(
        "--layout-partitions",
        action="store_true",
        help="experiment, with --layout-per-episode: layouts where half of the boxes are 2-3 m partitions "
        "(random_partitions:SEED; default: plain layouts, as the shipped weights)",
    )
    ap.add_argument(
        "--act-on-pushes",
        type=int,
        default=0,
        metavar="N",
        help="experiment: act on a copy of the network taken every N updates, as policy_node acts on the ROS "
        "trainer's pushes (trainer_node's push_interval_updates, 50); 0 = the newest network (default)",
    )
    ap.add_argument("--validation-steps", type=int, default=500, help="steps per validation world")
    ap.add_argument("--hfov-deg", type=float, default=SimConfig.hfov_deg, help="experiment: camera field of view (deg)")
    ap.add_argument(
        "--input-size",
        type=int,
        default=TrainerConfig.input_size_px,
        metavar="PX",
        help="experiment: square network input and depth image size in px (84: SAM sees 10 x 10 nodes instead of 8 x 8)",
    )
    ap.add_argument(
        "--frames",
        type=int,
        default=TrainerConfig.frames,
        help="experiment: depth frames stacked into the state (the paper's 5; policy_node's frame_stack must match)",
    )
    ap.add_argument(
        "--turn-penalty",
        type=float,
        default=TrainerConfig.turn_penalty,
        help="experiment: subtract this from the reward of every turning step (0 = the paper's reward)",
    )
    ap.add_argument(
        "--n-step",
        type=int,
        default=TrainerConfig.n_step,
        metavar="N",
        help=f"experiment: learn from N-step returns, 1..{MAX_N_STEP} (1 = one-step Q-learning, as the paper)",
    )
    ap.add_argument(
        "--priority-alpha",
        type=float,
        default=TrainerConfig.priority_alpha,
        metavar="A",
        help="experiment: prioritized replay, sampling ~ |TD error|^A, 0..1 (0 = uniform, as the paper; Schaul et al. use 0.6)",
    )
    ap.add_argument(
        "--priority-beta",
        type=float,
        default=TrainerConfig.priority_beta,
        metavar="B",
        help="prioritized replay: importance-weight exponent at the start, rising linearly to 1 over --steps",
    )
    ap.add_argument(
        "--ema-decay",
        type=float,
        default=LearnerConfig.ema_decay,
        help="experiment: also keep a moving average of the weights (e.g. 0.999) as policy_<model>_ema.safetensors (0 = off)",
    )
    ap.add_argument(
        "--augment-shift",
        type=int,
        default=LearnerConfig.augment_shift_px,
        metavar="PX",
        help=f"experiment: shift each sampled state and next state by up to PX pixels, 0..{MAX_SHIFT_PX} "
        "(random-shift augmentation as DrQ; 0 = off, as the paper)",
    )
    ap.add_argument(
        "--lr-anneal",
        action="store_true",
        help="experiment: lower the learning rate linearly to 0.1x over the run's updates (default: constant, as the paper)",
    )
    ap.add_argument(
        "--sam-readout",
        choices=SAM_READOUTS,
        default=TrainerConfig.sam_readout,
        help="SAM only: max pools the nodes (the paper's design); flatten keeps every node's place (an extension)",
    )
    ap.add_argument(
        "--conv-channels",
        type=int,
        nargs="+",
        default=list(TrainerConfig.conv_channels),
        metavar="C",
        help="experiment: the conv trunk's output channels, one stride-2 layer each (both models); "
        "the default 16 32 32 gives SAM 8 x 8 nodes from 64 px, 16 32 gives 16 x 16",
    )
    sizes = ap.add_argument_group("SAM's relational module (an experiment; the defaults are the shipped SAM's)")
    sizes.add_argument("--d-model", type=int, default=TrainerConfig.d_model, help="node feature size, split over the heads")
    sizes.add_argument("--heads", type=int, default=TrainerConfig.heads, help="attention heads")
    sizes.add_argument("--relational-blocks", type=int, default=TrainerConfig.relational_blocks, help="relational blocks")
    sizes.add_argument("--mlp-hidden", type=int, default=TrainerConfig.mlp_hidden, help="width of each block's MLP")
    a = ap.parse_args()
    size_args = {name: getattr(a, name) for name in SAM_SIZES}
    if a.model == "cnn" and any(v != getattr(TrainerConfig, k) for k, v in size_args.items()):
        ap.error("--d-model, --heads, --relational-blocks and --mlp-hidden size SAM's relational module; the CNN has none")
    try:
        NetConfig(**size_args).validate()
    except ValueError as e:
        ap.error(f"SAM sizes (--d-model, --heads, --relational-blocks, --mlp-hidden): {e}")
    if any(not 1 <= n <= a.steps for n in a.save_weights_at):
        ap.error(f"--save-weights-at steps must lie in [1, --steps={a.steps}], got {a.save_weights_at}")
    if not 8 <= a.input_size <= 512:
        ap.error(f"--input-size must lie in [8, 512] px (policy_node's input_height/input_width range), got {a.input_size}")
    try:  # after --input-size's own check: its message names the right option
        NetConfig(conv_channels=tuple(a.conv_channels), height=a.input_size, width=a.input_size).validate()
    except ValueError as e:
        ap.error(f"--conv-channels: {e}")
    if not 1 <= a.frames <= MAX_FRAMES:
        ap.error(f"--frames must lie in [1, {MAX_FRAMES}] (policy_node's frame_stack range), got {a.frames}")
    if not 1 <= a.n_step <= MAX_N_STEP:
        ap.error(f"--n-step must lie in [1, {MAX_N_STEP}], got {a.n_step}")
    if not 0 <= a.augment_shift <= MAX_SHIFT_PX:
        ap.error(f"--augment-shift must lie in [0, {MAX_SHIFT_PX}] px, got {a.augment_shift}")
    if not 0.0 <= a.priority_alpha <= 1.0 or not 0.0 <= a.priority_beta <= 1.0:
        ap.error(f"--priority-alpha and --priority-beta must lie in [0, 1], got {a.priority_alpha}, {a.priority_beta}")
    if not 0.0 < a.reward_window_fraction <= 1.0:
        ap.error(f"--reward-window-fraction must lie in (0, 1], got {a.reward_window_fraction}")
    if not 0.0 <= a.random_start_fraction <= 1.0:
        ap.error(f"--random-start-fraction must lie in [0, 1], got {a.random_start_fraction}")
    if a.world_every and (a.world_every < 2 or not a.layout_per_episode):
        ap.error(f"--world-every must be 0 or >= 2, and needs --layout-per-episode, got {a.world_every}")
    if a.layout_partitions and not a.layout_per_episode:
        ap.error("--layout-partitions changes the training layouts: it needs --layout-per-episode")
    if a.act_on_pushes < 0:
        ap.error(f"--act-on-pushes must be >= 0 updates, got {a.act_on_pushes}")
    torch.set_num_threads(a.threads)
    cfg = TrainerConfig(
        model=a.model,
        seed=a.seed,
        total_steps=a.steps,
        save_replay=not a.no_save_replay,
        epsilon_decay_steps=a.epsilon_decay_steps,
        learning_starts=a.learning_starts,
        replay_ratio=a.replay_ratio,
        clearance_m=a.clearance_m,
        clearance_weight=a.clearance_weight,
        turn_penalty=a.turn_penalty,
        n_step=a.n_step,
        priority_alpha=a.priority_alpha,
        priority_beta=a.priority_beta,
        priority_beta_steps=a.steps,
        turning_actions=turning_indices(PAPER_ACTIONS),
        sam_readout=a.sam_readout,
        input_size_px=a.input_size,
        frames=a.frames,
        conv_channels=tuple(a.conv_channels),
        **size_args,
        learner=dataclasses.replace(
            LearnerConfig(),
            learning_rate=a.learning_rate,
            ema_decay=a.ema_decay,
            augment_shift_px=a.augment_shift,
            lr_anneal_updates=max(1, int((a.steps - a.learning_starts) * a.replay_ratio)) if a.lr_anneal else 0,
        ),
    )
    log = lambda s: print(s, flush=True)  # noqa: E731
    run_dir = a.run_dir or f"runs/inproc_{a.model}_seed{a.seed}"
    validation = None
    if a.validate_every:
        validation = lambda t: Validation(  # noqa: E731
            t,
            a.validate_every,
            steps=a.validation_steps,
            log=log,
            hfov_deg=a.hfov_deg,
            reward_window_fraction=a.reward_window_fraction,
        )
    try:
        t = run(
            cfg,
            run_dir,
            a.world,
            resume=a.resume,
            log=log,
            layout_per_episode=a.layout_per_episode,
            validation=validation,
            hfov_deg=a.hfov_deg,
            redraw_heading=a.redraw_heading,
            max_episode_steps=a.max_episode_steps,
            save_weights_at=a.save_weights_at,
            random_start_fraction=a.random_start_fraction,
            reward_window_fraction=a.reward_window_fraction,
            world_every=a.world_every,
            partitions=a.layout_partitions,
            act_on_pushes=a.act_on_pushes,
        )
    except RewardWindowError as e:
        ap.error(f"--hfov-deg / --reward-window-fraction: {e}")
    print(f"weights: {t.policy_weights_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
