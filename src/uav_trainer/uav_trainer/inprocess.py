"""Training without ROS: the same recipe, simulator, networks, replay, learner and run directory as
`train`, in one synchronous loop (act one step, then learn what replay_ratio allows).

Bit-for-bit the run `train` makes over ROS for the same recipe and seed (on the same machine), with no
node start-up: for benchmarks and quick experiments. Example:

    python -m uav_trainer.inprocess --model sam --steps 30000 --seed 0 --run-dir runs/inproc_sam_seed0
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np
import torch

from uav_common.actions import PAPER_ACTIONS, turning_indices
from uav_common.settings import SettingError, add_flags, build, given_flags, refuse_retired_flags, specs
from uav_policy import weights as wio
from uav_policy.agent import Agent
from uav_policy.networks import build_network
from uav_policy.rollout import Flight
from uav_sim.planner import PlannerConfig, SimPlanner
from uav_sim.reward import CENTER_WINDOW_FRACTION
from uav_sim.simulator import RewardWindowError, SimConfig, Simulator, reward_floor_problem, with_sensor
from uav_sim.stacked_sim import StackedSim
from uav_sim.world import WorldChoice, WorldError

from .recipes import DEFAULT_RECIPE, RecipeError, load_recipe, parse_assignments
from .teacher import NO_LABEL, reason_shares
from .training import RunDirError, Training
from .training_config import TrainerConfig, reward_description

_TRIED = "an experiment that did not help (docs/RESULTS.md, 'What was tried')"
# The in-process trainer's flags that were retired, and what replaces them.
RETIRED_FLAGS = {
    "--layout-per-episode": "use --sim-arg world:=random_each_episode (the shipped recipe's)",
    "--world-every": "use --sim-arg mix_world_every:=K (the shipped recipe's is 4, with mix_world basic)",
    "--hfov-deg": "use --sim-arg hfov_deg:=DEG",
    "--reward-window-fraction": "use --sim-arg reward_window_fraction:=F",
    "--max-episode-steps": "use --sim-arg max_episode_steps:=N",
    "--save-weights-at": "use --snapshots N (one every thirtieth of the budget)",
    "--input-size": "use --input-size-px",
    "--frames": "use --frame-stack",
    **{
        flag: _TRIED
        for flag in ("--random-start-fraction", "--redraw-heading", "--layout-partitions", "--act-on-pushes")
        + ("--validate-every", "--validation-steps", "--clearance-m", "--clearance-weight", "--n-step", "--priority-alpha")
        + ("--priority-beta", "--ema-decay", "--lr-anneal", "--attention-entropy-weight", "--feature-norm")
        + ("--no-feature-norm", "--augment-shift-px", "--consistency-weight")
        + ("--sam-positions",)
    },
}

# sim_node parameters the in-process loop does not model (ROS plumbing); a recipe may set them.
ROS_ONLY_SIM = frozenset({"mode", "watchdog_timeout_s", "lockstep_republish_s", "wait_for_subscribers"})
ROS_ONLY_SIM |= {"camera_frame_id", "odom_frame_id", "base_frame_id"}


def sim_settings(values: dict, seed: int, input_size_px: int) -> tuple[SimConfig, WorldChoice]:
    """The simulator and world a recipe's sim_node section describes, rendering at the network's input size.
    SettingError names a parameter that cannot be used."""
    world_names = {s.name for s in specs(WorldChoice)}
    world = build(WorldChoice, {k: v for k, v in values.items() if k in world_names})
    rest = {k: v for k, v in values.items() if k not in world_names and k not in ROS_ONLY_SIM}
    sim = build(SimConfig, rest)
    return dataclasses.replace(sim, seed=seed, image_width=input_size_px, image_height=input_size_px), world


def run(
    cfg: TrainerConfig,
    run_dir: str,
    sim_cfg: SimConfig,
    worlds: WorldChoice = WorldChoice(),
    log_every: int = 1000,
    log=print,
    resume: bool = False,
    on_step=None,
) -> Training:
    """Train until the budget; `on_step(training)` may return True to stop early.

    A camera whose reward window sees the floor nearer than delta is refused (RewardWindowError) before
    anything is written: every step would be punished and the run could only learn to crash."""
    sim_cfg.validate()
    sim_cfg = with_sensor(sim_cfg)  # a preset's camera: its field of view is the one the weights record
    first, layouts = worlds.load(cfg.seed)
    floor = reward_floor_problem(sim_cfg, first.start_xyz_m[2])
    if floor:
        raise RewardWindowError(floor)
    training = Training(cfg, run_dir, log=log, resume=resume)
    training.camera_hfov_deg = sim_cfg.hfov_deg  # recorded in every weights file this run writes
    paper_window = sim_cfg.reward_window_fraction == CENTER_WINDOW_FRACTION
    training.reward_window_fraction = None if paper_window else sim_cfg.reward_window_fraction
    teaching = f", teacher: the planner ({cfg.teacher})" if cfg.teacher != "none" else ""
    window = sim_cfg.reward_window_fraction
    log(f"training {cfg.model}, seed {cfg.seed}: reward {reward_description(cfg)}, window {window:g}{teaching}")
    sim = Simulator(first, sim_cfg, next_worlds=layouts)
    # The policy's own network, answering each frame with the weights its release carries (as over ROS).
    acting = Agent(build_network(training.net_cfg, seed=cfg.seed), training.net_cfg, str(training.learner.device), seed=cfg.seed)
    net_cfg = training.net_cfg
    flight = Flight(StackedSim(sim, net_cfg.frames, input_hw=(net_cfg.height, net_cfg.width), map_grid=net_cfg.map_grid), acting)
    training.add_first(flight.env.last_input, grid=flight.env.last_grid)
    loaded = None  # the version of the released weights the acting network has
    # The teacher labels every frame; it flies a step instead of the student with a probability that falls to 0.
    teacher = (
        SimPlanner(sim, PlannerConfig(knowledge=cfg.teacher, memory_frames=net_cfg.frames)) if cfg.teacher != "none" else None
    )
    label, agreed = NO_LABEL, []  # the teacher's action for the frame decided on; whether the student's greedy choice was it
    reason = None  # with attention_weight: the share of each attention cell the teacher's reason covers in that frame

    def decide():
        nonlocal loaded, label, reason
        version, blob = training.released_weights()
        if version != loaded:
            wio.load_bytes(blob, training.net_cfg, into=acting.net)
            loaded = version
        plan = teacher.label() if teacher is not None else None
        label = plan.action if plan is not None else NO_LABEL
        if training.reason_grid is not None:
            mask, env = teacher.reason_mask(), flight.env
            reason = reason_shares(env.input_mask(mask), training.reason_grid, env.map, net_cfg.map_grid, mask)
        decision = flight.decide(training.epsilon(), instead=training.teacher_flies(label))
        training.after_release()
        if teacher is not None:
            agreed.append(int(np.argmax(decision.q)) == label)
        return decision

    t0 = time.perf_counter()
    try:
        decision = decide()
        while not training.budget_done and not training.failed:
            step = flight.execute(decision)
            r = step.after
            frame, grid = flight.env.last_input, flight.env.last_grid  # on the network's input, as policy_node gives it
            if r.truncated:
                training.add_truncated(frame, grid=grid)
            else:
                training.add_step(step.action, r.beta_m, r.collided, frame, teacher=label, reason=reason, grid=grid)
            if not training.budget_done:
                # The policy acts on the new frame before this step's updates, as over ROS, where trainer_node
                # releases the frame first and learns while the policy acts and the simulator steps.
                decision = decide()
            for path in training.learn_due():
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
                    + (f"  student picks the teacher's action {100 * np.mean(agreed):3.0f} %" if agreed else "")
                )
                agreed.clear()
    finally:
        sim.close()
        training.save_checkpoint(final=True)
        training.close()
    return training


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recipe", default=DEFAULT_RECIPE, help=f"recipe name or file (default: {DEFAULT_RECIPE}), as train")
    ap.add_argument("--params-dir", default="params", help="folder with recipes/ (default: params)")
    ap.add_argument("--steps", type=int, default=30000, help="environment steps budget (default: 30000)")
    ap.add_argument("--run-dir", default=None, help="default: runs/inproc_<model>_seed<seed>")
    ap.add_argument(
        "--threads", type=int, default=1, help="torch threads (default: 1, trainer_node's torch_threads: the run equals train's)"
    )
    ap.add_argument("--resume", action="store_true", help="resume from the run directory's latest checkpoint")
    ap.add_argument("--world", default=None, help="training world (default: the recipe's)")
    ap.add_argument(
        "--sim-arg", action="append", default=[], metavar="NAME:=VALUE", help="a sim_node parameter over the recipe's"
    )
    add_flags(ap, TrainerConfig, skip=("total_steps",), title="trainer_node parameters (over the recipe; --steps is the budget)")
    refuse_retired_flags(ap, sys.argv[1:] if argv is None else argv, RETIRED_FLAGS)
    a = ap.parse_args(argv)
    if a.steps <= 0:
        ap.error("--steps must be positive")
    try:
        recipe = load_recipe(a.recipe, a.params_dir)
        sim_values = {**recipe.node("sim_node"), **parse_assignments(a.sim_arg)}
        if a.world:
            sim_values["world"] = a.world
        values = {**recipe.node("trainer_node"), **given_flags(a), "total_steps": a.steps}
        cfg = build(TrainerConfig, values)
        cfg = dataclasses.replace(cfg, turning_actions=turning_indices(PAPER_ACTIONS))
        cfg.validate()
        sim_cfg, worlds = sim_settings(sim_values, cfg.seed, cfg.input_size_px)
    except (RecipeError, SettingError, ValueError) as e:
        ap.error(str(e))
    torch.set_num_threads(a.threads)
    log = lambda s: print(s, flush=True)  # noqa: E731
    log(f"recipe {recipe.path}: {recipe.summary()}")
    try:
        t = run(cfg, a.run_dir or f"runs/inproc_{cfg.model}_seed{cfg.seed}", sim_cfg, worlds, log=log, resume=a.resume)
    except (RewardWindowError, WorldError) as e:
        ap.error(f"sim_node parameters: {e}")
    except RunDirError as e:
        ap.error(str(e))
    report = t.unwritten_report()
    if report or not t.policy_weights_path.is_file():
        print(report or f"no weights written in {t.policy_weights_path.parent} (see the log above)", file=sys.stderr)
        return 1
    print(f"weights: {t.policy_weights_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
