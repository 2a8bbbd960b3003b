"""evaluate: fly a policy exploit-only through the ROS nodes and measure the paper's test metrics.

    ros2 run uav_trainer evaluate --model sam --weights runs/sam_seed0/policy_sam.safetensors \
        --worlds basic complex turbulent --steps 1000

For each (model, weights, world) it starts sim_node and policy_node (epsilon 0 unless --epsilon),
counts crashes, mean reward per step (uav_sim.reward) and distance flown between crashes over
`--steps` lockstep steps, and writes Markdown and CSV tables (mean and 95% CI over the weight
files given, i.e. over training seeds) beside the paper's numbers.

The paper's protocol restarts every episode at the world's start pose. The simulator and an
epsilon-0 policy are deterministic, so after a crash the same flight repeats and one failure is
counted again every lap. `--start-yaw-jitter-deg 180 --repeats 5` measures over varied start
headings instead (seeded: sim seeds --seed .. --seed+repeats-1, steps summed per weight file).

`--inprocess` measures the same thing without ROS (same simulator, stack and network in one
process; several times faster), for screening many weight files; the tables say which was used.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import os
import time
from pathlib import Path

import numpy as np

from uav_common import contract
from uav_sim.reward import CENTER_WINDOW_FRACTION, step_reward

from .launching import Processes, params_args

PAPER = {  # Table 1 crashes / Table 2 mean reward, per 1000 test steps
    ("sam", "basic"): (0, 2.406),
    ("sam", "complex"): (1, 2.16),
    ("sam", "turbulent"): (1, -7.809),
    ("cnn", "basic"): (8, 2.459),
    ("cnn", "complex"): (5, 2.319),
    ("cnn", "turbulent"): (10, -7.83),
}


@dataclasses.dataclass
class EvalResult:
    model: str
    world: str
    weights: str
    steps: int
    crashes: int
    mean_reward: float
    distance_m: float
    crash_sites: int = -1  # distinct places (0.1 m grid) where a crashing step began, per run, summed; -1 unknown
    turn_steps: int = -1  # steps that changed the heading by more than TURN_DEG (-1 unknown)
    cells: int = -1  # distinct 1 m x 1 m floor cells flown through, per run, summed (-1 unknown)

    @property
    def distance_between_crashes_m(self) -> float:
        return self.distance_m / self.crashes if self.crashes else math.inf


# One row per crash in crashes.csv (--crash-log): where the crashing step began (pose before it), how
# many steps the episode had flown, the heading the episode started at, and the action taken.
CRASH_FIELDS = (
    "model",
    "world",
    "weights",
    "sim_seed",
    "step",
    "episode_step",
    "x_m",
    "y_m",
    "yaw_deg",
    "start_yaw_deg",
    "action",
)


def crash_site(xy) -> tuple[float, float]:
    """Where a crashing step began, on a 0.1 m grid: a deterministic policy restarted at the same
    pose crashes at the same site again, so crashes / sites tells repeats from new failures."""
    return (round(xy[0], 1), round(xy[1], 1))


TURN_DEG = 15.0  # the paper's turning actions yaw 30 degrees per step, the straight ones 0


class Behaviour:
    """How a policy flies, beside how often it crashes: the share of steps spent turning, and how
    much of the room it covers (distinct 1 m cells). A policy that circles on the spot can crash
    rarely while covering almost nothing; these numbers make that visible."""

    def __init__(self, x: float, y: float, yaw_rad: float):
        self.turn_steps = 0
        self.cells = {(math.floor(x), math.floor(y))}
        self.yaw = yaw_rad

    def step(self, x: float, y: float, yaw_rad: float, collided: bool) -> None:
        """After every step; after a collision the pose is the next episode's start."""
        if not collided:
            turn = (yaw_rad - self.yaw + math.pi) % (2 * math.pi) - math.pi
            self.turn_steps += abs(math.degrees(turn)) > TURN_DEG
        self.cells.add((math.floor(x), math.floor(y)))
        self.yaw = yaw_rad


def quaternion_yaw(q) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


