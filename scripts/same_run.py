#!/usr/bin/env python3
"""Is a training run the same as another? Episodes, weights and flights, compared exactly.

    python scripts/same_run.py runs/sam_seed0 runs/inproc_sam_seed0
    python scripts/same_run.py runs/sam_seed0 runs/inproc_sam_seed0 --tables runs/eval_a/results.csv runs/eval_b/results.csv
    python scripts/same_run.py runs/sam_seed4 --packaged sam

Without --tables: the two run folders' episodes.csv (byte for byte) and every policy_*.safetensors
file the first run wrote, tensor by tensor (a file the second lacks is reported). With --packaged
MODEL: the file the run chose on the validation worlds (its validation.csv, written by `choose`) against the
one network packaged with uav_policy for MODEL; for a packaged set of several files, the run's snapshots in
step order, then its final weights, against them in their order. With --tables A B:
the evaluate rows of the first run in table A against the rows of the second run in table B, every
column but the weights paths (a row belongs to a run when all its weights files lie in that run's
folder; the folders need not exist). Prints one line per item and 'same' or 'DIFFERENT' last; exits
1 when anything differs (e.g. `train` against `python -m uav_trainer.inprocess` with the same recipe and seed).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path, PurePath

import numpy as np
from csv_input import read_csv
from safetensors import SafetensorError
from safetensors.numpy import load_file

from uav_eval import ENSEMBLE_SEP

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "src" / p) for p in ("uav_common", "uav_sim", "uav_policy", "uav_trainer")]


def same_weights(a: Path, b: Path) -> str | None:
    """None when the two safetensors files hold equal tensors (names, dtypes, values), else what differs."""
    try:
        x, y = load_file(a), load_file(b)
    except (OSError, SafetensorError) as e:
        return f"unreadable: {e}"
    if sorted(x) != sorted(y):
        return f"tensor names differ ({len(x)} and {len(y)} tensors)"
    bad = [k for k in x if x[k].dtype != y[k].dtype or not np.array_equal(x[k], y[k])]
    return f"{len(bad)} of {len(x)} tensors differ, e.g. {bad[0]}" if bad else None


def compare_runs(a: Path, b: Path) -> list[tuple[str, str | None]]:
    """(item, None or what differs) for episodes.csv and each weights file of run `a`."""
    out = []
    try:
        ea, eb = (a / "episodes.csv").read_bytes(), (b / "episodes.csv").read_bytes()
        na, nb = (e.count(b"\n") - 1 for e in (ea, eb))
        out.append((f"episodes.csv ({na} episodes)", None if ea == eb else f"differs ({nb} episodes in {b})"))
    except OSError as e:
        out.append(("episodes.csv", f"unreadable: {e.strerror}"))
    files = sorted(p.name for p in a.glob("policy_*.safetensors"))
    if not files:
        out.append((f"{a}/policy_*.safetensors", "no weights files"))
    for name in files:
        other = b / name
        out.append((name, same_weights(a / name, other) if other.exists() else f"missing in {b}"))
    return out


def chosen_file(run: Path) -> Path | None:
    """The weights file a run's validation.csv marks as chosen, or None."""
    path = run / "validation.csv"
    if not path.is_file():
        return None
    _, rows = read_csv(str(path), ("weights", "chosen"), "a choose validation.csv")
    rows = [r for r in rows if r["chosen"] == "1"]
    return run / rows[0]["weights"] if len(rows) == 1 and rows[0].get("weights") else None


def compare_packaged(run: Path, model: str) -> list[tuple[str, str | None]]:
    from uav_eval.selection import run_files  # the snapshots in step order, then the final weights
    from uav_policy.weights import packaged_weights

    mine, packaged = run_files(run, model), packaged_weights(model)
    if len(packaged) == 1:  # one network: the file the run chose
        chosen = chosen_file(run)
        if chosen is None:
            return [(str(run), "no validation.csv naming one chosen file (run `choose` on it)")]
        return [(f"{chosen.name} (chosen) = packaged {packaged[0].name}", same_weights(chosen, packaged[0]))]
    if len(mine) != len(packaged):
        return [(str(run), f"{len(mine)} weights files against {len(packaged)} packaged for {model}")]
    return [(f"{p.name} = packaged {q.name}", same_weights(p, q)) for p, q in zip(mine, packaged, strict=True)]


def rows_of_run(path: str, run: Path) -> dict[tuple[str, str], dict]:
    """The rows of `run` in an evaluate results.csv, keyed by (model, world), weights column dropped."""
    _, rows = read_csv(path, ("model", "world", "weights"), "an evaluate results.csv")
    mine = {}
    for row in rows:
        if {PurePath(f).parent for f in row["weights"].split(ENSEMBLE_SEP)} == {PurePath(run)}:
            mine[(row["model"], row["world"])] = {k: v for k, v in row.items() if k != "weights"}
    return mine


def compare_tables(a: Path, b: Path, table_a: str, table_b: str) -> list[tuple[str, str | None]]:
    ra, rb = rows_of_run(table_a, a), rows_of_run(table_b, b)
    if not ra:
        return [(table_a, f"no rows of {a}")]
    out = []
    for key in sorted(ra):
        if key not in rb:
            out.append((" ".join(key), f"no row of {b} in {table_b}"))
            continue
        diff = [k for k in ra[key] if ra[key][k] != rb[key].get(k)]
        out.append((" ".join(key), f"{', '.join(diff)} differ" if diff else None))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_a", type=Path)
    ap.add_argument("run_b", type=Path, nargs="?", help="the other run (not with --packaged)")
    ap.add_argument("--tables", nargs=2, metavar=("A_CSV", "B_CSV"), help="compare the runs' evaluate rows instead")
    ap.add_argument("--packaged", metavar="MODEL", choices=("sam", "cnn"), help="compare run_a with the packaged weights")
    a = ap.parse_args(argv)
    if (a.run_b is None) != bool(a.packaged) or (a.packaged and a.tables):
        ap.error("give a second run, or --packaged MODEL (without --tables)")
    if a.packaged:
        items = compare_packaged(a.run_a, a.packaged)
    elif a.tables:
        items = compare_tables(a.run_a, a.run_b, *a.tables)
    else:
        for run in (a.run_a, a.run_b):
            if not run.is_dir():
                ap.error(f"{run} is not a run folder")
        items = compare_runs(a.run_a, a.run_b)
    for item, diff in items:
        print(f"{item}: {'identical' if diff is None else diff}")
    same = all(diff is None for _, diff in items)
    print("same" if same else "DIFFERENT")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
