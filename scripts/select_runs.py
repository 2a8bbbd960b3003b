#!/usr/bin/env python3
"""Choose training runs (seeds) on validation layouts, then see how the chosen ones fly the test worlds.

    python scripts/select_runs.py runs/val/results.csv --group 4 \\
        --test docs/results/x/varied_start/results.csv docs/results/x/fixed_start/results.csv --out selected/

The validation results.csv is an `evaluate` run of several training seeds' weights on layouts that
neither training nor the test worlds use (e.g. `random:300..309 random_partitions:300..309`). A
run's validation score is its crashes per 1000 steps pooled over those layouts; ties go to the
higher mean reward per step. The runs of each model, in seed order, are cut into groups of
`--group` consecutive seeds and the best-scoring run of each group is chosen, as a user who trains
`--group` seeds and keeps one would do. Nothing of the test worlds enters the choice.

With `--test` (evaluate results.csv files of the same weights on the test worlds) it prints, per
model and test file: every run's validation and test crash rates; Spearman's rank correlation
between validation and test crash rates over runs, with a two-sided permutation p-value; and per
world, the chosen runs' mean against the mean of their groups (what keeping a random seed of each
group gives on average), with a bootstrap interval and sign-flip p-value over groups. Test files
in folders of the same name are joined (e.g. `x/varied_start/results.csv x/cnn/varied_start/results.csv`:
one protocol, two models). `--out` writes the chosen runs' test rows as `<out>/<folder name>/results.csv`,
for `evaluate --from-csv` (the usual tables) and `compare_models.py`.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np
from compare_models import compare_paired, pool_worlds, seeds_of
from csv_input import read_csv


def read_rows(path: str) -> tuple[list[str], list[dict]]:
    """(header, rows) of an evaluate results.csv; each row keeps its text and gains _n, _c, _r
    (steps, crashes, mean reward per step) as numbers."""
    header, rows = read_csv(path, ("model", "world", "weights", "steps", "crashes", "mean_reward"), "an evaluate results.csv")
    for i, r in enumerate(rows, start=2):
        try:
            r["_n"], r["_c"], r["_r"] = int(r["steps"]), int(r["crashes"]), float(r["mean_reward"])
        except ValueError:
            raise SystemExit(f"{path} line {i}: steps, crashes and mean_reward must be numbers") from None
        if r["_n"] <= 0 or r["_c"] < 0:
            raise SystemExit(f"{path} line {i}: steps must be positive and crashes not negative")
    return header, rows


def validation_scores(rows: list[dict]) -> dict[tuple[str, str], tuple[float, float]]:
    """(model, weights) -> (crashes per 1000 steps, mean reward per step), pooled over the rows' worlds."""
    return {
        (r["model"], r["weights"]): (1000.0 * r["crashes"] / r["steps"], r["mean_reward"])
        for r in pool_worlds(rows, "validation")
    }


def choose(scores: dict[str, tuple[float, float]], group: int, model: str) -> list[tuple[list[str], str]]:
    """[(the group's weights files in seed order, the chosen one)] for one model's runs."""
    keyed = []
    for weights in scores:
        seeds = seeds_of(weights)
        if seeds is None or len(seeds) != 1:
            raise SystemExit(f"{model}: {weights}: every weights file must sit in a runs/<name>_seed<N>/ folder")
        keyed.append((seeds[0], weights))
    keyed.sort()
    if len({s for s, _ in keyed}) != len(keyed):
        raise SystemExit(f"{model}: two weights files share a seed; give one run per seed")
    if group < 1 or len(keyed) % group:
        raise SystemExit(f"--group {group} must divide the number of {model} runs ({len(keyed)})")
    groups = [[w for _, w in keyed[i : i + group]] for i in range(0, len(keyed), group)]
    return [(g, min(g, key=lambda w: (scores[w][0], -scores[w][1]))) for g in groups]


def ranks(x: np.ndarray) -> np.ndarray:
    """Ranks from 1, ties given their mean rank."""
    order = np.argsort(x, kind="stable")
    r = np.empty(x.size)
    r[order] = np.arange(1, x.size + 1)
    for v in np.unique(x):
        r[x == v] = r[x == v].mean()
    return r