class StepMonitor:
    """Counts steps, crashes, reward and distance from step_outcome and odom (joined by stamp)."""

    def __init__(self, steps: int):
        self.target = steps
        self.joiner = contract.StampJoiner(("outcome", "odom"), max_pending=1000)
        self.first = True
        self.steps = self.crashes = 0
        self.sites: set[tuple[float, float]] = set()
        self.reward = 0.0
        self.distance = 0.0
        self.last_xy = None
        self.last_stamp = self.step_ns = None
        self.gaps = 0  # steps whose stamp is not one step after the previous one: messages were lost
        self.behaviour: Behaviour | None = None

    def add(self, stream: str, msg) -> None:
        stamp = contract.stamp_ns(msg.header.stamp)
        j = self.joiner.add(stream, stamp, msg)
        if j is None or self.done:
            return
        p = j["odom"].pose.pose.position
        xy = (p.x, p.y)
        yaw = quaternion_yaw(j["odom"].pose.pose.orientation)
        if self.first:  # the frame before any command: not a step
            self.first, self.last_xy, self.last_stamp = False, xy, stamp
            self.behaviour = Behaviour(p.x, p.y, yaw)
            return
        delta = stamp - self.last_stamp
        self.step_ns = delta if self.step_ns is None else self.step_ns
        self.gaps += delta != self.step_ns
        self.last_stamp = stamp
        out = j["outcome"]
        collided, truncated = contract.outcome_collided(out), contract.outcome_truncated(out)
        if not truncated:  # a time limit's step has no outcome (evaluation sets none)
            beta = 0.0 if collided else min(max(float(out.range), 0.0), float(out.max_range))
            self.reward += step_reward(beta, collided)
        self.steps += 1
        if collided:
            self.crashes += 1  # the vehicle is back at the start: no distance for this jump
            self.sites.add(crash_site(self.last_xy))
        elif not truncated:
            self.distance += math.hypot(xy[0] - self.last_xy[0], xy[1] - self.last_xy[1])
        self.behaviour.step(p.x, p.y, yaw, collided or truncated)
        self.last_xy = xy

    @property
    def done(self) -> bool:
        return self.steps >= self.target


ENSEMBLE_SEP = "+"  # joins an ensemble's weights files in the weights column


def architecture_args(model: str, weights: str) -> list[str]:
    """policy_node parameters for a weights file whose SAM readout, input size or frame stack is not the default."""
    from uav_policy import weights as wio
    from uav_policy.networks import NetConfig

    cfg = wio.config_for(model, weights)
    args = [f"sam_readout:={cfg.sam_readout}"] if cfg.sam_readout != NetConfig.sam_readout else []
    if (cfg.height, cfg.width) != (NetConfig.height, NetConfig.width):
        args += [f"input_height:={cfg.height}", f"input_width:={cfg.width}"]
    if cfg.frames != NetConfig.frames:
        args.append(f"frame_stack:={cfg.frames}")
    return args


def image_size_args(model: str, weights: str, sim_args) -> list[str]:
    """sim_node parameters that render at the input size of `weights`, unless `sim_args` set a size."""
    from uav_policy import weights as wio

    if not weights or any(a.partition(":=")[0] in ("image_width", "image_height") for a in sim_args):
        return []
    cfg = wio.config_for(model, weights)
    return [f"image_width:={cfg.width}", f"image_height:={cfg.height}"]


def weights_or_packaged(model: str, weights: str) -> list[str]:
    """The files a policy flies: `weights` (one file, or an ensemble's joined by ENSEMBLE_SEP), or
    without them the packaged files policy_node loads by default ([] when there are none)."""
    from uav_policy import weights as wio

    return weights.split(ENSEMBLE_SEP) if weights else [str(p) for p in wio.packaged_weights(model)]


def flown_hfov_deg(model: str, weights: str) -> float:
    """The camera field of view weights fly with when no hfov_deg is given: the one the weights file (or,
    without one, the packaged files policy_node loads) was trained with, else SimConfig's default."""
    from uav_policy import weights as wio

    return wio.camera_for(next(iter(weights_or_packaged(model, weights)), None), wio.UNRECORDED_HFOV_DEG)


def flown_window(model: str, weights: str) -> float:
    """The reward window weights are measured with when none is given: the one the weights file (or the
    packaged files) records, else the paper's (SimConfig's default, which sim_node's need not be)."""
    from uav_policy import weights as wio

    return wio.window_for(next(iter(weights_or_packaged(model, weights)), None), CENTER_WINDOW_FRACTION)


def sim_arg_number(sim_args, wanted: str) -> float | None:
    """The value of `wanted` among sim_node arguments NAME:=VALUE, if one is given (ValueError if not a number)."""
    for arg in sim_args:
        name, _, value = arg.partition(":=")
        if name == wanted:
            try:
                return float(value)
            except ValueError:
                raise ValueError(f"sim_node argument {arg!r}: {wanted} must be a number") from None
    return None


def sim_arg_hfov_deg(sim_args) -> float | None:
    """The hfov_deg among sim_node arguments NAME:=VALUE, if one is given (ValueError if not a number)."""
    return sim_arg_number(sim_args, "hfov_deg")


def weights_label(files: list[str]) -> str:
    """How progress lines name a policy: its file, "packaged", or an ensemble's size, first and last file
    (the weights column of results.csv keeps every file)."""
    if len(files) > 1:
        return f"ensemble of {len(files)} ({files[0]} ... {files[-1]})"
    return files[0] if files else "packaged"


INPROCESS_SIM_ARGS = ("hfov_deg", "reward_window_fraction")  # the sim_node parameters --inprocess honours


