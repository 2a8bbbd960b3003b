"""evaluate: fly a policy exploit-only through the ROS nodes and measure the paper's test metrics.

    ros2 run uav_trainer evaluate --model sam --weights runs/sam_seed0/policy_sam.safetensors \
        --worlds basic complex turbulent --steps 1000

For each (model, weights, world) it starts sim_node and policy_node (epsilon 0 unless --epsilon),
counts crashes, mean reward per step (uav_sim.reward) and distance flown between crashes over
`--steps` lockstep steps, and writes Markdown and CSV tables (mean and 95% CI over the weight
files given, i.e. over training seeds) beside the paper's numbers.
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

from uav_sim import contract
from uav_sim.reward import step_reward

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

    @property
    def distance_between_crashes_m(self) -> float:
        return self.distance_m / self.crashes if self.crashes else math.inf


class StepMonitor:
    """Counts steps, crashes, reward and distance from step_outcome and odom (joined by stamp)."""

    def __init__(self, steps: int):
        self.target = steps
        self.joiner = contract.StampJoiner(("outcome", "odom"), max_pending=1000)
        self.first = True
        self.steps = self.crashes = 0
        self.reward = 0.0
        self.distance = 0.0
        self.last_xy = None

    def add(self, stream: str, msg) -> None:
        j = self.joiner.add(stream, contract.stamp_ns(msg.header.stamp), msg)
        if j is None or self.done:
            return
        p = j["odom"].pose.pose.position
        xy = (p.x, p.y)
        if self.first:  # the frame before any command: not a step
            self.first, self.last_xy = False, xy
            return
        out = j["outcome"]
        collided = contract.outcome_collided(out)
        beta = 0.0 if collided else min(max(float(out.range), 0.0), float(out.max_range))
        self.reward += step_reward(beta, collided)
        self.steps += 1
        if collided:
            self.crashes += 1  # the vehicle is back at the start: no distance for this jump
        else:
            self.distance += math.hypot(xy[0] - self.last_xy[0], xy[1] - self.last_xy[1])
        self.last_xy = xy

    @property
    def done(self) -> bool:
        return self.steps >= self.target


def evaluate_once(
    model: str,
    weights: str,
    world: str,
    steps: int,
    epsilon: float = 0.0,
    seed: int = 0,
    params_dir: Path | None = None,
    timeout_s: float = 600.0,
    log_dir: Path | None = None,
    progress=None,
) -> EvalResult:
    """Run sim_node + policy_node (installed executables) and measure `steps` lockstep steps."""
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
        # The monitor subscribes before the sim starts; lockstep only advances once the policy answers.
        procs.start("sim", "uav_sim", "sim_node", params_args(params_dir, "sim") + pargs([f"world:={world}", f"seed:={seed}"]))
        wargs = [f"weights:={weights}"] if weights else []
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
    finally:
        procs.stop_all(["policy", "sim"])
        executor.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
    return EvalResult(model, world, weights, mon.steps, mon.crashes, mon.reward / max(mon.steps, 1), mon.distance)


def evaluate_inprocess(model: str, weights: str, world: str, steps: int, seed: int = 0, net=None) -> EvalResult:
    """The same measurement without ROS (same simulator, stack and network): for benchmarks and checks."""
    from uav_policy import weights as wio
    from uav_policy.actions import PAPER_ACTIONS
    from uav_policy.agent import Agent
    from uav_policy.frame_stack import FrameStack
    from uav_policy.networks import NetConfig
    from uav_sim.simulator import SimConfig, Simulator
    from uav_sim.vehicle import BodyTwist
    from uav_sim.world import load_world

    cfg = NetConfig(model=model)
    agent = Agent(net if net is not None else wio.load_file(weights, cfg), cfg, seed=seed)
    sim = Simulator(load_world(world), SimConfig(seed=seed))
    stack = FrameStack(cfg.frames)
    r = sim.observe()
    state = stack.reset(r.depth_m)
    crashes, reward, dist, last = 0, 0.0, 0.0, (r.pose.x_m, r.pose.y_m)
    try:
        for _ in range(steps):
            a = PAPER_ACTIONS[agent.act(state, 0.0)[0]]
            r = sim.step(BodyTwist(a.linear_x_mps, yaw_rate_radps=a.yaw_rate_radps(sim.config.step_duration_s)))
            reward += r.reward
            if r.collided:
                crashes += 1
                state = stack.reset(r.depth_m)
            else:
                dist += math.hypot(r.pose.x_m - last[0], r.pose.y_m - last[1])
                state = stack.push(r.depth_m)
            last = (r.pose.x_m, r.pose.y_m)
    finally:
        sim.close()
    return EvalResult(model, world, weights, steps, crashes, reward / steps, dist)


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


def write_tables(results: list[EvalResult], out_dir: Path, steps: int) -> tuple[Path, Path]:
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
                ]
            )
    models = sorted({r.model for r in results}, key=["sam", "cnn"].index)
    worlds = list(dict.fromkeys(r.world for r in results))
    lines = [
        f"Exploit-only (epsilon 0) evaluation, {steps} lockstep steps per run; mean ± 95% CI over the "
        "weight files (training seeds); n = runs per cell.",
        "",
    ]
    for title, key, digits in (
        ("Table 1: crashes per 1000 steps", lambda r: 1000 * r.crashes / r.steps, 2),
        ("Table 2: mean reward per step", lambda r: r.mean_reward, 3),
    ):
        lines += [f"### {title}", ""]
        lines += [
            "| world | " + " | ".join(f"D3QN-{m.upper()} | paper" for m in models) + " |",
            "|" + "---|" * (1 + 2 * len(models)),
        ]
        idx = 0 if "crashes" in title else 1
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
    lines += [
        "### Distance flown between crashes (m), pooled over runs",
        "",
        "| world | " + " | ".join(f"D3QN-{m.upper()}" for m in models) + " |",
        "|" + "---|" * (1 + len(models)),
    ]
    for world in worlds:
        cells = []
        for m in models:
            runs = [r for r in results if r.model == m and r.world == world]
            dist, crashes = sum(r.distance_m for r in runs), sum(r.crashes for r in runs)
            free = sum(1 for r in runs if r.crashes == 0)
            head = f"{dist / crashes:.0f}" if crashes else f"no crash in {dist:.0f} m"
            cells.append(f"{head} ({free}/{len(runs)} runs crash-free)" if runs else "-")
        lines.append(f"| {world} | " + " | ".join(cells) + " |")
    lines.append("")
    md_path = out_dir / "results.md"
    md_path.write_text("\n".join(lines))
    return md_path, csv_path


def main(argv=None) -> int:
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
    ap.add_argument("--seed", type=int, default=0, help="simulator seed (weather)")
    ap.add_argument("--out", default="runs/eval", help="output folder for results.md / results.csv")
    ap.add_argument("--params-dir", default="params")
    ap.add_argument("--from-csv", default=None, help="only rewrite the tables from an earlier results.csv")
    a = ap.parse_args(argv)
    if a.from_csv:
        rows = list(csv.DictReader(open(a.from_csv)))
        results = [
            EvalResult(
                r["model"],
                r["world"],
                r["weights"],
                int(r["steps"]),
                int(r["crashes"]),
                float(r["mean_reward"]),
                float(r["distance_m"]),
            )
            for r in rows
        ]
        md, _ = write_tables(results, Path(a.out), results[0].steps if results else a.steps)
        print(md.read_text())
        return 0
    models = a.model or ["sam"]
    runs: list[tuple[str, str]] = []
    for m in models:
        files = [w.split("=", 1)[1] for w in (a.weights or []) if w.startswith(f"{m}=")]
        files += [w for w in (a.weights or []) if "=" not in w] if len(models) == 1 else []
        runs += [(m, f) for f in files] or [(m, "")]
    params = Path(a.params_dir) if Path(a.params_dir).is_dir() else None
    from tqdm import tqdm

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    results = []
    total = len(runs) * len(a.worlds) * a.steps
    with tqdm(total=total, unit="step", dynamic_ncols=True, disable=None) as bar:
        for model, weights in runs:
            for world in a.worlds:
                bar.set_description(f"{model} {world} {Path(weights).name if weights else 'packaged'}")
                r = evaluate_once(model, weights, world, a.steps, a.epsilon, a.seed, params, progress=bar.update)
                results.append(r)
                bar.write(
                    f"{model:3s} {world:10s} {weights or 'packaged'}: {r.crashes} crashes, "
                    f"mean reward {r.mean_reward:.3f}, {r.distance_m:.0f} m flown"
                )
    md, csv_path = write_tables(results, Path(a.out), a.steps)
    print(md.read_text())
    print(f"written: {md} {csv_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
