"""Is one model's crash rate lower than the other's? A two-sample comparison over training seeds.

    ros2 run uav_eval compare_models docs/results/behaviour/turn_penalty_20_seeds/results.csv [--a sam --b cnn]
    ros2 run uav_eval compare_models new.csv old.csv --by run --a redraw_sam --b turn_sam
    ros2 run uav_eval compare_models long.csv short.csv --by run --paired --a tl300long_sam --b tl300_sam
    ros2 run uav_eval compare_models min.csv mean.csv --by file --paired --a min --b mean

Reads an `evaluate` results.csv (one row per weights file and world). For each world and metric
(crashes per 1000 steps, mean reward per step) it prints, in Markdown: the mean of each model over
its weights files (training seeds), the difference a - b with a 95 % bootstrap interval
(percentile, resampling seeds within each model), and a two-sided permutation p-value for "the
two models' seeds come from one distribution" (difference of means, model labels shuffled).
Both are seeded, so the output is reproducible. `--by run` compares two training variants instead
of two models: a row's group is its weights file's folder without `_seed<N>` (runs/turn_sam_seed3/
policy_sam.safetensors -> turn_sam; a snapshot policy_sam_step40000.safetensors -> turn_sam_step40000;
an ensemble of three files, evaluate --ensemble 3 -> turn_sam_ens3; three snapshots of one run as an
ensemble -> turn_sam_snap3; ten snapshots of each of two runs -> turn_sam_snap10_ens2). `--by file`
takes two results.csv files and makes the first one's rows group --a and the second's group --b: the
same weights files flown two ways (e.g. evaluate --ensemble-rule min against the mean).
`--paired` (with `--by run` or `--by file`) compares the same training seeds in both groups: the difference is the
mean over seeds of a - b, its interval resamples seeds, and the p-value flips the signs of the
per-seed differences (a sign-flip permutation test), which is stronger than the unpaired test when
seeds differ more from each other than the variants do. Only seeds present in both groups count.
`--pool-worlds NAME` first sums each weights file's rows over all worlds into one world NAME (steps
and crashes summed, reward weighted by steps): e.g. twenty validation layouts as one score per seed.
An ensemble (evaluate --ensemble) is paired with the same ensemble in b if b has it, else with the
mean of b's rows for its members' seeds: does voting beat the members it is made of?
`--bar basic=0,complex=1,turbulent=1` (`--bar paper`: the paper's SAM, these numbers) also counts the
weights files of each group that are at or under the bar in every world named (crashes per 1000
steps), with a two-sided Fisher exact test of the two shares: under the paper's fixed start a mean
over seeds is mostly a few seeds repeating one failure, and this asks how many seeds fly the bar.
"""

from __future__ import annotations

import argparse
import csv
import math
import re
import sys
from collections import defaultdict
from pathlib import PurePath

import numpy as np

from . import ENSEMBLE_SEP  # light: this tool reads tables and needs no torch


def run_name(weights: str) -> str:
    """runs/turn_sam_seed3/policy_sam.safetensors -> turn_sam; .../policy_sam_step40000.safetensors -> turn_sam_step40000;
    an ensemble of three (evaluate --ensemble 3: files joined by '+') -> turn_sam_ens3, or turn_sam_snap3
    when all three are files of one run (its snapshots), or
    turn_sam_snap10_ens2 for ten snapshots of each of two runs"""
    if ENSEMBLE_SEP in weights:
        files = weights.split(ENSEMBLE_SEP)
        folders = [PurePath(f).parent for f in files]
        runs = len(set(folders))
        if runs == 1:
            return f"{_run_folder(PurePath(files[0]))}_snap{len(files)}"
        per_run = len(files) // runs
        if per_run > 1 and all(folders.count(d) == per_run for d in set(folders)):
            return f"{_run_folder(PurePath(files[0]))}_snap{per_run}_ens{runs}"
        return f"{run_name(files[0])}_ens{len(files)}"
    path = PurePath(weights)
    step = re.search(r"_step(\d+)\.safetensors$", path.name)
    return _run_folder(path) + (f"_step{step.group(1)}" if step else "")


def _run_folder(path: PurePath) -> str:
    """The training run a weights file belongs to: its folder without `_seed<N>`."""
    return re.sub(r"_seed\d+$", "", path.parent.name)


def seeds_of(weights: str) -> tuple[int, ...] | None:
    """runs/turn_sam_seed3/policy_sam.safetensors -> (3,); an ensemble -> its members' seeds, e.g. (3, 4, 5);
    None when a file has no _seed<N> folder."""
    seeds = []
    for path in weights.split(ENSEMBLE_SEP):
        m = re.search(r"_seed(\d+)$", PurePath(path).parent.name)
        if not m:
            return None
        seeds.append(int(m.group(1)))
    return tuple(seeds)