def evaluate_once(
    model: str,
    weights: str,
    world: str,
    steps: int,
    epsilon: float = 0.0,
    seed: int = 0,
    params_dir: Path | None = None,
    timeout_s: float = 600.0,
    start_yaw_jitter_deg: float = 0.0,
    sim_args: tuple[str, ...] = (),
    log_dir: Path | None = None,
    progress=None,
) -> EvalResult:
    """Run sim_node + policy_node (installed executables) and measure `steps` lockstep steps.

    Without hfov_deg in `sim_args` the simulator gets the camera the weights were trained with, without
    reward_window_fraction the reward window they record (else the paper's), and without image_width/image_height
    it renders at their input size. `weights` may be an ensemble's files joined by ENSEMBLE_SEP (which
    must share architecture, camera and reward window: load_policy checks): policy_node gets the list."""
    files = weights.split(ENSEMBLE_SEP) if weights else []
    first = files[0] if files else ""
    if sim_arg_hfov_deg(sim_args) is None:
        sim_args = (*sim_args, f"hfov_deg:={flown_hfov_deg(model, first)}")
    if sim_arg_number(sim_args, "reward_window_fraction") is None:
        sim_args = (*sim_args, f"reward_window_fraction:={flown_window(model, first)}")
    sim_args = (*sim_args, *image_size_args(model, first, sim_args))
    import rclpy
    import rclpy.executors
    from nav_msgs.msg import Odometry
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Range

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("evaluate_monitor", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    mon = StepMonitor(steps)
    deep = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=10000)
    node.create_subscription(Range, contract.OUTCOME_TOPIC, lambda m: mon.add("outcome", m), deep)
    node.create_subscription(Odometry, contract.ODOM_TOPIC, lambda m: mon.add("odom", m), deep)
    procs = Processes(log_dir=log_dir, quiet=log_dir is None)
    pargs = lambda kv: [x for item in kv for x in ("-p", item)]  # noqa: E731
    try:
        # The lockstep sim only advances once the policy answers, and it says its first frame again
        # every lockstep_republish_s: the policy starts once the monitor has that frame, so no step
        # can go by before the monitor hears the simulator.
        sim = procs.start(
            "sim",
            "uav_sim",
            "sim_node",
            params_args(params_dir, "sim")
            + pargs([f"world:={world}", f"seed:={seed}", f"start_yaw_jitter_deg:={float(start_yaw_jitter_deg)}", *sim_args]),
        )
        ready_by = time.monotonic() + 60.0
        while mon.first:
            executor.spin_once(timeout_sec=0.05)
            if sim.poll() is not None:
                raise RuntimeError(f"sim_node exited with code {sim.returncode} before its first frame")
            if time.monotonic() > ready_by:
                raise TimeoutError("no first frame from sim_node within 60 s")
        wargs = [f"weights:={','.join(files)}", *architecture_args(model, first)] if files else []
        procs.start(
            "policy",
            "uav_policy",
            "policy_node",
            params_args(params_dir, "policy")
            + pargs([f"model:={model}", f"epsilon:={epsilon}", f"seed:={seed}", "publish_overlay:=false", *wargs]),
        )
        end = time.monotonic() + timeout_s
        last = 0
        while not mon.done:
            executor.spin_once(timeout_sec=0.05)
            if progress and mon.steps != last:
                progress(mon.steps - last)
                last = mon.steps
            for name, p in procs.procs.items():
                if p.poll() is not None:
                    raise RuntimeError(f"{name}_node exited with code {p.returncode} during evaluation")
            if time.monotonic() > end:
                raise TimeoutError(f"evaluation reached only {mon.steps}/{steps} steps in {timeout_s} s")
        if mon.gaps:
            raise RuntimeError(f"the monitor missed messages ({mon.gaps} steps out of sequence): the measurement is void")
    finally:
        procs.stop_all(["policy", "sim"])
        executor.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
    b = mon.behaviour
    return EvalResult(
        model,
        world,
        weights,
        mon.steps,
        mon.crashes,
        mon.reward / max(mon.steps, 1),
        mon.distance,
        len(mon.sites),
        b.turn_steps if b else -1,
        len(b.cells) if b else -1,
    )


