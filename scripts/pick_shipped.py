#!/usr/bin/env python3
"""Rank training runs by their crashes over evaluate tables, to choose the weights to package.

    python scripts/pick_shipped.py docs/results/round35_fov150_basic_episodes/{fixed,varied}_start/results.csv \\
        docs/results/round36_basic_episodes_second_draw/{fixed,varied}_start/results.csv --model sam

Every row of the given evaluate results.csv files whose model column is `--model` counts for the
run its weights belong to (a run = the folder of its weights files; an ensemble of one run's
snapshots is that run). A run's score is its crashes summed over all its rows (worlds, protocols)
per 1000 steps; ties go to the higher mean reward per step. It prints the `--top` best runs and
their weights column, first the one to ship. The tables are the test worlds, so the chosen run's
own numbers flatter its model: the multi-seed tables are what judge the model.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import PurePath

from compare_models import ENSEMBLE_SEP
from csv_input import read_csv


def run_of(weights: str) -> str:
    """The run folder of a weights column (one file or an ensemble's files); a usage error when an
    ensemble mixes runs or the column is empty (the packaged weights belong to no run)."""
    folders = {str(PurePath(f).parent) for f in weights.split(ENSEMBLE_SEP)}
    if not weights or len(folders) != 1:
        raise ValueError(f"weights {weights!r} do not belong to one training run")
    return folders.pop()


def rank(paths: list[str], model: str) -> list[dict]:
    """One dict per run (run, weights, rows, steps, crashes, per_1000, mean_reward), best first."""
    runs: dict[str, dict] = defaultdict(lambda: {"weights": set(), "rows": 0, "steps": 0, "crashes": 0, "reward": 0.0})
    for path in paths:
        _, rows = read_csv(path, ("model", "world", "weights", "steps", "crashes", "mean_reward"), "an evaluate results.csv")
        for line, row in enumerate(rows, start=2):
            if row["model"] != model:
                continue
            try:
                run = run_of(row["weights"])
                steps, crashes, reward = int(row["steps"]), int(row["crashes"]), float(row["mean_reward"])
            except ValueError as e:
                raise SystemExit(f"{path}, line {line}: {e}") from None
            r = runs[run]
            r["weights"].add(row["weights"])
            r["rows"] += 1
            r["steps"] += steps
            r["crashes"] += crashes
            r["reward"] += reward * steps
    if not runs:
        raise SystemExit(f"no rows of model {model!r} in {', '.join(paths)}")
    out = []
    for run, r in runs.items():
        if len(r["weights"]) != 1:
            raise SystemExit(f"run {run} was flown as {len(r['weights'])} different weights sets: give the tables of one")
        steps = max(r["steps"], 1)
        out.append(
            {
                "run": run,
                "weights": r["weights"].pop(),
                "rows": r["rows"],
                "steps": r["steps"],
                "crashes": r["crashes"],
                "per_1000": 1000.0 * r["crashes"] / steps,
                "mean_reward": r["reward"] / steps,
            }
        )
    return sorted(out, key=lambda r: (r["per_1000"], -r["mean_reward"], r["run"]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="+", help="evaluate results.csv files (the runs' rows in each)")
    ap.add_argument("--model", default="sam", help="the model column's value to read (default sam)")
    ap.add_argument("--top", type=int, default=5, help="how many runs to list (default 5)")
    a = ap.parse_args(argv)
    if a.top < 1:
        ap.error("--top must be >= 1")
    ranked = rank(a.csv, a.model)
    tied = sum(1 for r in ranked if r["per_1000"] == ranked[0]["per_1000"])
    print(f"{len(ranked)} {a.model} runs; {tied} share the fewest crashes ({ranked[0]['per_1000']:.3f} per 1000 steps)")
    print("| rank | run | rows | steps | crashes | per 1000 steps | mean reward |")
    print("|---|---|---|---|---|---|---|")
    for i, r in enumerate(ranked[: a.top], start=1):
        cells = (i, r["run"], r["rows"], r["steps"], r["crashes"], f"{r['per_1000']:.3f}", f"{r['mean_reward']:.4f}")
        print("| " + " | ".join(map(str, cells)) + " |")
    print(f"chosen: {ranked[0]['run']}")
    print(f"weights: {' '.join(ranked[0]['weights'].split(ENSEMBLE_SEP))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