def partners(xa: list[float], sa: list, xb: list[float], sb: list) -> tuple[np.ndarray, np.ndarray]:
    """Pairs for --paired: a's row with the b row of the same seeds (snapshot ensembles of one run: the
    same seed, however many snapshots), else (an ensemble against single files) with the mean of the b
    rows of its members' seeds; rows without a partner are left out."""
    seeds = lambda key: tuple(sorted(set(key)))  # noqa: E731
    by_seeds = dict(zip(map(seeds, sb), xb, strict=True))
    pairs = []
    for x, key in zip(xa, map(seeds, sa), strict=True):
        if key in by_seeds:
            pairs.append((key, x, by_seeds[key]))
        elif len(key) > 1 and all((k,) in by_seeds for k in key):
            pairs.append((key, x, float(np.mean([by_seeds[(k,)] for k in key]))))
    pairs.sort()  # by seeds: the resampling sees the same order whatever the rows' order
    return np.array([p[1] for p in pairs]), np.array([p[2] for p in pairs])


def compare(a: np.ndarray, b: np.ndarray, rng: np.random.Generator, resamples: int) -> tuple[float, float, float, float]:
    """(difference of means, bootstrap 2.5 %, 97.5 %, permutation p-value)."""
    diff = float(a.mean() - b.mean())
    boot = rng.choice(a, (resamples, a.size)).mean(1) - rng.choice(b, (resamples, b.size)).mean(1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    pooled = np.concatenate([a, b])
    perm = np.argsort(rng.random((resamples, pooled.size)), axis=1)
    shuffled = pooled[perm]
    d = shuffled[:, : a.size].mean(1) - shuffled[:, a.size :].mean(1)
    p = (1 + np.count_nonzero(np.abs(d) >= abs(diff) - 1e-12)) / (1 + resamples)
    return diff, float(lo), float(hi), float(p)


def compare_paired(a: np.ndarray, b: np.ndarray, rng: np.random.Generator, resamples: int) -> tuple[float, float, float, float]:
    """The same for paired values (a[i] and b[i] from one training seed): bootstrap over seeds, sign-flip test."""
    d = a - b
    diff = float(d.mean())
    lo, hi = np.percentile(rng.choice(d, (resamples, d.size)).mean(1), [2.5, 97.5])
    flipped = (rng.choice((-1.0, 1.0), (resamples, d.size)) * d).mean(1)
    p = (1 + np.count_nonzero(np.abs(flipped) >= abs(diff) - 1e-12)) / (1 + resamples)
    return diff, float(lo), float(hi), float(p)


def pool_worlds(rows: list[dict], name: str) -> list[dict]:
    """One row per (table, model, weights file): its rows' steps and crashes summed, reward weighted by steps."""
    pooled: dict[tuple[int | None, str, str], dict] = {}
    for r in rows:
        key = (r.get("file"), r["model"], r["weights"])  # the same file in two tables (--by file) stays two rows
        p = pooled.setdefault(key, {**r, "world": name, "steps": 0, "crashes": 0, "reward_sum": 0.0})
        p["steps"] += int(r["steps"])
        p["crashes"] += int(r["crashes"])
        p["reward_sum"] += float(r["mean_reward"]) * int(r["steps"])
    return [{**p, "mean_reward": p["reward_sum"] / p["steps"]} for p in pooled.values()]


PAPER_BAR = "basic=0,complex=1,turbulent=1"  # the paper's D3QN-SAM, crashes per 1000 steps


def parse_bar(text: str) -> dict[str, float]:
    """'basic=0,complex=1' (or 'paper') -> {'basic': 0.0, 'complex': 1.0}; ValueError naming the bad part."""
    bar = {}
    for part in (PAPER_BAR if text == "paper" else text).split(","):
        world, eq, value = (x.strip() for x in part.partition("="))
        try:
            limit = float(value)
        except ValueError:
            limit = math.nan
        if not (world and eq and limit >= 0):
            raise ValueError(f"{part!r} is not WORLD=CRASHES_PER_1000 (a number >= 0)")
        bar[world] = limit
    return bar


def fisher_exact(k1: int, n1: int, k2: int, n2: int) -> float:
    """Two-sided Fisher exact p for k1 of n1 against k2 of n2: the probabilities of the tables with the
    same marginal totals (hypergeometric) that are no more likely than the observed one, summed."""
    k = k1 + k2

    def prob(x: int) -> float:
        return math.comb(n1, x) * math.comb(n2, k - x) / math.comb(n1 + n2, k)

    observed = prob(k1)
    return min(1.0, sum(prob(x) for x in range(max(0, k - n2), min(k, n1) + 1) if prob(x) <= observed * (1 + 1e-9)))


def crash_rate(row: dict) -> float:
    """A results row's crashes per 1000 steps, from its counts (not the rounded column)."""
    return 1000.0 * int(row["crashes"]) / int(row["steps"])


def seeds_at_bar(rows: list[dict], group_of, bar: dict[str, float]) -> dict[str, tuple[int, int]]:
    """group -> (weights files at or under `bar` in every world of it, weights files with all its worlds)."""
    rates: dict[tuple[str, str], dict[str, float]] = defaultdict(dict)
    for r in rows:
        rates[(group_of(r), r["weights"])][r["world"]] = crash_rate(r)
    counts: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for (group, _), by_world in rates.items():
        if all(w in by_world for w in bar):
            counts[group][0] += all(by_world[w] <= limit + 1e-9 for w, limit in bar.items())
            counts[group][1] += 1
    return {g: (k, n) for g, (k, n) in counts.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="+", help="evaluate results.csv file(s); rows are joined")
    ap.add_argument("--a", default="sam")
    ap.add_argument("--b", default="cnn")
    ap.add_argument("--resamples", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--by",
        choices=("model", "run", "file"),
        default="model",
        help="group rows by model, by training run, or (file: two csv files) by the file they come from, --a then --b",
    )
    ap.add_argument("--paired", action="store_true", help="with --by run or file: pair the two groups' rows by training seed")
    ap.add_argument("--pool-worlds", metavar="NAME", help="sum each weights file's rows over all worlds into one world NAME")
    ap.add_argument(
        "--bar",
        metavar="WORLD=N,...",
        help=f"also count the seeds at or under N crashes per 1000 steps in every world named ('paper': {PAPER_BAR}), "
        "with a Fisher exact test",
    )
    a = ap.parse_args(argv)
    if a.paired and a.by == "model":
        ap.error("--paired needs --by run or --by file (two variants trained on the same seeds)")
    if a.by == "file" and (len(a.csv) != 2 or a.a == a.b):
        ap.error("--by file needs two results.csv files and two different names --a and --b for them")
    try:
        bar = parse_bar(a.bar) if a.bar else None
    except ValueError as e:
        ap.error(f"--bar: {e}")
    if bar and a.pool_worlds:
        ap.error("--bar counts seeds per world: it does not go with --pool-worlds")
    values: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    seeds: dict[tuple[str, str], list[tuple[int, ...] | None]] = defaultdict(list)  # in the order of values' rows
    worlds: list[str] = []
    rows = [{**r, "file": i} for i, path in enumerate(a.csv) for r in csv.DictReader(open(path))]
    if a.pool_worlds:
        rows = pool_worlds(rows, a.pool_worlds)
    group_of = {
        "model": lambda r: r["model"],
        "run": lambda r: run_name(r["weights"]),
        "file": lambda r: (a.a, a.b)[r["file"]],
    }[a.by]
    for r in rows:
        if r["world"] not in worlds:
            worlds.append(r["world"])
        group = group_of(r)
        values[(group, r["world"], "crashes")].append(crash_rate(r))
        values[(group, r["world"], "reward")].append(float(r["mean_reward"]))
        seeds[(group, r["world"])].append(seeds_of(r["weights"]))
    rng = np.random.default_rng(a.seed)
    A, B = (a.a.upper(), a.b.upper()) if a.by == "model" else (a.a, a.b)
    how = "paired by training seed, sign-flip test" if a.paired else "unpaired"
    print(f"{A} - {B} over training seeds ({', '.join(a.csv)}); {how}; {a.resamples} resamples, seed {a.seed}.")
    print()
    print(f"| world | metric | {A} mean (n) | {B} mean (n) | difference | 95 % bootstrap CI | permutation p |")
    print("|---|---|---|---|---|---|---|")
    missing = True
    for world in worlds:
        for metric, unit in (("crashes", "crashes / 1000 steps"), ("reward", "reward / step")):
            x, y = (np.array(values[(m, world, metric)]) for m in (a.a, a.b))
            if a.paired:  # the seeds both groups have; each must appear once per group and world
                sx, sy = (seeds[(m, world)] for m in (a.a, a.b))
                if None in sx + sy or len(set(sx)) != len(sx) or len(set(sy)) != len(sy):
                    print(f"--paired: {world}: every weights file needs a distinct _seed<N> folder per group", file=sys.stderr)
                    return 2
                x, y = partners(list(x), sx, list(y), sy)
            if x.size < 2 or y.size < 2:
                continue
            missing = False
            diff, lo, hi, p = (compare_paired if a.paired else compare)(x, y, rng, a.resamples)
            print(
                f"| {world} | {unit} | {x.mean():.3f} ({x.size}) | {y.mean():.3f} ({y.size}) | {diff:+.3f} | "
                f"{lo:+.3f} to {hi:+.3f} | {p:.3f} |"
            )
    if missing:
        print(f"no world has two or more weights files {'(seeds) ' if a.paired else ''}of both {a.a} and {a.b}", file=sys.stderr)
        return 2
    if bar:
        counts = seeds_at_bar(rows, group_of, bar)
        (k1, n1), (k2, n2) = (counts.get(m, (0, 0)) for m in (a.a, a.b))
        if not n1 or not n2:
            print(f"--bar: {a.a} or {a.b} has no weights file measured in all of {', '.join(bar)}", file=sys.stderr)
            return 2
        limits = ", ".join(f"{w} {v:g}" for w, v in bar.items())
        print()
        print(
            f"Seeds at or under the bar ({limits} crashes per 1000 steps, every world): {A} {k1} of {n1}, "
            f"{B} {k2} of {n2}; Fisher exact two-sided p = {fisher_exact(k1, n1, k2, n2):.3f}."
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