def evaluate_inprocess(
    model: str,
    weights: str,
    world: str,
    steps: int,
    seed: int = 0,
    net=None,
    start_yaw_jitter_deg: float = 0.0,
    hfov_deg: float | None = None,
    net_cfg=None,
    crash_log: list | None = None,
    reward_window_fraction: float | None = None,
) -> EvalResult:
    """The same measurement without ROS (same simulator, stack and network): for benchmarks and checks.

    `weights`: a file, or an ensemble's files joined by ENSEMBLE_SEP, or "" for the packaged files.
    hfov_deg None: the camera the weights were trained with (with `net` and no file: the sim default).
    `net_cfg`: `net`'s architecture (default: the weights file's, else the model's default); the
    camera renders at its input size. `crash_log`, when a list, gets one dict per crash (CRASH_FIELDS).
    `reward_window_fraction` None: the window the weights file records, else the paper's (SimConfig's default)."""
    from uav_policy import weights as wio
    from uav_policy.agent import Agent
    from uav_sim.simulator import SimConfig, Simulator
    from uav_sim.world import load_world

    from .rollout import Flight

    if net is None:
        files = weights_or_packaged(model, weights)
        if not files:
            raise FileNotFoundError(f"no weights given and no packaged {model} weights")
        net, net_cfg, hfov_deg, reward_window_fraction = load_policy(model, files, hfov_deg, reward_window_fraction)
    cfg = net_cfg if net_cfg is not None else wio.config_for(model, weights)
    if hfov_deg is None:  # `net` given without its camera: the weights file's, else the sim default
        hfov_deg = wio.camera_for(weights, wio.UNRECORDED_HFOV_DEG)
    if reward_window_fraction is None:
        reward_window_fraction = wio.window_for(weights, CENTER_WINDOW_FRACTION)
    agent = Agent(net, cfg, seed=seed)
    sim_cfg = SimConfig(
        seed=seed,
        start_yaw_jitter_deg=start_yaw_jitter_deg,
        hfov_deg=hfov_deg,
        image_width=cfg.width,
        image_height=cfg.height,
        reward_window_fraction=reward_window_fraction,
    )
    sim = Simulator(load_world(world), sim_cfg)
    flight = Flight(sim, agent, cfg.frames)
    r = flight.last
    crashes, reward, dist, sites = 0, 0.0, 0.0, set()
    behaviour = Behaviour(r.pose.x_m, r.pose.y_m, r.pose.yaw_rad)
    start_yaw = r.pose.yaw_rad  # the episode's start heading
    try:
        for step in range(1, steps + 1):
            episode_step = sim.step_in_episode + 1  # the simulator's count, before it restarts on a crash
            s = flight.step(0.0)
            before, r = s.before.pose, s.after
            reward += r.reward
            if r.collided:
                crashes += 1
                sites.add(crash_site((before.x_m, before.y_m)))
                if crash_log is not None:
                    crash_log.append(
                        dict(
                            model=model,
                            world=world,
                            weights=weights,
                            sim_seed=seed,
                            step=step,
                            episode_step=episode_step,
                            x_m=round(before.x_m, 3),
                            y_m=round(before.y_m, 3),
                            yaw_deg=round(math.degrees(before.yaw_rad), 1),
                            start_yaw_deg=round(math.degrees(start_yaw), 1),
                            action=flight.actions[s.action].name,
                        )
                    )
                start_yaw = r.pose.yaw_rad
            else:
                dist += math.hypot(r.pose.x_m - before.x_m, r.pose.y_m - before.y_m)
            behaviour.step(r.pose.x_m, r.pose.y_m, r.pose.yaw_rad, r.collided)
    finally:
        sim.close()
    return EvalResult(
        model, world, weights, steps, crashes, reward / steps, dist, len(sites), behaviour.turn_steps, len(behaviour.cells)
    )


def load_policy(model: str, files: list[str], hfov_deg: float | None, window: float | None = None):
    """(the network, or for several files a QEnsemble on their mean Q-values; its NetConfig; the
    camera to fly with; the reward window) for weights files of one architecture. Without hfov_deg
    the members' trained camera and without `window` their reward window, each of which must then
    be the same for all (ValueError if not)."""
    from uav_policy import weights as wio

    net = wio.load_files(files, model)
    if hfov_deg is None:
        cameras = {wio.camera_for(f, wio.UNRECORDED_HFOV_DEG) for f in files}
        if len(cameras) != 1:
            raise ValueError(f"members were trained with different cameras {sorted(cameras)}: give --sim-arg hfov_deg:=X")
        hfov_deg = cameras.pop()
    if window is None:
        windows = {wio.window_for(f, CENTER_WINDOW_FRACTION) for f in files}
        if len(windows) != 1:
            raise ValueError(
                f"members were trained with different reward windows {sorted(windows)}: give --sim-arg reward_window_fraction:=F"
            )
        window = windows.pop()
    return net, net.cfg, hfov_deg, window


def pool(runs: list[EvalResult]) -> EvalResult:
    """Several evaluations of one weight file in one world as one (steps, crashes and distance summed)."""
    first = runs[0]
    steps = sum(r.steps for r in runs)
    reward = sum(r.mean_reward * r.steps for r in runs) / steps
    return EvalResult(
        first.model,
        first.world,
        first.weights,
        steps,
        sum(r.crashes for r in runs),
        reward,
        sum(r.distance_m for r in runs),
        *(
            sum(getattr(r, k) for r in runs) if all(getattr(r, k) >= 0 for r in runs) else -1
            for k in ("crash_sites", "turn_steps", "cells")
        ),
    )


