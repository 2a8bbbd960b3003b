#!/usr/bin/env python3
"""How fast did training runs go once learning ran? Env steps per second from their metrics.csv.

    python scripts/step_rates.py runs/cnn_seed13 runs/sam_seed20 --labels "CNN alone" "SAM alone"

For each run folder: the progress rows of metrics.csv after the first row with updates (the steady
state), their count, the mean and least `env_steps_per_s`, and how many rows fell under 10 and under
5 steps/s (stalls). Prints a Markdown table (round 45 in docs/RESULTS.md: the CNN lockstep runs).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from csv_input import read_csv

from uav_trainer.episodes import steady_metrics_rows

COLUMNS = ("updates", "env_steps_per_s")


def steady_rates(metrics: Path) -> list[float]:
    """env_steps_per_s of the rows after the first one with updates; exits with a message on bad input."""
    _, rows = read_csv(str(metrics), COLUMNS, "a training run's metrics.csv")
    try:
        rates = [float(r["env_steps_per_s"]) for r in steady_metrics_rows(rows)]
    except (TypeError, ValueError):
        raise SystemExit(f"{metrics}: a row's updates or env_steps_per_s is not a number") from None
    if not rates or not all(math.isfinite(x) for x in rates):
        raise SystemExit(f"{metrics}: no finite progress rows after learning started")
    return rates


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="run folders (train's --run-dir), each with a metrics.csv")
    ap.add_argument("--labels", nargs="+", help="a description for each run (default: none)")
    args = ap.parse_args(argv)
    labels = args.labels or [""] * len(args.runs)
    if len(labels) != len(args.runs):
        ap.error(f"--labels: {len(labels)} descriptions for {len(args.runs)} runs")
    rates = [steady_rates(Path(run) / "metrics.csv") for run in args.runs]  # every file read before any output
    print("| run | condition | rows | mean env steps/s | min | rows < 10 /s | rows < 5 /s |")
    print("|---|---|---|---|---|---|---|")
    for run, label, x in zip(args.runs, labels, rates, strict=True):
        slow10, slow5 = sum(v < 10 for v in x), sum(v < 5 for v in x)
        print(f"| {Path(run).name} | {label} | {len(x)} | {sum(x) / len(x):.1f} | {min(x):.1f} | {slow10} | {slow5} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
