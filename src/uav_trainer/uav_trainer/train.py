"""train: the main job. Brings up sim_node, policy_node and trainer_node and trains an agent.

    ros2 run uav_trainer train --model sam --steps 30000 --seed 0

The recipe (`--recipe NAME` for params/recipes/NAME.yaml, or `--recipe FILE` for your own) sets the
nodes' parameters on top of params/*.yaml; `--world`, `--sim-arg` and `--trainer-arg` still win.
`shipped` (the default) is how the packaged weights were trained, behind a RealSense D435-like camera; `wide150`
the ideal 150 deg camera that met the paper's figures; `paper` the paper's setting.
trainer_node learns in lockstep with acting: after each step it stores the transition, runs the
updates replay_ratio allows and only then releases the next frame to policy_node with the new
weights and epsilon, so a run is, bit for bit, `python -m uav_trainer.inprocess` with the same
recipe and seed.

`--actors N` (N > 1) starts N sim_node/policy_node pairs in namespaces /actor0 ... /actor<N-1>, each
with seed seed+i (its own world sequence) and its own exploration rate, feeding one trainer_node:
more experience per update, asynchronously (not bit-reproducible). An actor that dies is reported and
training goes on with the others; none of them publishes /clock. Actors on other hosts can join the
same trainer: docs/TRAINING.md, "Many actors".

Writes runs/<model>_seed<seed>/ (checkpoints, metrics.csv, episodes.csv, tb/, curves.png,
policy_<model>.safetensors and the recipe's snapshots). At the end it chooses one of those files on the
validation worlds (uav_eval.selection, `choose`; validation.csv) and prints the command that flies it.
Ctrl-C stops the trainer first, which saves
a final checkpoint with the replay memory, then the policy and the simulator. Running it again with
the same run directory resumes where it stopped.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from uav_common.launching import Processes, find_executable, params_args, ros_log_dir, stop_signals
from uav_common.settings import refuse_retired_flags
from uav_policy.net_config import MAX_FRAMES, SAM_READOUTS, NetConfig
from uav_policy.push import write_key
from uav_sim.world import VALIDATION_STEPS

from .recipes import DEFAULT_RECIPE, RecipeError, load_recipe, parse_assignments
from .training_config import snapshot_file, snapshot_steps

RETIRED_FLAGS = {
    "--learning": "train always learns in lockstep with acting (concurrent learning trained weaker policies)",
    "--max-rate-hz": "lockstep learning needs no step-rate cap",
}


def parser(argv: list[str]) -> argparse.ArgumentParser:
    """train's flags (a retired one given in `argv` stops it at once, naming its replacement)."""
    ap = argparse.ArgumentParser(prog="train", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    refuse_retired_flags(ap, argv, RETIRED_FLAGS)
    ap.add_argument("--model", choices=("sam", "cnn"), default="sam")
    ap.add_argument(
        "--recipe",
        default=DEFAULT_RECIPE,
        help="a recipe in PARAMS_DIR/recipes (shipped: how the packaged weights were trained, behind a depth camera "
        "like a RealSense D435; wide150: an ideal 150 deg camera; paper: the paper's setting) or a path to your own "
        f"recipe file (default: {DEFAULT_RECIPE})",
    )
    ap.add_argument("--world", default=None, help="training world, e.g. basic or random_each_episode (default: the recipe's)")
    ap.add_argument("--steps", type=int, default=30000, help="environment steps budget (default: 30000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--actors",
        type=int,
        default=1,
        metavar="N",
        help=f"actor pairs (sim_node + policy_node) feeding the one trainer_node, in namespaces /actor0 ... (1 to "
        f"{MAX_ACTORS}; default: 1, in lockstep and bit-identical to inprocess; more: asynchronous)",
    )
    ap.add_argument("--run-dir", default=None, help="output directory (default: runs/<model>_seed<seed>)")
    ap.add_argument(
        "--log-dir",
        default=None,
        help="node logs (default: the ROS log folder, $ROS_LOG_DIR or ~/.ros/log, train_<run folder>_<time>/): "
        "outside the run folder, so a full or failing run disk does not cut off the trace of what went wrong",
    )
    ap.add_argument("--params-dir", default="params", help="folder with sim.yaml, policy.yaml, trainer.yaml and recipes/")
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
        default=None,
        help="SAM readout (uav_policy/networks.py; default: the recipe's, else trainer.yaml's); the policy takes it "
        "from the pushed weights",
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
    ap.add_argument(
        "--validation-steps",
        type=int,
        default=VALIDATION_STEPS,
        metavar="N",
        help=f"at the end, fly each weights file the run wrote N steps in each validation world and name the one with "
        f"the fewest crashes (default: {VALIDATION_STEPS}; 0: name the final weights without choosing)",
    )
    return ap


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = parser(argv)
    a = ap.parse_args(argv)
    if a.validation_steps < 0:
        ap.error("--validation-steps must be >= 0 (0: no choice, the final weights)")
    if a.steps <= 0:
        ap.error("--steps must be positive")
    if not 1 <= a.actors <= MAX_ACTORS:
        ap.error(f"--actors must lie in [1, {MAX_ACTORS}], got {a.actors}")
    if a.input_size is not None and not 8 <= a.input_size <= 512:
        ap.error(f"--input-size must lie in [8, 512] px, got {a.input_size}")
    if a.frames is not None and not 1 <= a.frames <= MAX_FRAMES:
        ap.error(f"--frames must lie in [1, {MAX_FRAMES}], got {a.frames}")
    try:
        recipe = load_recipe(a.recipe, a.params_dir)
        sim_values = {**recipe.node("sim_node"), **parse_assignments(a.sim_arg)}
        trainer_values = {**recipe.node("trainer_node"), **parse_assignments(a.trainer_arg)}
    except RecipeError as e:
        ap.error(str(e))
    try:
        snapshot_at = snapshot_steps(int(trainer_values.get("snapshots", 0)), a.steps)
    except ValueError as e:
        ap.error(f"--steps {a.steps} with recipe {recipe.path}: {e}")
    frames = [] if a.frames is None else [f"frame_stack:={a.frames}"]
    # A teacher is sim_node's planner: it remembers what the trainer's frame stack holds.
    teacher = str(trainer_values.get("teacher", "none"))
    stack = a.frames or int(trainer_values.get("frame_stack", NetConfig.frames))
    teach = [f"teacher:={teacher}", f"teacher_frames:={stack}"] if teacher != "none" else []
    # A network with the local map: the policy's first network takes it too (the pushes' architecture).
    frames += ["local_map:=true"] if str(trainer_values.get("local_map", False)).lower() == "true" else []
    size = [] if a.input_size is None else [a.input_size]
    run_dir = Path(a.run_dir or f"runs/{a.model}_seed{a.seed}")
    params = Path(a.params_dir) if Path(a.params_dir).is_dir() else None
    logs = Path(a.log_dir) if a.log_dir else ros_log_dir() / f"train_{run_dir.resolve().name}_{time.strftime('%Y%m%d-%H%M%S')}"
    started = time.time() - 1.0  # files written from here on are this run's (1 s for coarse file-system clocks)
    # A new key for each run, in the run folder (mode 0600): only this run's trainer can push to its policy.
    try:
        key = write_key(run_dir / "push.key")
    except OSError as e:
        ap.error(f"--run-dir {run_dir}: cannot write there ({e.strerror or e})")
    try:
        logs.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        ap.error(f"--log-dir {logs}: cannot write there ({e.strerror or e})")
    procs = Processes(log_dir=logs)
    trainer, actors = start_nodes(procs, a, recipe, params, key, run_dir, size, frames, teach)
    many = f" from {a.actors} actors (asynchronous)" if a.actors > 1 else ""
    print(
        f"training D3QN-{a.model.upper()} with recipe {recipe.path} ({recipe.summary()}) for {a.steps} steps{many} -> "
        f"{run_dir} (node logs in {logs})",
        flush=True,
    )
    interrupted = stop_signals()
    code = 0
    try:
        code = follow(trainer, run_dir, a.steps, interrupted, procs, actors)
    finally:
        procs.stop("trainer", timeout_s=120)
        procs.stop_all([f"policy{n}" for n in actors] + [f"sim{n}" for n in actors])
    return report(a, trainer, run_dir, logs, snapshot_at, started, sim_values, code, interrupted)


def start_nodes(procs: Processes, a, recipe, params, key, run_dir: Path, size: list, frames: list, teach: list):
    """Start each actor's sim_node and policy_node and the trainer_node: (the trainer's process, the actors' names)."""
    p = lambda items: [x for kv in items for x in ("-p", kv)]  # noqa: E731
    node_args = lambda name: params_args(params, name) + recipe.ros_args(f"{name}_node")  # noqa: E731
    world = [f"world:={a.world}"] if a.world else []
    namespaces = actor_namespaces(a.actors)
    actors = [ns.removeprefix("/actor") for ns in namespaces]  # process and log names: sim, sim0, sim1, ...
    for name, ns, seed in zip(actors, namespaces, range(a.seed, a.seed + a.actors), strict=True):
        remap = ["-r", f"__ns:={ns}"] if ns else []
        # wait_for_subscribers: the sim steps once policy and trainer both listen (no step goes unlearnt).
        sim_extra = [*world, f"seed:={seed}", "wait_for_subscribers:=2", *(["publish_clock:=false"] if ns else [])]
        sim_extra += [f"image_{side}:={px}" for px in size for side in ("width", "height")] + teach + a.sim_arg
        procs.start(f"sim{name}", "uav_sim", "sim_node", remap + node_args("sim") + p(sim_extra))
        procs.start(
            f"policy{name}",
            "uav_policy",
            "policy_node",
            remap
            + node_args("policy")
            + p([f"model:={a.model}", f"seed:={seed}", "epsilon:=1.0", "wait_for_trainer:=true"])
            # insight_every:=0: an actor whose weights change every other step measures no explanations (a frame's
            # measurement would hold the next release); `evaluate` measures the run's weights.
            + p(["accept_pushes:=true", f"push_key_file:={key}", "safety:=false", "shield:=never", "insight_every:=0"])
            + p([f"input_{side}:={px}" for px in size for side in ("height", "width")] + frames),
        )
    trainer = procs.start(
        "trainer",
        "uav_trainer",
        "trainer_node",
        node_args("trainer")
        + p(
            [
                f"model:={a.model}",
                *([f"sam_readout:={a.sam_readout}"] if a.sam_readout else []),
                f"seed:={a.seed}",
                f"total_steps:={a.steps}",
                f"run_dir:={run_dir}",
                f"push_key_file:={key}",
                f"resume:={'false' if a.no_resume else 'true'}",
                *([f"actors:=[{', '.join(namespaces)}]"] if a.actors > 1 else []),
                *[f"input_size_px:={px}" for px in size],
                *frames,
                *a.trainer_arg,
            ]
        ),
    )
    return trainer, actors


def report(a, trainer, run_dir: Path, logs: Path, snapshot_at, started: float, sim_values: dict, code: int, interrupted) -> int:
    """What the run wrote and the command that flies the weights chosen (or why it stopped); the exit code."""
    trainer_code = trainer.returncode
    failed = trainer_code not in (0, None, -signal.SIGINT)
    # Only files this run wrote: an earlier run's (or a crashed run's) files are not this run's result.
    planned = [snapshot_file(run_dir, a.model, n) for n in snapshot_at] + [run_dir / f"policy_{a.model}.safetensors"]
    files = [p for p in planned if p.exists() and p.stat().st_mtime >= started]
    if failed:
        print(f"trainer_node exited with code {trainer_code}; see {logs / 'trainer.log'}", file=sys.stderr)
        unwritten = [line for line in _read_lines(logs / "trainer.log") if "weights not written:" in line]
        if unwritten:
            print(unwritten[-1].split("] ")[-1], file=sys.stderr)
            files = [p for p in files if not any(str(p) in line for line in unwritten)]
        if files:
            print(f"written before it stopped: {', '.join(map(str, files))}", file=sys.stderr)
        return trainer_code
    if files and not interrupted():
        chosen, why = name_one(run_dir, a.model, files, a.validation_steps)
        # The simulator behind the camera the run trained with, for the command that flies the result.
        sensor, camera = sim_values.get("sensor", "ideal"), sim_values.get("hfov_deg")
        if sensor != "ideal":
            sim_p = f"-p sensor:={sensor} -p sensor_scale:={float(sim_values.get('sensor_scale', 1.0))}"
        else:
            sim_p = f"-p hfov_deg:={float(camera)}" if camera is not None else ""
        fly_sim = f"ros2 run uav_sim sim_node --ros-args {sim_p} & " if sim_p else ""
        print(
            f"weights written: {', '.join(map(str, files))}\nweights: {chosen} ({why})\nfly it: {fly_sim}ros2 run "
            f"uav_policy policy_node --ros-args -p model:={a.model} -p weights:={chosen}"
        )
    elif files:
        print(f"stopped before the budget: weights so far {', '.join(map(str, files))}; the same command resumes")
    else:
        print(f"this run wrote no weights in {run_dir}", file=sys.stderr)
    return code if not interrupted() else 130


def name_one(run_dir: Path, model: str, files: list[Path], steps: int) -> tuple[Path, str]:
    """The one file a run ships, and why: chosen on the validation worlds (steps > 0) by uav_eval's `choose` (run as
    a program: measuring is not imported by what learns), else the final weights."""
    final = run_dir / f"policy_{model}.safetensors"
    fallback = final if final in files else files[-1]
    if steps == 0 or len(files) == 1:
        return fallback, "the run's only weights file" if len(
            files
        ) == 1 else "the final weights, not chosen (--validation-steps 0)"
    cmd = [find_executable("uav_eval", "choose"), str(run_dir), "--model", model, "--steps", str(steps), "--again"]
    said = None
    with subprocess.Popen([*cmd, "--files", *map(str, files)], stdout=subprocess.PIPE, text=True) as p:
        for line in p.stdout:
            print(line, end="", flush=True)
            said = re.match(r"chosen: (.+) \((\d+) crashes in (\d+) validation steps", line) or said
    if p.returncode != 0 or said is None:
        return fallback, f"the final weights: choosing on the validation worlds failed (code {p.returncode}, see above)"
    path, crashes, flown = said.groups()
    table = run_dir / "validation.csv"
    return Path(path), f"chosen of {len(files)} on the validation worlds: {crashes} crashes in {flown} steps; {table}"


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(errors="replace").splitlines()
    except OSError:
        return []


PROGRESS_EVERY_S = 30.0  # a progress line this often when stdout is no terminal (a log file, CI, nohup)
MAX_ACTORS = 16


def actor_namespaces(n: int) -> list[str]:
    """The actors' namespaces: none for one actor (the nodes as `ros2 run` starts them), /actor0 ... for more."""
    return [""] if n == 1 else [f"/actor{i}" for i in range(n)]


def follow(trainer, run_dir: Path, total: int, interrupted, procs: Processes, actors=("",)) -> int:
    """Progress from metrics.csv until the trainer exits or Ctrl-C: a bar on a terminal, else a line every
    PROGRESS_EVERY_S seconds and one at the end (steps, rate, ETA). One actor's node exiting stops a run with
    one actor; with several, the run goes on (the trainer counts the actor lost) while any actor is whole."""
    from tqdm import tqdm

    metrics = run_dir / "metrics.csv"
    bar = tqdm(total=total, unit="step", dynamic_ncols=True, disable=None)
    lines = bar.disable  # tqdm disables itself when stdout is not a terminal
    t0, done, printed = time.monotonic(), 0, time.monotonic()
    code = 0
    told = set()
    while trainer.poll() is None and not interrupted():
        dead = [f"{kind}{n}" for n in actors for kind in ("sim", "policy") if procs.procs[f"{kind}{n}"].poll() is not None]
        for name in sorted(set(dead) - told):
            print(f"\n{name}_node exited (code {procs.procs[name].returncode})", file=sys.stderr)
            told.add(name)
        whole = [n for n in actors if f"sim{n}" not in dead and f"policy{n}" not in dead]
        if not whole:
            print("no actor is left whole; stopping", file=sys.stderr)
            code = 1
            break
        time.sleep(1.0)
        steps, info = read_progress(metrics)
        if steps > done:
            bar.update(min(steps, total) - done)
            done = min(steps, total)
        if info:
            bar.set_postfix_str(info, refresh=True)
        if lines and time.monotonic() - printed >= PROGRESS_EVERY_S:
            print(progress_line(done, total, time.monotonic() - t0, info), flush=True)
            printed = time.monotonic()
    bar.close()
    if lines:
        steps, info = read_progress(metrics)
        print(progress_line(min(max(steps, done), total), total, time.monotonic() - t0, info), flush=True)
    return code


def progress_line(steps: int, total: int, elapsed_s: float, info: str) -> str:
    """'progress: 1200/30000 steps (4%), 24.1 steps/s, ETA 19:54 | <metrics>' for logs."""
    rate = steps / elapsed_s if elapsed_s > 0 else 0.0
    left = (total - steps) / rate if rate > 0 else float("inf")
    eta = "--:--" if left == float("inf") else f"{int(left // 60)}:{int(left % 60):02d}"
    return f"progress: {steps}/{total} steps ({100.0 * steps / total:.0f}%), {rate:.1f} steps/s, ETA {eta}" + (
        f" | {info}" if info else ""
    )


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