# Two-sided 95% Student t quantiles by sample size n (n - 1 degrees of freedom); normal beyond 30.
T975 = {
    2: 12.706,
    3: 4.303,
    4: 3.182,
    5: 2.776,
    6: 2.571,
    7: 2.447,
    8: 2.365,
    9: 2.306,
    10: 2.262,
    11: 2.228,
    12: 2.201,
    13: 2.179,
    14: 2.160,
    15: 2.145,
    16: 2.131,
    17: 2.120,
    18: 2.110,
    19: 2.101,
    20: 2.093,
    21: 2.086,
    22: 2.080,
    23: 2.074,
    24: 2.069,
    25: 2.064,
    26: 2.060,
    27: 2.056,
    28: 2.052,
    29: 2.048,
    30: 2.045,
}


def mean_ci95(values) -> tuple[float, float]:
    """Mean and half-width of a 95% t confidence interval (nan for n < 2)."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return math.nan, math.nan
    if v.size < 2:
        return float(v.mean()), math.nan
    t = T975.get(v.size, 1.96)
    return float(v.mean()), float(t * v.std(ddof=1) / math.sqrt(v.size))


def fmt(mean: float, hw: float, digits: int = 2) -> str:
    if math.isinf(mean):
        return "no crash"
    return f"{mean:.{digits}f}" + ("" if math.isnan(hw) else f" ± {hw:.{digits}f}")


def distance_cell(runs: list[EvalResult]) -> str:
    dist, crashes = sum(r.distance_m for r in runs), sum(r.crashes for r in runs)
    free = sum(1 for r in runs if r.crashes == 0)
    head = f"{dist / crashes:.0f}" if crashes else f"no crash in {dist:.0f} m"
    return f"{head} ({free}/{len(runs)} runs crash-free)"


def pooled_table(results, models, worlds, title: str, column: str, cell, intro: str = "") -> list[str]:
    """A Markdown table with one cell per (world, model) computed from all runs of that pair."""
    lines = [f"### {title}", "", *([intro, ""] if intro else [])]
    lines += ["| world | " + " | ".join(f"D3QN-{m.upper()}{column}" for m in models) + " |", "|" + "---|" * (1 + len(models))]
    for world in worlds:
        cells = []
        for m in models:
            runs = [r for r in results if r.model == m and r.world == world]
            cells.append(cell(runs) if runs else "-")
        lines.append(f"| {world} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def write_tables(results: list[EvalResult], out_dir: Path, steps: int, protocol: str = "") -> tuple[Path, Path]:
    """results.csv (one row per run) and results.md (Tables 1-2 and distance, mean ± 95% CI over seeds)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = out_dir / "results.csv"
    with open(csv_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "model",
                "world",
                "weights",
                "steps",
                "crashes",
                "crashes_per_1000",
                "mean_reward",
                "distance_m",
                "distance_between_crashes_m",
                "crash_sites",
                "turn_steps",
                "cells_visited",
            ]
        )
        for r in results:
            w.writerow(
                [
                    r.model,
                    r.world,
                    r.weights,
                    r.steps,
                    r.crashes,
                    f"{1000 * r.crashes / r.steps:.2f}",
                    f"{r.mean_reward:.4f}",
                    f"{r.distance_m:.2f}",
                    f"{r.distance_between_crashes_m:.2f}",
                    r.crash_sites,
                    r.turn_steps,
                    r.cells,
                ]
            )
    models = sorted({r.model for r in results}, key=["sam", "cnn"].index)
    worlds = list(dict.fromkeys(r.world for r in results))
    lines = [
        f"Exploit-only (epsilon 0) evaluation, {steps} lockstep steps per run; mean ± 95% CI over the "
        "weight files (training seeds); n = runs per cell." + (f" {protocol}" if protocol else ""),
        "",
    ]
    for title, key, digits, idx in (  # idx: the column of PAPER
        ("Table 1: crashes per 1000 steps", lambda r: 1000 * r.crashes / r.steps, 2, 0),
        ("Table 2: mean reward per step", lambda r: r.mean_reward, 3, 1),
    ):
        lines += [f"### {title}", ""]
        lines += [
            "| world | " + " | ".join(f"D3QN-{m.upper()} | paper" for m in models) + " |",
            "|" + "---|" * (1 + 2 * len(models)),
        ]
        for world in worlds:
            cells = []
            for m in models:
                vals = [key(r) for r in results if r.model == m and r.world == world]
                cells.append(f"{fmt(*mean_ci95(vals), digits)} (n={len(vals)})" if vals else "-")
                paper = PAPER.get((m, world))
                cells.append(str(paper[idx]) if paper else "-")
            lines.append(f"| {world} | " + " | ".join(cells) + " |")
        lines.append("")
    # Distance between crashes pooled over runs: runs without a crash would otherwise be dropped.
    lines += pooled_table(results, models, worlds, "Distance flown between crashes (m), pooled over runs", "", distance_cell)
    if results and all(r.crash_sites >= 0 for r in results):
        intro = (
            "A site is where a crashing step began (0.1 m grid), counted per run. With a fixed start pose a "
            "deterministic policy repeats its flight after every crash, so many crashes at few sites are one "
            "failure counted again."
        )
        lines += pooled_table(
            results,
            models,
            worlds,
            "Crashes and distinct crash sites, summed over runs",
            " crashes / sites",
            lambda runs: f"{sum(r.crashes for r in runs)} / {sum(r.crash_sites for r in runs)}",
            intro,
        )
    if results and all(r.turn_steps >= 0 and r.cells >= 0 for r in results):
        intro = (
            f"A turning step changes the heading by more than {TURN_DEG:g}°; the area is the number of distinct "
            "1 m x 1 m cells flown through, per run. A policy that circles on the spot crashes rarely but turns "
            "on almost every step and covers little. Mean ± 95% CI over the weight files."
        )
        lines += pooled_table(
            results,
            models,
            worlds,
            "Flight behaviour: turning steps (%) / floor area covered (m² per 1000 steps)",
            "",
            lambda runs: (
                fmt(*mean_ci95([100 * r.turn_steps / r.steps for r in runs]), 0)
                + " / "
                + fmt(*mean_ci95([1000 * r.cells / r.steps for r in runs]), 0)
            ),
            intro,
        )
    md_path = out_dir / "results.md"
    md_path.write_text("\n".join(lines))
    return md_path, csv_path


