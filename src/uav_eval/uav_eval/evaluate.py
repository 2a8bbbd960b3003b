"""evaluate: fly a policy exploit-only through the ROS nodes and measure the paper's test metrics.

    ros2 run uav_eval evaluate --model sam --weights runs/sam_seed0/policy_sam.safetensors \
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
import os
import time
from collections import Counter
from pathlib import Path

from . import ENSEMBLE_SEP, MODELS, PLANNERS
from .autopsy import SEEN_WORDS
from .flights import (
    CRASH_FIELDS,
    INPROCESS_SIM_ARGS,
    EvalResult,
    FlightSpec,
    evaluate_inprocess,
    sim_arg_hfov_deg,
    sim_arg_number,
    weights_label,
    weights_or_packaged,
)
from .ros_flights import bag_name, evaluate_once
from .tables import pool, read_results_csvs, write_tables


def expand_worlds(names: list[str]) -> list[str]:
    """The worlds named, with 'validation' standing for the validation set; each is checked to load
    (ValueError naming the one that does not)."""
    from uav_sim.world import VALIDATION, VALIDATION_WORLDS, WorldError, load_world

    worlds = [w for name in names for w in (VALIDATION_WORLDS if name == VALIDATION else (name,))]
    for w in worlds:
        try:
            load_world(w)
        except WorldError as e:
            raise ValueError(str(e)) from None
    return list(dict.fromkeys(worlds))


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="evaluate", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--model",
        action="append",
        choices=MODELS,
        help="repeatable; default: sam. planner / planner_all (with --inprocess) fly the privileged planner knowing what "
        "the last five frames showed / the whole world (uav_sim.planner): the task's limit with the four actions; "
        "planner_map the planner on the local map of the measured depth and odometry only",
    )
    ap.add_argument(
        "--weights",
        nargs="*",
        default=None,
        help="weights files (one per training seed); for several models give MODEL=PATH; default: the packaged weights",
    )
    ap.add_argument(
        "--worlds",
        nargs="+",
        default=["basic", "complex", "turbulent"],
        help="worlds to fly (default: the test worlds); 'validation' stands for the validation worlds "
        "(uav_sim.world.VALIDATION_WORLDS), on which every choice is made (docs/WORLDS.md)",
    )
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
        "--until-crashes",
        type=int,
        default=0,
        metavar="N",
        help="stop a weights file's repeats in a world once N crashes are counted (0: fly all): with --repeats R and "
        "--steps S each row flies until N crashes or R x S steps, long enough to resolve a 2x difference at N about 20",
    )
    add_how_flags(ap)
    return ap


def add_how_flags(ap: argparse.ArgumentParser) -> None:
    """How the policies fly and what is written: ensembles, insight, outputs, in process, crash log, bags, safety, shield."""
    ap.add_argument(
        "--ensemble",
        type=int,
        default=1,
        metavar="K",
        help="fly each K consecutive weights files of a model as one policy, the mean of their Q-values (an "
        "extension; policy_node gets the K files as its weights, comma-separated; one results row per group, its weights column "
        "the files joined by '+')",
    )
    ap.add_argument(
        "--insight-every",
        type=int,
        default=1,
        metavar="K",
        help="measure what the decisions look at on every K-th step (default 1: every step; 0: never). The measure "
        "costs more than the flight (tens of ms a decision for an ensemble): K 10 evaluates several times faster",
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
    ap.add_argument(
        "--record",
        default="",
        metavar="DIR",
        help="keep each flight as a bag (MCAP) in DIR/<model>_<world>_w<weights group>_seed<seed> (needs the ROS nodes)",
    )
    ap.add_argument(
        "--safety",
        action="store_true",
        help="fly through policy_node's safety layer (with --inprocess: the same layer without the node); crashes then "
        "include what it prevented, and its interventions are counted: compare with a run without it, never mix the two",
    )
    ap.add_argument(
        "--shield",
        action="store_true",
        help="the network chooses among the actions the local map says are safe (policy_node's shield; with --inprocess "
        "uav_policy.shield without the node); its overrides are counted. Without it: the network alone",
    )


def checked(ap: argparse.ArgumentParser, a) -> tuple[float | None, float | None, dict]:
    """(the camera, the reward window, the in-process sensor) the arguments ask for; ap.error for what cannot be flown."""
    sensor = {}
    if a.record and a.inprocess:
        ap.error("--record needs the ROS nodes: it records their topics (leave out --inprocess)")
    if a.record and Path(a.record).is_dir() and any(Path(a.record).iterdir()):
        ap.error(f"--record {a.record}: not empty (bags are never overwritten; choose a new folder)")
    if a.crash_log and not a.inprocess:
        ap.error("--crash-log needs --inprocess")
    if a.insight_every < 0:
        ap.error("--insight-every must be >= 0 (0: never)")
    if a.repeats < 1 or a.steps < 1:
        ap.error("--repeats and --steps must be >= 1")
    if a.until_crashes < 0:
        ap.error("--until-crashes must be >= 0 (0: fly every repeat)")
    try:
        a.worlds = expand_worlds(a.worlds)
    except ValueError as e:
        ap.error(f"--worlds: {e}")
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
        from uav_sim.sensor import preset

        given = dict(arg.partition(":=")[::2] for arg in a.sim_arg)
        sensor = {"sensor": given.get("sensor")}  # None: the preset of the weights' camera, else ideal
        try:
            preset(sensor["sensor"] or "ideal")
            sensor["sensor_scale"] = sim_arg_number(a.sim_arg, "sensor_scale")
        except ValueError as e:
            ap.error(f"--sim-arg: {e}")
        if sensor["sensor_scale"] is not None and not 0.05 <= sensor["sensor_scale"] <= 1.0:
            ap.error(f"--sim-arg sensor_scale must lie in [0.05, 1], got {sensor['sensor_scale']:g}")
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
    return hfov_deg, window, sensor


def protocol_line(a, hfov_deg: float | None) -> str:
    """The tables' protocol line: how the flights were flown."""
    from uav_policy.weights import UNRECORDED_HFOV_DEG

    if a.start_yaw_jitter_deg > 0:
        protocol = (
            f"Every episode starts at a random heading (uniform ±{a.start_yaw_jitter_deg:g}°), "
            f"{a.repeats} x {a.steps} steps per weight file (sim seeds {a.seed}..{a.seed + a.repeats - 1})."
        )
    else:
        protocol = "Every episode starts at the world's start pose (the paper's protocol)."
    if a.until_crashes:
        protocol += (
            f" A row stops at its {a.until_crashes}th crash (--until-crashes; over ROS at the end of that repeat):"
            " its steps are its own."
        )
    if a.sim_arg:
        protocol += f" sim_node parameters: {', '.join(a.sim_arg)}."
    if hfov_deg is None and any(m not in PLANNERS for m in a.model or ["sam"]):
        protocol += (
            " Camera: each weights file flies with the field of view it was trained with (its header;"
            f" {UNRECORDED_HFOV_DEG:g}° when it has none)."
        )
    if any(m in PLANNERS for m in a.model or []):
        protocol += (
            " The planner (uav_sim.planner) flies behind the packaged networks' camera and plans on the true geometry"
            " (planner_map: on the local map of the measured depth and odometry)."
        )
    if a.safety:
        protocol += " Flown through policy_node's safety layer (--safety, its default settings)."
    if a.shield:
        protocol += " Shielded (--shield): the network's best action of those the local map says are safe flies."
    if a.inprocess:
        protocol += " Measured in-process (--inprocess: the same simulator and network without the ROS nodes)."
    if a.ensemble > 1:
        protocol += (
            f" Each policy is {a.ensemble} weights files flown as one, acting on the mean of their Q-values"
            f" (--ensemble {a.ensemble}); means and intervals are over these policies."
        )
    return protocol


