"""How much of a crash rate is one failure counted again? Repeated crashes per table and world.

    python scripts/repeat_failures.py docs/results/round29_fov150_snapshots/snap10/fixed_start/results.csv \
        docs/results/round30_seed_pairs/fixed_start/results.csv --labels single pairs --worlds complex

From the paper's fixed start a greedy policy in our deterministic simulator flies the same flight
again after every crash (in Turbulent the particles do not restart, so laps differ), so a policy
that fails once at one place fails there until its 1000 steps run out: a loop. evaluate's
results.csv counts each row's crashes and its distinct crash sites (where a crashing step began, 0.1
m grid), so crashes - sites are the repeats. For each table and world this prints, in Markdown: the
policies (weights rows of --model), how many crash, how many repeat a failure (more crashes than
sites), the repeats as a share of all crashes, the largest row, and the mean crashes per 1000 steps
over the policies beside the same mean with each site counted once. With more than one table a last
row pools their policies per world.

The pooled row answers what the paper's protocol asks of a recipe: its fixed-start mean is about
(the share of policies that loop) x (the crashes of a loop); a loop of 25 crashes in one policy of
twenty adds 1.25 per 1000 steps, more than the paper's Complex figure. Read it beside bar_odds.py.
"""

from __future__ import annotations

import argparse
import sys

from csv_input import add_table_arguments, read_csv, table_labels

COLUMNS = ("model", "world", "weights", "steps", "crashes", "crash_sites")


def counts(rows: list[dict], model: str, path: str) -> dict[str, list[tuple[int, int, int]]]:
    """world -> [(steps, crashes, sites)] for the rows of `model`; exits with a one-line message on a bad row."""
    out: dict[str, list[tuple[int, int, int]]] = {}
    for line, r in enumerate(rows, start=2):
        if r["model"] != model:
            continue
        try:
            steps, crashes, sites = (int(r[c]) for c in ("steps", "crashes", "crash_sites"))
        except (TypeError, ValueError):
            raise SystemExit(f"{path}, line {line}: steps, crashes and crash_sites must be whole numbers") from None
        if steps < 1 or sites < 0 or crashes < sites or (crashes > 0) != (sites > 0):
            raise SystemExit(f"{path}, line {line}: impossible counts (steps {steps}, crashes {crashes}, sites {sites})")
        out.setdefault(r["world"], []).append((steps, crashes, sites))
    return out


def summary(cells: list[tuple[int, int, int]]) -> dict[str, float]:
    """The figures of one table's world (or of several pooled), from (steps, crashes, sites) per policy."""
    n = len(cells)
    crashes = sum(c for _, c, _ in cells)
    repeats = sum(c - s for _, c, s in cells)
    return {
        "policies": n,
        "crashing": sum(c > 0 for _, c, _ in cells),
        "repeating": sum(c > s for _, c, s in cells),
        "repeat_share": repeats / crashes if crashes else 0.0,
        "largest": max(c for _, c, _ in cells),
        "rate": sum(1000.0 * c / t for t, c, _ in cells) / n,
        "site_rate": sum(1000.0 * s / t for t, _, s in cells) / n,
    }


def row(label: str, world: str, f: dict[str, float]) -> str:
    return (
        f"| {label} | {world} | {f['policies']} | {f['crashing']} | {f['repeating']} | {100 * f['repeat_share']:.0f} % "
        f"| {f['largest']} | {f['rate']:.2f} | {f['site_rate']:.2f} |"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_table_arguments(ap, "evaluate results.csv files (the crash_sites column is needed)", "each file's path")
    ap.add_argument("--worlds", nargs="+", help="the worlds to show (default: every world of the tables, in order)")
    args = ap.parse_args(argv)
    labels = table_labels(ap, args, list(args.csv))
    tables = [counts(read_csv(p, COLUMNS, "an evaluate results.csv")[1], args.model, p) for p in args.csv]
    seen = list(dict.fromkeys(w for t in tables for w in t))
    worlds = args.worlds or seen
    missing = [w for w in worlds if w not in seen]
    if missing or not worlds:
        print(f"no {args.model} rows for world(s) {', '.join(missing) or '(none)'} in these tables", file=sys.stderr)
        return 2
    columns = ("table", "world", "policies", "crashing", "repeating a failure", "repeats / crashes", "largest")
    print("| " + " | ".join((*columns, "crashes per 1000", "sites per 1000")) + " |")
    print("|---" * 9 + "|")
    for label, table in zip(labels, tables, strict=True):
        for w in worlds:
            if w in table:
                print(row(label, w, summary(table[w])))
    if len(tables) > 1:
        for w in worlds:
            print(row(f"all {len(tables)} tables", w, summary([c for t in tables for c in t.get(w, [])])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
