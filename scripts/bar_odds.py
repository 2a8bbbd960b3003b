"""How likely is a set of K training seeds to meet the paper's bar? A bootstrap over the seeds of evaluate tables.

    python scripts/bar_odds.py docs/results/round31_snap3_second_draw/pooled_40_seeds/{fixed_start,varied_start}/results.csv \
        --labels fixed random --set-size 20

Reads one evaluate results.csv per protocol, each with the same weights files flown one way (e.g. from
the fixed start and with random start headings). It draws `--draws` sets of `--set-size` weights files
with replacement, the same files for every table, and prints in Markdown, for each table and for all of
them together, the share of sets whose mean crashes per 1000 steps over the set is at or under the bar
in every world (and in each world alone). That is the issue's reading of "at least as good as the
paper": a mean over training seeds per world. A set that met the bar once tells little when the
next set of the same recipe may not; this says how often a set of that size would.

The files in the tables are taken as the population, so the odds are only as good as the seeds
behind them: a world where none of them crashed gets odds 1 by construction (a rate under one crash
in all their steps cannot be seen), and a rare habit none of them has is not in the draw.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import PurePath

import numpy as np
from compare_models import crash_rate, parse_bar
from csv_input import add_table_arguments, read_csv, table_labels

COLUMNS = ("model", "world", "weights", "steps", "crashes")


def rates_by_weights(rows: list[dict], model: str, worlds) -> tuple[dict[str, dict[str, float]], int]:
    """(weights -> world -> crashes per 1000 steps for this model's weights files with every world of
    `worlds`, the number of its files that lack one of them)."""
    rates: dict[str, dict[str, float]] = defaultdict(dict)
    for r in rows:
        if r["model"] == model and r["world"] in worlds:
            rates[r["weights"]][r["world"]] = crash_rate(r)
    complete = {w: by_world for w, by_world in rates.items() if all(x in by_world for x in worlds)}
    return complete, len(rates) - len(complete)


def at_bar(means: np.ndarray, bar: np.ndarray) -> np.ndarray:
    """Per world (last axis): is the mean crash rate at or under the bar (with room for float rounding)?"""
    return means <= bar + 1e-9


def odds(tables: list[np.ndarray], bar: np.ndarray, set_size: int, draws: int, seed: int) -> tuple[list[np.ndarray], float]:
    """tables: one (files, worlds) array of crash rates each, rows the same files in every table.
    Returns, per table, the share of drawn sets at or under the bar in each world and then in all of
    them (worlds + 1 values), and the share at or under it in every world of every table."""
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, tables[0].shape[0], size=(draws, set_size))
    every = np.ones(draws, dtype=bool)
    shares = []
    for rates in tables:
        ok = at_bar(rates[picks].mean(axis=1), bar)  # (draws, worlds)
        every &= ok.all(axis=1)
        shares.append(np.append(ok.mean(axis=0), ok.all(axis=1).mean()))
    return shares, float(every.mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_table_arguments(ap, "evaluate results.csv files, one per protocol, with the same weights files", "each file's folder")
    ap.add_argument("--bar", default="paper", help="WORLD=CRASHES_PER_1000,... or 'paper' (basic=0,complex=1,turbulent=1)")
    ap.add_argument("--set-size", type=int, help="seeds per drawn set (default: as many as the tables have)")
    ap.add_argument("--draws", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:
        bar = parse_bar(args.bar)
    except ValueError as e:
        ap.error(f"--bar: {e}")
    labels = table_labels(ap, args, [PurePath(p).parent.name or p for p in args.csv])
    if args.draws < 1 or (args.set_size is not None and args.set_size < 1):
        ap.error("--draws and --set-size must be >= 1")
    worlds = list(bar)
    per_table = []
    for label, path in zip(labels, args.csv, strict=True):
        table, incomplete = rates_by_weights(read_csv(path, COLUMNS, "an evaluate results.csv")[1], args.model, worlds)
        if incomplete:
            print(f"{label}: {incomplete} weights file(s) without all of {', '.join(worlds)} left out", file=sys.stderr)
        per_table.append(table)
    files = sorted(set.intersection(*(set(t) for t in per_table)))
    if not files:
        print(f"no {args.model} weights file has all of {', '.join(worlds)} in every table", file=sys.stderr)
        return 2
    for label, table in zip(labels, per_table, strict=True):
        if len(table) > len(files):
            print(f"{label}: {len(table) - len(files)} weights file(s) not in every table left out", file=sys.stderr)
    tables = [np.array([[t[f][w] for w in worlds] for f in files]) for t in per_table]
    limit = np.array([bar[w] for w in worlds])
    k = args.set_size or len(files)
    shares, every = odds(tables, limit, k, args.draws, args.seed)

    pct = lambda x: f"{100 * x:.1f} %"  # noqa: E731
    bar_text = ", ".join(f"{w} <= {bar[w]:g}" for w in worlds)
    print(f"# Odds that {k} seeds meet the bar ({bar_text} crashes per 1000 steps, mean over the seeds)\n")
    print(
        f"{len(files)} {args.model} weights files in every table; {args.draws} sets of {k} drawn from them with "
        f"replacement, the same files in every table (seed {args.seed}). 'all {len(files)}': the mean over all the "
        "files, as the tables have it.\n"
    )
    print(f"| table | all {len(files)}: {' / '.join(worlds)} | at the bar | " + " | ".join(worlds) + " | every world |")
    print("|---" * (len(worlds) + 4) + "|")
    yes = lambda met: "yes" if met else "no"  # noqa: E731
    met_all = True
    for label, rates, share in zip(labels, tables, shares, strict=True):
        means = rates.mean(axis=0)
        met = bool(at_bar(means, limit).all())
        met_all &= met
        print(f"| {label} | {' / '.join(f'{m:.2f}' for m in means)} | {yes(met)} | " + " | ".join(pct(s) for s in share) + " |")
    if len(tables) > 1:
        print(f"| every table | | {yes(met_all)} | " + " | " * (len(worlds) - 1) + f" | {pct(every)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
