"""Do the same training seeds fail again? Replicate runs of the same seeds, tested for a seed effect.

    python scripts/seed_effect.py docs/results/round40_push_interval_six_seeds/push_every_50/fixed_start/results.csv \
        docs/results/round40_push_interval_six_seeds/push_every_update/fixed_start/results.csv \
        docs/results/round43_same_seeds_again/fixed_start/results.csv --labels push50 push1 push50_again --world complex

Each table is an evaluate results.csv of runs of the same training seeds (a weights row's seed is its
folder's `_seed<N>`, as in compare_models.py; an ensemble of one run's files counts as that seed), e.g.
the same recipe trained twice over ROS, where thread timing makes every run a fresh draw. For one world
this prints, in Markdown, each seed's crashes per 1000 steps in every table, then two tests of "a seed's
runs fail alike more than chance allows":
- Friedman: the seeds' crash rates are ranked within each table (ties share their mean rank); the
  statistic is the sum over seeds of their rank sums squared, large when the same seeds rank high in
  every table;
- agreement: each run is a crash (at least one) or not; the statistic counts, over seeds, the pairs of a
  seed's runs that agree (with two tables: the seeds whose two runs agree).
The p-values are one-sided permutation tests that shuffle each table's values among the seeds on their
own (so each table keeps its own crash rate): exact over every arrangement when there are at most
2 000 000 (and at most 9 seeds), else from 200 000 seeded draws, as (hits + 1) / (draws + 1). Only seeds
present in every table count; with six seeds and two tables the agreement test cannot go below 1/20 (three
crashing seeds in each), so name a third table when the question needs it.
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys

import numpy as np
from compare_models import crash_rate, seeds_of
from csv_input import add_table_arguments, read_csv, table_labels

COLUMNS = ("model", "world", "weights", "steps", "crashes")
EXACT_LIMIT = 2_000_000
DRAWS = 200_000


def rates_by_seed(rows: list[dict], model: str, world: str, path: str) -> dict[int, float]:
    """seed -> crashes per 1000 steps of the one row of `model` in `world` for that seed; exits with a one-line
    message on a bad row, a row without one seed, or a seed with two rows."""
    out: dict[int, float] = {}
    for line, r in enumerate(rows, start=2):
        if r["model"] != model or r["world"] != world:
            continue
        try:
            steps, crashes = int(r["steps"]), int(r["crashes"])
        except (TypeError, ValueError):
            raise SystemExit(f"{path}, line {line}: steps and crashes must be whole numbers") from None
        if steps < 1 or crashes < 0:
            raise SystemExit(f"{path}, line {line}: impossible counts (steps {steps}, crashes {crashes})")
        seeds = set(seeds_of(r["weights"]) or ())
        if len(seeds) != 1:
            raise SystemExit(f"{path}, line {line}: the weights are not one seed's run (no single _seed<N> folder)")
        seed = seeds.pop()
        if seed in out:
            raise SystemExit(f"{path}, line {line}: seed {seed} has a second {model} row in {world}")
        out[seed] = crash_rate(r)
    return out


def ranks(values: np.ndarray) -> np.ndarray:
    """Ranks from 1, ties sharing their mean rank."""
    _, where, counts = np.unique(values, return_inverse=True, return_counts=True)
    last = np.cumsum(counts)  # each distinct value's ranks run from last - count + 1 to last
    return ((2 * last - counts + 1) / 2)[where]


def friedman_stat(sums: np.ndarray) -> np.ndarray:
    """Sum over seeds (last axis) of the rank sums squared."""
    return (sums**2).sum(axis=-1)


def agreement_stat(sums: np.ndarray, tables: int) -> np.ndarray:
    """Sum over seeds (last axis) of the agreeing pairs of runs, from each seed's count of crashing runs."""
    return (sums * (sums - 1) / 2 + (tables - sums) * (tables - sums - 1) / 2).sum(axis=-1)


def permutation_p(columns: list[np.ndarray], stat, rng: np.random.Generator) -> tuple[float, float, str]:
    """P(stat >= observed) with each column (one table's values over the seeds) shuffled on its own; the first
    column stays put (moving all columns alike changes nothing). Returns (observed, p, 'exact' or 'N draws')."""
    observed = stat(np.sum(columns, axis=0))
    n = len(columns[0])
    distinct = [
        math.factorial(n) // math.prod(math.factorial(k) for k in np.unique(c, return_counts=True)[1]) for c in columns[1:]
    ]
    if math.factorial(n) <= EXACT_LIMIT and math.prod(distinct) <= EXACT_LIMIT:  # n! bounds the enumeration's cost
        sums = columns[0][None, :]
        for a in (np.array(sorted(set(itertools.permutations(c)))) for c in columns[1:]):
            sums = (sums[:, None, :] + a[None, :, :]).reshape(-1, len(columns[0]))
    else:
        sums = np.tile(columns[0], (DRAWS, 1))
        for c in columns[1:]:
            sums = sums + rng.permuted(np.tile(c, (DRAWS, 1)), axis=1)
        hits = int(np.sum(stat(sums) >= observed - 1e-9))
        return observed, (hits + 1) / (DRAWS + 1), f"{DRAWS} draws"  # the observed arrangement counts as one draw
    return observed, float(np.mean(stat(sums) >= observed - 1e-9)), "exact"


def p_text(p: float) -> str:
    return f"{p:.3f}" if p >= 0.001 else f"{p:.1e}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_table_arguments(ap, "evaluate results.csv files, each one run of the same training seeds", "t1 t2 ...")
    ap.add_argument("--world", default="complex", help="the world to read (default complex)")
    args = ap.parse_args(argv)
    labels = table_labels(ap, args, [f"t{i + 1}" for i in range(len(args.csv))])
    if len(args.csv) < 2:
        ap.error("name at least two tables: replicate runs of the same seeds")
    tables = [rates_by_seed(read_csv(p, COLUMNS, "an evaluate results.csv")[1], args.model, args.world, p) for p in args.csv]
    seeds = sorted(set.intersection(*(set(t) for t in tables)))
    if len(seeds) < 3:
        print(
            f"{len(seeds)} seed(s) in every table's {args.model} {args.world} rows; a seed effect needs at least 3",
            file=sys.stderr,
        )
        return 2
    rates = np.array([[t[s] for s in seeds] for t in tables])  # tables x seeds
    print(f"| seed | {' | '.join(labels)} | runs crashing |")
    print(f"|---|{'---|' * len(labels)}---|")
    for j, s in enumerate(seeds):
        print(f"| {s} | {' | '.join(f'{x:.2f}' for x in rates[:, j])} | {int((rates[:, j] > 0).sum())} of {len(tables)} |")
    rng = np.random.default_rng(0)
    rank_cols = [ranks(r) for r in rates]
    crash_cols = [(r > 0).astype(float) for r in rates]
    friedman, p_f, how_f = permutation_p(rank_cols, friedman_stat, rng)
    agree, p_a, how_a = permutation_p(crash_cols, lambda x: agreement_stat(x, len(tables)), rng)
    pairs = len(seeds) * math.comb(len(tables), 2)
    print()
    print(f"{args.model} {args.world}, {len(seeds)} seeds x {len(tables)} tables:")
    print(f"- Friedman (crash rates ranked within each table): statistic {friedman:.1f}, "
          f"one-sided p = {p_text(p_f)} ({how_f})")  # fmt: skip
    print(
        f"- agreement (crash or not): {int(agree)} of {pairs} pairs of a seed's runs agree, one-sided p = {p_text(p_a)} ({how_a})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