def spearman(x: np.ndarray, y: np.ndarray, rng: np.random.Generator, resamples: int) -> tuple[float, float]:
    """(Spearman's rho, two-sided permutation p); rho is nan when either side is constant."""
    rx, ry = ranks(x), ranks(y)
    if rx.std() == 0 or ry.std() == 0:
        return float("nan"), 1.0
    rho = float(np.corrcoef(rx, ry)[0, 1])
    perm = np.argsort(rng.random((resamples, ry.size)), axis=1)
    shuffled = ry[perm] - ry.mean()
    rhos = (shuffled @ (rx - rx.mean())) / (np.linalg.norm(rx - rx.mean()) * np.linalg.norm(ry - ry.mean()))
    p = (1 + np.count_nonzero(np.abs(rhos) >= abs(rho) - 1e-12)) / (1 + resamples)
    return rho, float(p)


def report(label: str, model: str, scores, chosen, rows: list[dict], rng: np.random.Generator, resamples: int) -> None:
    """One test file's tables for one model: every run, then validation against test per world."""
    per = {(r["weights"], r["world"]): 1000.0 * r["_c"] / r["_n"] for r in rows if r["model"] == model}
    worlds = list(dict.fromkeys(world for _, world in per))
    lacking = [w for w in scores if any((w, world) not in per for world in worlds)]
    if not worlds or lacking:
        which = lacking[0] if lacking else "any run"
        raise SystemExit(f"{label}: no {model} test rows for {which} (every run needs every world)")
    picked = {c for _, c in chosen}
    print(f"### {label}: crashes per 1000 steps")
    print()
    print("| seed | validation | validation reward | " + " | ".join(worlds) + " |")
    print("|---|---|---|" + "---|" * len(worlds))
    for g, _ in chosen:
        for w in g:
            cells = " | ".join(f"{per[(w, world)]:.2f}" for world in worlds)
            print(f"| {seeds_of(w)[0]}{' (chosen)' if w in picked else ''} | {scores[w][0]:.2f} | {scores[w][1]:.3f} | {cells} |")
    print()
    print(
        "| world | Spearman rho, validation vs test (p) | chosen mean (n) | group mean | chosen - group | 95 % CI | sign-flip p |"
    )
    print("|---|---|---|---|---|---|---|")
    runs = list(scores)
    for world in worlds:
        rho, p_rho = spearman(np.array([scores[w][0] for w in runs]), np.array([per[(w, world)] for w in runs]), rng, resamples)
        x = np.array([per[(c, world)] for _, c in chosen])
        y = np.array([np.mean([per[(w, world)] for w in g]) for g, _ in chosen])
        diff, lo, hi, p = compare_paired(x, y, rng, resamples)
        cells = f"{x.mean():.3f} ({x.size}) | {y.mean():.3f} | {diff:+.3f} | {lo:+.3f} to {hi:+.3f} | {p:.3f}"
        corr = "n/a (a constant column)" if np.isnan(rho) else f"{rho:+.2f} ({p_rho:.3f})"
        print(f"| {world} | {corr} | {cells} |")
    print()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("validation", help="evaluate results.csv of the runs on validation layouts")
    ap.add_argument("--group", type=int, required=True, help="choose one run of each this many consecutive seeds")
    ap.add_argument("--test", nargs="*", default=[], help="evaluate results.csv files of the same weights on the test worlds")
    ap.add_argument("--out", help="write the chosen runs' test rows to OUT/<test file's folder>/results.csv")
    ap.add_argument("--resamples", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if a.resamples < 1:
        ap.error("--resamples must be >= 1")
    if a.out and not a.test:
        ap.error("--out needs --test (it writes the chosen runs' test rows)")
    val = validation_scores(read_rows(a.validation)[1])
    tests: dict[str, tuple[list[str], list[dict]]] = {}  # test files joined by their folder's name
    for t in a.test:
        header, rows = read_rows(t)
        tests.setdefault(Path(t).parent.name or t, (header, []))[1].extend(rows)
    rng = np.random.default_rng(a.seed)
    picked: set[str] = set()
    for model in sorted({m for m, _ in val}):
        scores = {w: s for (m, w), s in val.items() if m == model}
        chosen = choose(scores, a.group, model)
        picked |= {c for _, c in chosen}
        print(f"## {model}: one run of each {a.group} consecutive seeds, chosen on {a.validation}")
        print()
        for label, (_, rows) in tests.items():
            report(label, model, scores, chosen, rows, rng, a.resamples)
    for label, (header, rows) in tests.items():
        if a.out:
            path = Path(a.out) / label / "results.csv"
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=header, extrasaction="ignore")
                writer.writeheader()
                writer.writerows(r for r in rows if r["weights"] in picked)
            print(f"written: {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