RESULTS_COLUMNS = ("model", "world", "weights", "steps", "crashes", "mean_reward", "distance_m")


def _csv_whole(row: dict, column: str, where: str, default: int | None = None) -> int:
    text = row.get(column)
    if text in (None, "") and default is not None:
        return default
    try:
        return int(text)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {column} must be a whole number, got {text!r}") from None


def _csv_number(row: dict, column: str, where: str) -> float:
    try:
        value = float(row[column])
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value):
        raise ValueError(f"{where}: {column} must be a finite number, got {row[column]!r}")
    return value


def read_results_csvs(paths: list[str]) -> list[EvalResult]:
    """The rows of earlier results.csv files (write_tables' format) as EvalResults, in order. ValueError,
    naming the file and line, for a missing or unreadable file, a missing column, a model other than sam
    or cnn, a count that is not a whole number or is impossible (crashes > steps), a number that is not
    finite, or no rows at all. The optional columns (crash_sites, turn_steps, cells_visited) default to
    -1 (unknown), as for tables written before they existed."""
    results = []
    for path in paths:
        try:
            with open(path, newline="") as f:
                reader = csv.DictReader(f)
                missing = [c for c in RESULTS_COLUMNS if c not in (reader.fieldnames or [])]
                if missing:
                    raise ValueError(f"{path}: no column {', '.join(missing)} (not an evaluate results.csv?)")
                rows = list(reader)
        except (OSError, UnicodeDecodeError, csv.Error) as e:
            raise ValueError(f"{path}: cannot read it ({e})") from None
        for line, r in enumerate(rows, start=2):
            where = f"{path} line {line}"
            if r["model"] not in ("sam", "cnn"):
                raise ValueError(f"{where}: model must be sam or cnn, got {r['model']!r}")
            if not r["world"] or not r["weights"]:
                raise ValueError(f"{where}: world and weights must not be empty (a short row?)")
            steps, crashes = _csv_whole(r, "steps", where), _csv_whole(r, "crashes", where)
            if steps < 1 or not 0 <= crashes <= steps:
                raise ValueError(f"{where}: needs steps >= 1 and 0 <= crashes <= steps, got {steps} and {crashes}")
            results.append(
                EvalResult(
                    r["model"],
                    r["world"],
                    r["weights"],
                    steps,
                    crashes,
                    _csv_number(r, "mean_reward", where),
                    _csv_number(r, "distance_m", where),
                    _csv_whole(r, "crash_sites", where, -1),
                    _csv_whole(r, "turn_steps", where, -1),
                    _csv_whole(r, "cells_visited", where, -1),
                )
            )
    if not results:
        raise ValueError(f"no rows in {', '.join(paths)}")
    return results