def planned_runs(ap: argparse.ArgumentParser, a, protocol: str) -> tuple[list, dict, str]:
    """(the runs: (model, its files: one, an ensemble's, or none for the packaged weights), the packaged files per model,
    the protocol line with what the runs fly)."""
    models = a.model or ["sam"]
    planners = [m for m in models if m in PLANNERS]
    if planners and not a.inprocess:
        ap.error(f"--model {planners[0]} needs --inprocess: the planner reads the simulator's world, which no ROS topic carries")
    if planners and any(w.startswith(f"{m}=") for m in planners for w in a.weights or []):
        ap.error(f"--model {planners[0]} flies no weights file")
    runs: list[tuple[str, list[str]]] = []  # (model, its files: one, an ensemble's, or none for the packaged weights)
    # What a run without files flies (policy_node's default); a planner flies none.
    packaged = {m: [] if m in PLANNERS else weights_or_packaged(m, "") for m in models}
    for m in models:
        if m in PLANNERS:
            runs.append((m, []))
            continue
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
    return runs, packaged, protocol


def main(argv=None) -> int:
    ap = parser()
    a = ap.parse_args(argv)
    hfov_deg, window, sensor = checked(ap, a)
    protocol = protocol_line(a, hfov_deg)
    if a.from_csv:
        try:
            results = read_results_csvs(a.from_csv)
        except ValueError as e:
            ap.error(f"--from-csv: {e}")
        md, _ = write_tables(results, Path(a.out), results[0].steps, protocol)
        print(md.read_text())
        return 0
    runs, packaged, protocol = planned_runs(ap, a, protocol)
    params = Path(a.params_dir) if Path(a.params_dir).is_dir() else None
    from tqdm import tqdm

    from uav_policy.weights import WeightsError, load_policy, read_file_config, read_file_window
    from uav_sim.reward import CENTER_WINDOW_FRACTION

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
                ensembles[model, ENSEMBLE_SEP.join(files)] = load_policy(model, members, hfov_deg, window, CENTER_WINDOW_FRACTION)
            except ValueError as e:
                ap.error(f"--ensemble {a.ensemble}, {model}: {e}" if files else f"the packaged {model} weights: {e}")

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    results, crash_rows = [], []
    total = len(runs) * len(a.worlds) * a.steps * a.repeats
    with tqdm(total=total, unit="step", dynamic_ncols=True, disable=None) as bar:

        def measure(model: str, weights: str, world: str, seed: int, group: int, max_crashes: int = 0) -> EvalResult:
            jitter, how = a.start_yaw_jitter_deg, (a.insight_every, a.safety, a.shield)
            if not a.inprocess:
                bag = Path(a.record) / bag_name(model, world, group, seed) if a.record else None
                spec = FlightSpec(
                    model, weights, world, a.steps, seed, jitter, *how, sim_args=tuple(a.sim_arg), epsilon=a.epsilon
                )
                return evaluate_once(spec, params, progress=bar.update, record_to=bag)
            net, net_cfg, hfov, win = ensembles.get((model, weights), (None, None, hfov_deg, window))
            spec = FlightSpec(model, weights, world, a.steps, seed, jitter, *how, hfov, win, max_crashes=max_crashes, **sensor)
            r = evaluate_inprocess(spec, net, net_cfg, crash_log=crash_rows if a.crash_log else None)
            bar.update(a.steps)
            return r

        rows, t0 = len(runs) * len(a.worlds), time.monotonic()
        for group, (model, files) in enumerate(runs):
            weights = ENSEMBLE_SEP.join(files)  # the weights column: "" for the packaged weights
            for world in a.worlds:
                bar.set_description(f"{model} {world} {Path(files[0]).name if files else 'packaged'}")
                flown = []
                for i in range(a.repeats):
                    left = a.until_crashes - sum(f.crashes for f in flown) if a.until_crashes else 0
                    flown.append(measure(model, weights, world, a.seed + i, group, left))
                    if a.until_crashes and sum(f.crashes for f in flown) >= a.until_crashes:
                        bar.update(a.steps * (a.repeats - 1 - i))  # the repeats this row no longer needs
                        break
                r = pool(flown)
                results.append(r)
                # One line per row, on a terminal and in a log alike: with its place in the whole and an ETA.
                elapsed = time.monotonic() - t0
                eta = elapsed / len(results) * (rows - len(results))
                bar.write(
                    f"[{len(results)}/{rows}, {elapsed:.0f} s, ETA {eta:.0f} s] {model:3s} {world:10s} "
                    f"{weights_label(files, model)}: "
                    f"{r.crashes} crashes at {r.crash_sites} sites, mean reward {r.mean_reward:.3f}, {r.distance_m:.0f} m flown"
                    + (f", {r.interventions} safety interventions" if r.interventions >= 0 else "")
                    + (f", {r.shield_overrides} shield overrides" if r.shield_overrides >= 0 else "")
                    + (
                        f"; looks at: entropy {r.insight.entropy:.2f}, map correlation {r.insight.map_correlation:.2f}, "
                        f"faithfulness {r.insight.faithfulness:.2f} (vs the mean map {r.insight.faithfulness_vs_mean_map:.2f})"
                        if r.insight
                        else ""
                    )
                )
    md, csv_path = write_tables(results, Path(a.out), a.steps * a.repeats, protocol)
    print(md.read_text())
    print(f"written: {md} {csv_path}")
    if a.crash_log:
        with open(Path(a.out) / "crashes.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=CRASH_FIELDS)
            w.writeheader()
            w.writerows(crash_rows)
        seen = Counter(r["hit_seen"] for r in crash_rows if r.get("hit_seen"))
        autopsy = ", ".join(f"{n} hit what {SEEN_WORDS[k]}" for k, n in seen.items())
        labelled = [r for r in results if r.teacher_agreement >= 0]
        if labelled:
            share = sum(r.teacher_agreement * r.steps for r in labelled) / sum(r.steps for r in labelled)
            autopsy += f"{'; ' if autopsy else ''}the map teacher's action flown on {100 * share:.1f} % of the steps (ties count)"
        print(f"written: {Path(a.out) / 'crashes.csv'} ({len(crash_rows)} crashes{'; ' + autopsy if autopsy else ''})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
