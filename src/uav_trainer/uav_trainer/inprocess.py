"""Training without ROS: the same simulator, networks, replay and learner in one synchronous loop.

Bit-for-bit reproducible for a seed (acting and learning alternate deterministically), so it
is what the benchmarks and hyperparameter searches use; the ROS trainer runs the same pieces
concurrently. Run: python -m uav_trainer.inprocess --model sam --steps 20000
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import torch

from uav_policy.actions import PAPER_ACTIONS
from uav_policy.agent import Agent
from uav_policy.frame_stack import FrameStack
from uav_policy.networks import NetConfig
from uav_sim.reward import step_reward
from uav_sim.simulator import SimConfig, Simulator
from uav_sim.vehicle import BodyTwist
from uav_sim.world import load_world

from .episodes import EpisodeStats
from .learner import Learner, LearnerConfig, linear_epsilon
from .replay import ReplayMemory


@dataclasses.dataclass(frozen=True)
class RunConfig:
    model: str = "sam"
    world: str = "basic"
    steps: int = 20000
    seed: int = 0
    learning_starts: int = 1000
    train_every: int = 4  # env steps per gradient update
    epsilon_start: float = 1.0
    epsilon_end: float = 0.05
    epsilon_decay_steps: int = 10000
    replay_capacity: int = 50000
    start_yaw_jitter_deg: float = 180.0


def run(rc: RunConfig, lc: LearnerConfig, on_log=None, log_every: int = 1000):
    torch.manual_seed(rc.seed)
    net_cfg = NetConfig(model=rc.model)
    sim = Simulator(load_world(rc.world), SimConfig(seed=rc.seed, start_yaw_jitter_deg=rc.start_yaw_jitter_deg))
    learner = Learner(net_cfg, dataclasses.replace(lc, seed=rc.seed))
    agent = Agent(learner.online, net_cfg, seed=rc.seed)
    mem = ReplayMemory(rc.replay_capacity, (net_cfg.height, net_cfg.width), net_cfg.frames, seed=rc.seed)
    stats = EpisodeStats()
    stack = FrameStack(net_cfg.frames)
    r = sim.observe()
    state = stack.reset(r.depth_m)
    mem.add_first(r.depth_m)
    t0, loss = time.perf_counter(), float("nan")
    for step in range(1, rc.steps + 1):
        eps = linear_epsilon(step, rc.epsilon_start, rc.epsilon_end, rc.epsilon_decay_steps)
        action = agent.act(state, eps)[0]
        a = PAPER_ACTIONS[action]
        r = sim.step(BodyTwist(a.linear_x_mps, yaw_rate_radps=a.yaw_rate_radps(sim.config.step_duration_s)))
        reward = step_reward(r.beta_m, r.collided)
        mem.add_transition(action, reward, r.collided, r.depth_m)
        stats.step(reward, r.collided, step)
        state = stack.reset(r.depth_m) if r.collided else stack.push(r.depth_m)
        if step >= rc.learning_starts and step % rc.train_every == 0:
            loss = learner.update(mem.sample(lc.batch_size))["loss"]
        if on_log and step % log_every == 0:
            on_log(step, eps, loss, stats, time.perf_counter() - t0, learner.updates)
    sim.close()
    return learner, stats


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    for f in dataclasses.fields(RunConfig):
        ap.add_argument(f"--{f.name.replace('_', '-')}", type=type(f.default), default=f.default)
    ap.add_argument("--lr", type=float, default=LearnerConfig.learning_rate)
    ap.add_argument("--save", default="", help="write the final online weights here (safetensors)")
    a = ap.parse_args()
    torch.set_num_threads(2)
    rc = RunConfig(**{f.name: getattr(a, f.name) for f in dataclasses.fields(RunConfig)})

    def log(step, eps, loss, stats, wall, updates):
        print(
            f"step {step:7d}  eps {eps:.3f}  loss {loss:.4f}  episodes {stats.episodes:5d}  "
            f"mean len {stats.mean_length():7.1f}  mean ep reward {stats.mean_reward():8.1f}  "
            f"{step / wall:6.1f} steps/s  {updates / wall:5.1f} updates/s",
            flush=True,
        )

    learner, _ = run(rc, LearnerConfig(learning_rate=a.lr), on_log=log)
    if a.save:
        from uav_policy.weights import save_file

        save_file(learner.online, learner.net_cfg, a.save)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