def main(argv=None) -> int:
    from uav_policy.weights import UNRECORDED_HFOV_DEG

    ap = argparse.ArgumentParser(prog="evaluate", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", action="append", choices=("sam", "cnn"), help="repeatable; default: sam")
    ap.add_argument(
        "--weights",
        nargs="*",
        default=None,
        help="weights files (one per training seed); for several models give MODEL=PATH; default: the packaged weights",
    )
    ap.add_argument("--worlds", nargs="+", default=["basic", "complex", "turbulent"])
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--epsilon", type=float, default=0.0)
    ap.add_argument("--seed", type=int, default=0, help="simulator seed (weather, start jitter)")
    ap.add_argument(
        "--start-yaw-jitter-deg",
        type=float,
        default=0.0,
        help="random start heading (+-deg) for every episode; 0 = the paper's fixed start pose",
    )
    ap.add_argument(
        "--sim-arg",
        action="append",
        default=[],
        metavar="NAME:=VALUE",
        help="extra sim_node parameter, e.g. --sim-arg hfov_deg:=90.0 (repeatable); without hfov_deg every weights "
        "file flies with the camera it was trained with (its header), else the sim default",
    )
    ap.add_argument("--repeats", type=int, default=1, help="runs per weight file and world (sim seeds --seed + i), pooled")
    ap.add_argument(
        "--ensemble",
        type=int,
        default=1,
        metavar="K",
        help="fly each K consecutive weights files of a model as one policy, the mean of their Q-values (an "
        "extension; policy_node gets the K files as its weights, comma-separated; one results row per group, its weights column "
        "the files joined by '+')",
    )
    ap.add_argument("--out", default="runs/eval", help="output folder for results.md / results.csv")
    ap.add_argument("--params-dir", default="params")
    ap.add_argument(
        "--from-csv",
        nargs="+",
        default=None,
        help="only rewrite the tables from earlier results.csv files (rows joined; give the same protocol flags "
        "as the measurement for the same protocol line)",
    )
    ap.add_argument(
        "--inprocess",
        action="store_true",
        help="measure without ROS (same simulator and network, one process): for screening; "
        "takes --sim-arg hfov_deg:=X and reward_window_fraction:=F only, and --epsilon 0",
    )
    ap.add_argument(
        "--crash-log",
        action="store_true",
        help="with --inprocess: also write crashes.csv, one row per crash (pose and heading before it, steps since "
        "the episode began, the start heading, the action)",
    )
    a = ap.parse_args(argv)
    if a.crash_log and not a.inprocess:
        ap.error("--crash-log needs --inprocess")
    if a.repeats < 1 or a.steps < 1:
        ap.error("--repeats and --steps must be >= 1")
    if a.ensemble < 1:
        ap.error("--ensemble must be >= 1")
    try:
        hfov_deg = sim_arg_hfov_deg(a.sim_arg)
        window = sim_arg_number(a.sim_arg, "reward_window_fraction")
    except ValueError as e:
        ap.error(f"--sim-arg: {e}")
    if a.inprocess:
        for arg in a.sim_arg:
            if arg.partition(":=")[0] not in INPROCESS_SIM_ARGS:
                ap.error(f"--inprocess takes only --sim-arg {':=X, '.join(INPROCESS_SIM_ARGS)}:=X, got {arg!r}")
        if window is not None and not 0.0 < window <= 1.0:
            ap.error(f"--sim-arg reward_window_fraction must lie in (0, 1], got {window:g}")
        if a.epsilon != 0.0:
            ap.error("--inprocess flies exploit-only: --epsilon must be 0")
        import torch

        # Batch-1 inference gains nothing from more threads (policy_node's torch_threads is 1 too),
        # and two evaluations sharing 2 cores with 2 threads each ran 16x slower (570 s vs 35 s).
        torch.set_num_threads(1)
    if not 0.0 <= a.start_yaw_jitter_deg <= 180.0:
        ap.error("--start-yaw-jitter-deg must be in [0, 180]")
    if a.start_yaw_jitter_deg > 0:
        protocol = (
            f"Every episode starts at a random heading (uniform ±{a.start_yaw_jitter_deg:g}°), "
            f"{a.repeats} x {a.steps} steps per weight file (sim seeds {a.seed}..{a.seed + a.repeats - 1})."
        )
    else:
        protocol = "Every episode starts at the world's start pose (the paper's protocol)."
    if a.sim_arg:
        protocol += f" sim_node parameters: {', '.join(a.sim_arg)}."
    if hfov_deg is None:
        protocol += (
            " Camera: each weights file flies with the field of view it was trained with (its header;"
            f" {UNRECORDED_HFOV_DEG:g}° when it has none)."
        )
    if a.inprocess:
        protocol += " Measured in-process (--inprocess: the same simulator and network without the ROS nodes)."
    if a.ensemble > 1:
        protocol += (
            f" Each policy is {a.ensemble} weights files flown as one, acting on the mean of their Q-values"
            f" (--ensemble {a.ensemble}); means and intervals are over these policies."
        )
    if a.from_csv:
        try:
            results = read_results_csvs(a.from_csv)
        except ValueError as e:
            ap.error(f"--from-csv: {e}")
        md, _ = write_tables(results, Path(a.out), results[0].steps, protocol)
        print(md.read_text())
        return 0
    models = a.model or ["sam"]
    runs: list[tuple[str, list[str]]] = []  # (model, its files: one, an ensemble's, or none for the packaged weights)
    packaged = {m: weights_or_packaged(m, "") for m in models}  # what a run without files flies (policy_node's default)
    for m in models:
        files = [w.split("=", 1)[1] for w in (a.weights or []) if w.startswith(f"{m}=")]
        files += [w for w in (a.weights or []) if "=" not in w] if len(models) == 1 else []
        if a.ensemble > 1 and not files:
            ap.error(f"--ensemble {a.ensemble}: give the {m} weights files to group (--weights)")
        if a.ensemble > 1 and len(files) % a.ensemble:
            ap.error(f"--ensemble {a.ensemble}: {m} has {len(files)} weights files, not a multiple of {a.ensemble}")
        runs += [(m, files[i : i + a.ensemble]) for i in range(0, len(files), a.ensemble)] or [(m, [])]
        if not files and len(packaged[m]) > 1:
            protocol += (
                f" The packaged {m} weights (policy_node's default) are {len(packaged[m])} files flown as one,"
                " acting on the mean of their Q-values."
            )
    params = Path(a.params_dir) if Path(a.params_dir).is_dir() else None
    from tqdm import tqdm

    from uav_policy.weights import WeightsError, read_file_config, read_file_window

    recorded_windows = set()
    for model, files in runs:  # unreadable weights fail here, before any node starts
        for path in files or packaged[model]:
            if "," in path and not a.inprocess:  # policy_node reads commas as separating files
                ap.error(f"--weights {model}={path}: policy_node cannot take a path with a comma (rename it, or --inprocess)")
            try:
                read_file_config(path)
                recorded_windows.add(read_file_window(path))
            except WeightsError as e:
                ap.error(f"--weights {model}={path}: {e}")
    if window is None and recorded_windows - {None}:
        protocol += (
            " Reward: each weights file's reward window as recorded in its header (the paper's 20 % when it records none): "
            f"{', '.join(f'{w:g}' for w in sorted(recorded_windows - {None}))}."
        )
    ensembles = {}  # (model, weights column) -> (network, its config, camera, reward window)
    for model, files in runs if a.inprocess else []:
        members = files or packaged[model]  # the packaged weights may be an ensemble too
        if len(members) > 1:
            try:
                ensembles[model, ENSEMBLE_SEP.join(files)] = load_policy(model, members, hfov_deg, window)
            except ValueError as e:
                ap.error(f"--ensemble {a.ensemble}, {model}: {e}" if files else f"the packaged {model} weights: {e}")

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    results, crash_rows = [], []
    total = len(runs) * len(a.worlds) * a.steps * a.repeats
    with tqdm(total=total, unit="step", dynamic_ncols=True, disable=None) as bar:

        def measure(model: str, weights: str, world: str, seed: int) -> EvalResult:
            jitter = a.start_yaw_jitter_deg
            if not a.inprocess:
                return evaluate_once(
                    model,
                    weights,
                    world,
                    a.steps,
                    a.epsilon,
                    seed,
                    params,
                    start_yaw_jitter_deg=jitter,
                    sim_args=tuple(a.sim_arg),
                    progress=bar.update,
                )
            net, net_cfg, hfov, win = ensembles.get((model, weights), (None, None, hfov_deg, window))
            r = evaluate_inprocess(
                model,
                weights,
                world,
                a.steps,
                seed,
                net=net,
                start_yaw_jitter_deg=jitter,
                hfov_deg=hfov,
                net_cfg=net_cfg,
                crash_log=crash_rows if a.crash_log else None,
                reward_window_fraction=win,
            )
            bar.update(a.steps)
            return r

        for model, files in runs:
            weights = ENSEMBLE_SEP.join(files)  # the weights column: "" for the packaged weights
            for world in a.worlds:
                bar.set_description(f"{model} {world} {Path(files[0]).name if files else 'packaged'}")
                r = pool([measure(model, weights, world, a.seed + i) for i in range(a.repeats)])
                results.append(r)
                bar.write(
                    f"{model:3s} {world:10s} {weights_label(files)}: {r.crashes} crashes at {r.crash_sites} sites, "
                    f"mean reward {r.mean_reward:.3f}, {r.distance_m:.0f} m flown"
                )
    md, csv_path = write_tables(results, Path(a.out), a.steps * a.repeats, protocol)
    print(md.read_text())
    print(f"written: {md} {csv_path}")
    if a.crash_log:
        with open(Path(a.out) / "crashes.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=CRASH_FIELDS)
            w.writeheader()
            w.writerows(crash_rows)
        print(f"written: {Path(a.out) / 'crashes.csv'} ({len(crash_rows)} crashes)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
