"""train: the main job. Brings up sim_node, policy_node and trainer_node and trains an agent.

    ros2 run uav_trainer train --model sam --steps 20000 --seed 0

Recipes (`--recipe`): `ensemble` (default) is how the packaged weights were trained, the recipe
with the fewest crashes measured (docs/RESULTS.md, round 35): a 150 deg camera with a 5 x 5 px
reward window, new layouts with Basic as every fourth episode, a 300-step episode limit, turn
penalty 1.0, two updates per four steps, and the online network saved at nine steps of the
budget's last 30 %, to be flown with the final weights as one policy of ten; `single` is the
earlier packaged weights' recipe (round 4): a 120 deg camera, a new procedural layout every
episode and a turn penalty of 1.0, one network; `paper` is the paper's setting: a 90 deg camera in
the Basic world with the paper's reward.

Learning (`--learning`): `lockstep` (default) has trainer_node learn after each step and release the
next frame to policy_node with the new weights and epsilon, so a run is, bit for bit, the in-process
run of its seed (docs/RESULTS.md, round 44); `concurrent` runs a learner thread beside acting, with
the step rate capped so that it keeps up (rounds 38-43).

Writes runs/<model>_seed<seed>/ (checkpoints, metrics.csv, episodes.csv, tb/, curves.png,
policy_<model>.safetensors). Ctrl-C stops the trainer first, which saves a final checkpoint with
the replay memory, then the policy and the simulator. Running it again with the same run
directory resumes where it stopped.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path

from uav_policy.networks import MAX_FRAMES, SAM_READOUTS

from .launching import Processes, params_args
from .training import snapshot_file, snapshot_steps

# What each recipe sets on top of params/*.yaml; --world, --sim-arg and --trainer-arg still win.
# `snapshots`: that many weight snapshots, one every thirtieth of the budget, ending one before it
# (30 000 steps: 21 000 ... 29 000); `max_rate_hz`: the step-rate cap of --learning concurrent unless
# --max-rate-hz says.
RECIPES = {
    "ensemble": {
        "world": "random_each_episode",
        "sim": [
            "hfov_deg:=150.0",
            "reward_window_fraction:=0.078",
            "mix_world:=basic",
            "mix_world_every:=4",
            "max_episode_steps:=300",
        ],
        "trainer": ["turn_penalty:=1.0", "replay_ratio:=0.5"],
        "snapshots": 9,
        "max_rate_hz": 30.0,
    },
    "single": {
        "world": "random_each_episode",
        "sim": ["hfov_deg:=120.0", "reward_window_fraction:=0.2"],
        "trainer": ["turn_penalty:=1.0"],
    },
    "paper": {"world": "basic", "sim": ["hfov_deg:=90.0", "reward_window_fraction:=0.2"], "trainer": ["turn_penalty:=0.0"]},
}
DEFAULT_MAX_RATE_HZ = 60.0


def snapshot_plan(snapshots: int, steps: int) -> tuple[list[str], list[int]]:
    """(trainer_node parameters, env steps) for `snapshots` weight snapshots, one every thirtieth of
    `steps`, the last one thirtieth before the end; nothing when `snapshots` is 0."""
    if not snapshots:
        return [], []
    every = max(1, steps // 30)
    first = max(every, steps - snapshots * every)
    args = [f"save_weights_every_steps:={every}", f"save_weights_from_step:={first}"]
    return args, snapshot_steps(every, first, steps)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="train", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", choices=("sam", "cnn"), default="sam")
    ap.add_argument(
        "--recipe",
        choices=tuple(RECIPES),
        default="ensemble",
        help="ensemble: how the packaged weights were trained, round 35's recipe (150 deg camera, new layouts with "
        "Basic every fourth episode, 300-step episodes, ten snapshots flown as one policy; docs/RESULTS.md); single: "
        "120 deg camera, new layout every episode, turn penalty 1.0, one network (round 4); paper: 90 deg camera, "
        "Basic world, the paper's reward (default: ensemble)",
    )
    ap.add_argument(
        "--world",
        default=None,
        help="training world, e.g. basic or random_each_episode (default: the recipe's)",
    )
    ap.add_argument("--steps", type=int, default=30000, help="environment steps budget (default: 30000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--max-rate-hz",
        type=float,
        default=None,
        help="with --learning concurrent: lockstep sim step-rate cap so the learner keeps its replay ratio on 2 CPU "
        "cores; 0 = uncapped (--learning lockstep needs none: uncapped unless given) "
        f"(default: {DEFAULT_MAX_RATE_HZ:g}, recipe ensemble {RECIPES['ensemble']['max_rate_hz']:g}: twice the updates)",
    )
    ap.add_argument(
        "--learning",
        choices=("lockstep", "concurrent"),
        default="lockstep",
        help="lockstep: trainer_node learns after each step and releases the next frame to policy_node with the new "
        "weights and epsilon, as inprocess does (for a seed, inprocess's episodes and weights); concurrent: a learner "
        "thread beside acting, weights pushed every push_interval_updates, steps capped by --max-rate-hz (rounds 38-43) "
        "(default: lockstep)",
    )
    ap.add_argument("--run-dir", default=None, help="output directory (default: runs/<model>_seed<seed>)")
    ap.add_argument("--params-dir", default="params", help="folder with sim.yaml, policy.yaml, trainer.yaml")
    ap.add_argument("--no-resume", action="store_true", help="ignore an existing checkpoint in the run directory")
    ap.add_argument(
        "--trainer-arg",
        action="append",
        default=[],
        metavar="NAME:=VALUE",
        help="extra trainer_node parameter, e.g. --trainer-arg learning_starts:=500 (repeatable)",
    )
    ap.add_argument("--sim-arg", action="append", default=[], metavar="NAME:=VALUE", help="extra sim_node parameter")
    ap.add_argument(
        "--sam-readout",
        choices=SAM_READOUTS,
        default="max",
        help="SAM readout for policy_node and trainer_node: max (the paper) or flatten (an extension)",
    )
    ap.add_argument(
        "--input-size",
        type=int,
        default=None,
        metavar="PX",
        help="square network input and camera image (px) for all three nodes (default: params/*.yaml's, 64); "
        "layer sizes go by --trainer-arg (conv_channels, and SAM's d_model, heads, relational_blocks, mlp_hidden)",
    )
    ap.add_argument(
        "--frames",
        type=int,
        default=None,
        help=f"depth frames in the state for policy_node and trainer_node (1 to {MAX_FRAMES}; default: params/*.yaml's, 5)",
    )
    a = ap.parse_args(argv)
    if a.steps <= 0:
        ap.error("--steps must be positive")
    if a.input_size is not None and not 8 <= a.input_size <= 512:
        ap.error(f"--input-size must lie in [8, 512] px, got {a.input_size}")
    if a.frames is not None and not 1 <= a.frames <= MAX_FRAMES:
        ap.error(f"--frames must lie in [1, {MAX_FRAMES}], got {a.frames}")
    frames = [] if a.frames is None else [f"frame_stack:={a.frames}"]
    size = [] if a.input_size is None else [a.input_size]
    if a.max_rate_hz is not None and a.max_rate_hz < 0:
        ap.error(f"--max-rate-hz must be >= 0, got {a.max_rate_hz:g}")
    recipe = RECIPES[a.recipe]
    world = a.world or recipe["world"]
    lockstep = a.learning == "lockstep"
    if a.max_rate_hz is not None:
        max_rate_hz = a.max_rate_hz
    else:  # lockstep: acting waits for learning, no cap needed
        max_rate_hz = 0.0 if lockstep else recipe.get("max_rate_hz", DEFAULT_MAX_RATE_HZ)
    snapshots, snapshot_at = snapshot_plan(recipe.get("snapshots", 0), a.steps)
    run_dir = Path(a.run_dir or f"runs/{a.model}_seed{a.seed}")
    params = Path(a.params_dir) if Path(a.params_dir).is_dir() else None
    logs = run_dir / "logs"
    procs = Processes(log_dir=logs)
    p = lambda name, items: [x for kv in items for x in ("-p", kv)]  # noqa: E731
    # A random start heading: drawn anew each episode in a fixed world; with random_each_episode one
    # draw per run, where every layout starts (as the packaged weights were trained).
    # wait_for_subscribers: the sim steps once policy and trainer both listen (no step goes unlearnt).
    sim_extra = ["start_yaw_jitter_deg:=180.0", f"max_rate_hz:={float(max_rate_hz)}", "wait_for_subscribers:=2"]
    sim_extra += recipe["sim"]
    sim_extra += [f"image_{side}:={px}" for px in size for side in ("width", "height")] + a.sim_arg
    procs.start(
        "sim", "uav_sim", "sim_node", params_args(params, "sim") + p("", [f"world:={world}", f"seed:={a.seed}", *sim_extra])
    )
    procs.start(
        "policy",
        "uav_policy",
        "policy_node",
        params_args(params, "policy")
        + p("", [f"model:={a.model}", f"sam_readout:={a.sam_readout}", f"seed:={a.seed}", "epsilon:=1.0"])
        + p("", [f"wait_for_trainer:={'true' if lockstep else 'false'}"])
        + p("", [f"input_{side}:={px}" for px in size for side in ("height", "width")] + frames),
    )
    trainer = procs.start(
        "trainer",
        "uav_trainer",
        "trainer_node",
        params_args(params, "trainer")
        + p(
            "",
            [
                f"model:={a.model}",
                f"sam_readout:={a.sam_readout}",
                f"seed:={a.seed}",
                f"total_steps:={a.steps}",
                f"run_dir:={run_dir}",
                f"resume:={'false' if a.no_resume else 'true'}",
                f"lockstep_learning:={'true' if lockstep else 'false'}",
                *recipe["trainer"],
                *snapshots,
                *[f"input_size_px:={px}" for px in size],
                *frames,
                *a.trainer_arg,
            ],
        ),
    )
    print(
        f"training D3QN-{a.model.upper()} (recipe {a.recipe}: {' '.join(recipe['sim'] + recipe['trainer'] + snapshots)}) "
        f"in '{world}' for {a.steps} steps, learning {a.learning} -> {run_dir} (node logs in {logs})"
    )
    interrupted = False

    def on_sigint(*_):
        nonlocal interrupted
        interrupted = True

    signal.signal(signal.SIGINT, on_sigint)
    signal.signal(signal.SIGTERM, on_sigint)
    code = 0
    try:
        code = follow(trainer, run_dir, a.steps, lambda: interrupted, procs)
    finally:
        procs.stop("trainer", timeout_s=120)
        procs.stop_all(["policy", "sim"])
    trainer_code = trainer.returncode
    weights = run_dir / f"policy_{a.model}.safetensors"
    if weights.exists():
        # The snapshots this budget planned that were written (a stop before the end writes fewer), then the final weights.
        files = [p for n in snapshot_at if (p := snapshot_file(run_dir, a.model, n)).exists()] + [weights]
        camera = [kv for kv in sim_extra if kv.startswith("hfov_deg:=")][-1:]
        fly_sim = f"ros2 run uav_sim sim_node --ros-args -p {camera[0]} & " if camera else ""
        print(
            f"weights: {', '.join(map(str, files))}\nfly them: {fly_sim}ros2 run uav_policy policy_node --ros-args "
            f"-p model:={a.model} -p weights:={','.join(map(str, files))}"
            + (f" -p sam_readout:={a.sam_readout}" if a.sam_readout != "max" else "")
        )
    if trainer_code not in (0, None, -signal.SIGINT):
        print(f"trainer_node exited with code {trainer_code}; see {logs / 'trainer.log'}", file=sys.stderr)
        return trainer_code
    return code if not interrupted else 130


def follow(trainer, run_dir: Path, total: int, interrupted, procs: Processes) -> int:
    """Show a progress bar from metrics.csv until the trainer exits or Ctrl-C."""
    from tqdm import tqdm

    metrics = run_dir / "metrics.csv"
    bar = tqdm(total=total, unit="step", dynamic_ncols=True, disable=None)
    done = 0
    while trainer.poll() is None and not interrupted():
        for name in ("sim", "policy"):
            if procs.procs[name].poll() is not None:
                print(f"\n{name}_node exited early (code {procs.procs[name].returncode}); stopping", file=sys.stderr)
                bar.close()
                return 1
        time.sleep(1.0)
        steps, info = read_progress(metrics)
        if steps > done:
            bar.update(min(steps, total) - done)
            done = min(steps, total)
        if info:
            bar.set_postfix_str(info, refresh=True)
    bar.close()
    return 0


def read_progress(metrics: Path) -> tuple[int, str]:
    try:
        lines = metrics.read_text().strip().splitlines()
    except OSError:
        return 0, ""
    if len(lines) < 2:
        return 0, ""
    head, last = lines[0].split(","), lines[-1].split(",")
    row = dict(zip(head, last, strict=False))
    try:
        return int(row["env_steps"]), (
            f"ep len {float(row['mean_episode_length']):.0f} ep rew {float(row['mean_episode_reward']):.0f} "
            f"eps {float(row['epsilon']):.2f} {float(row['env_steps_per_s']):.0f} st/s"
        )
    except (KeyError, ValueError):
        return 0, ""


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    raise SystemExit(main())
