"""Is one model's crash rate lower than the other's? A two-sample comparison over training seeds.

    python scripts/compare_models.py docs/results/behaviour/turn_penalty_20_seeds/results.csv [--a sam --b cnn]
    python scripts/compare_models.py new.csv old.csv --by run --a redraw_sam --b turn_sam

Reads an `evaluate` results.csv (one row per weights file and world). For each world and metric
(crashes per 1000 steps, mean reward per step) it prints, in Markdown: the mean of each model over
its weights files (training seeds), the difference a - b with a 95 % bootstrap interval
(percentile, resampling seeds within each model), and a two-sided permutation p-value for "the
two models' seeds come from one distribution" (difference of means, model labels shuffled).
Both are seeded, so the output is reproducible. `--by run` compares two training variants instead
of two models: a row's group is its weights file's folder without `_seed<N>` (runs/turn_sam_seed3/
policy_sam.safetensors -> turn_sam).
"""

from __future__ import annotations

import argparse
import csv
import re
import sys
from collections import defaultdict
from pathlib import PurePath

import numpy as np


def run_name(weights: str) -> str:
    """runs/turn_sam_seed3/policy_sam.safetensors -> turn_sam"""
    return re.sub(r"_seed\d+$", "", PurePath(weights).parent.name)


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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="+", help="evaluate results.csv file(s); rows are joined")
    ap.add_argument("--a", default="sam")
    ap.add_argument("--b", default="cnn")
    ap.add_argument("--resamples", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--by", choices=("model", "run"), default="model", help="group rows by model or by training run")
    a = ap.parse_args(argv)
    values: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    worlds: list[str] = []
    for path in a.csv:
        for r in csv.DictReader(open(path)):
            if r["world"] not in worlds:
                worlds.append(r["world"])
            group = r["model"] if a.by == "model" else run_name(r["weights"])
            values[(group, r["world"], "crashes")].append(1000.0 * int(r["crashes"]) / int(r["steps"]))
            values[(group, r["world"], "reward")].append(float(r["mean_reward"]))
    rng = np.random.default_rng(a.seed)
    A, B = (a.a.upper(), a.b.upper()) if a.by == "model" else (a.a, a.b)
    print(f"{A} - {B} over training seeds ({', '.join(a.csv)}); {a.resamples} resamples, seed {a.seed}.")
    print()
    print(f"| world | metric | {A} mean (n) | {B} mean (n) | difference | 95 % bootstrap CI | permutation p |")
    print("|---|---|---|---|---|---|---|")
    missing = True
    for world in worlds:
        for metric, unit in (("crashes", "crashes / 1000 steps"), ("reward", "reward / step")):
            x, y = (np.array(values[(m, world, metric)]) for m in (a.a, a.b))
            if x.size < 2 or y.size < 2:
                continue
            missing = False
            diff, lo, hi, p = compare(x, y, rng, a.resamples)
            print(
                f"| {world} | {unit} | {x.mean():.3f} ({x.size}) | {y.mean():.3f} ({y.size}) | {diff:+.3f} | "
                f"{lo:+.3f} to {hi:+.3f} | {p:.3f} |"
            )
    if missing:
        print(f"no world has two or more weights files of both {a.a} and {a.b}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
