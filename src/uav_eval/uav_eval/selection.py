"""choose: the one network a training run ships, picked on the validation worlds, never on the test worlds.

    ros2 run uav_eval choose runs/sam_seed0                  # train does this at its end
    ros2 run uav_eval choose runs/sam_seed* --across-runs    # one network from several runs (seeds), by the same rule

The rule, the same for SAM and CNN (docs/RESULTS.md, "How we choose"):
- every weights file the run wrote (its snapshots and its final weights) flies each validation world
  (uav_sim.world.VALIDATION_WORLDS: seeded layouts with partitions, doorways or weather that neither training
  nor the test worlds use) from random headings, `--steps` per world, exploit-only, behind the camera it was
  trained behind; world i starts from sim seed i;
- the file with the fewest crashes in all those steps is chosen; between equal counts, the later file
  (more training) wins;
- a file is stopped as soon as it cannot win, so a run's choice costs a few files' full flights.
`--across-runs` compares the files the runs chose (their validation.csv) by the same count, ties to the run
named first: "train N seeds, keep the best on validation" as an explicit, honest choice whose cost is N runs.
Each run folder gets validation.csv (one row per file: steps flown, crashes, whether it was chosen).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import re
import sys
import time
from pathlib import Path

from uav_sim.world import VALIDATION_STEPS

CSV_NAME = "validation.csv"
FIELDS = ("weights", "steps", "crashes", "complete", "chosen")


@dataclasses.dataclass(frozen=True)
class Candidate:
    weights: str
    steps: int  # flown before it finished or could no longer win
    crashes: int
    complete: bool  # flew every validation world to the end


def run_files(run_dir: Path, model: str | None = None) -> list[Path]:
    """A run's weights files, earliest first: policy_<model>_step<N>.safetensors by N, then policy_<model>.safetensors."""
    pattern = re.compile(r"policy_(sam|cnn)(?:_step(\d+))?\.safetensors$")
    found = []
    for p in run_dir.glob("policy_*.safetensors"):
        m = pattern.match(p.name)
        if m and (model is None or m.group(1) == model):
            found.append((float("inf") if m.group(2) is None else int(m.group(2)), p))
    return [p for _, p in sorted(found)]


def choose(files: list[Path], model: str, steps: int = VALIDATION_STEPS, log=print) -> list[Candidate]:
    """Fly the files (earliest first) on the validation worlds by the rule above; the chosen one is the best
    complete Candidate (`best`)."""
    from uav_sim.world import VALIDATION_WORLDS

    from .flights import FlightSpec, evaluate_inprocess

    if not files:
        raise ValueError("no weights files to choose from")
    results: dict[Path, Candidate] = {}
    best: Candidate | None = None
    for path in reversed(files):  # the latest first: it wins ties, so it sets the bar the others must beat
        crashes, flown = 0, 0
        if best is not None and best.crashes == 0:  # nothing earlier can beat a file that never crashed
            results[path] = Candidate(str(path), 0, 0, False)
            continue
        for i, world in enumerate(VALIDATION_WORLDS):
            # An earlier file must have fewer crashes than the best so far: stop it at the count that ties.
            budget = best.crashes - crashes if best is not None else 0
            r = evaluate_inprocess(FlightSpec(model, str(path), world, steps, i, 180.0, insight_every=0, max_crashes=budget))
            crashes, flown = crashes + r.crashes, flown + r.steps
            if best is not None and crashes >= best.crashes:
                break
        else:
            results[path] = best = Candidate(str(path), flown, crashes, True)
            log(f"  {path.name}: {crashes} crashes in {flown} validation steps")
            continue
        results[path] = Candidate(str(path), flown, crashes, False)
        log(f"  {path.name}: stopped after {flown} steps ({crashes} crashes: cannot beat {Path(best.weights).name})")
    return [results[p] for p in files]


def best(candidates: list[Candidate]) -> Candidate:
    """The chosen candidate: fewest crashes among the complete ones; ties to the later (listed after)."""
    complete = [c for c in candidates if c.complete]
    if not complete:
        raise ValueError("no candidate flew the whole validation set")
    return min(reversed(complete), key=lambda c: c.crashes)


def write_csv(run_dir: Path, candidates: list[Candidate], chosen: Candidate) -> Path:
    path = run_dir / CSV_NAME
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(FIELDS)
        for c in candidates:
            w.writerow([Path(c.weights).name, c.steps, c.crashes, int(c.complete), int(c is chosen)])
    tmp.replace(path)
    return path


def read_chosen(run_dir: Path) -> Candidate:
    """The file a run's validation.csv names as chosen (ValueError when there is none or it is unreadable)."""
    path = run_dir / CSV_NAME
    try:
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get("chosen") == "1"]
    except (OSError, csv.Error, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: cannot read it ({e}); run `choose {run_dir}` first") from None
    if len(rows) != 1:
        raise ValueError(f"{path}: names {len(rows)} chosen files, not one")
    r = rows[0]
    try:
        return Candidate(str(run_dir / r["weights"]), int(r["steps"]), int(r["crashes"]), True)
    except (KeyError, ValueError):
        raise ValueError(f"{path}: a malformed chosen row {r}") from None


def choose_run(
    run_dir: Path, model: str, steps: int = VALIDATION_STEPS, log=print, again: bool = False, files: list[Path] | None = None
) -> Candidate:
    """Choose among a run's files (default: all its weights files), write its validation.csv and return the chosen
    file's Candidate. A validation.csv already there for the same files and budget is reused unless `again`."""
    from uav_sim.world import VALIDATION_WORLDS

    files = run_files(run_dir, model) if files is None else files
    if not files:
        raise ValueError(f"{run_dir}: no policy_{model}*.safetensors files")
    if not again:
        try:
            with open(run_dir / CSV_NAME, newline="") as f:
                names = [r["weights"] for r in csv.DictReader(f)]
            c = read_chosen(run_dir)
        except (OSError, KeyError, ValueError, csv.Error):
            pass
        else:
            if names == [p.name for p in files] and c.steps == steps * len(VALIDATION_WORLDS):
                log(f"{run_dir}: chosen before ({CSV_NAME}; --again flies them again)")
                return c
    log(f"choosing one of {len(files)} files of {run_dir} on the validation worlds ({steps} steps each, random headings)")
    candidates = choose(files, model, steps, log)
    chosen = best(candidates)
    write_csv(run_dir, candidates, chosen)
    return chosen


def model_of(run_dir: Path) -> str:
    models = {m for m in ("sam", "cnn") if run_files(run_dir, m)}
    if len(models) != 1:
        what = "holds no weights files" if not models else "holds both models' weights: give --model"
        raise ValueError(f"{run_dir}: {what}")
    return models.pop()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="choose", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="run folders (train's --run-dir)")
    ap.add_argument("--model", choices=("sam", "cnn"), default=None, help="default: the model of the run's files")
    ap.add_argument("--steps", type=int, default=VALIDATION_STEPS, help="steps per validation world and file")
    ap.add_argument("--again", action="store_true", help="fly the files again even where validation.csv has chosen")
    ap.add_argument(
        "--files", nargs="+", type=Path, default=None, help="one run's files to choose among (default: all its weights files)"
    )
    ap.add_argument(
        "--across-runs",
        action="store_true",
        help="then name the one file, of the runs' chosen files, with the fewest validation crashes (ties: the run named first)",
    )
    a = ap.parse_args(argv)
    if a.steps < 1:
        ap.error("--steps must be >= 1")
    if a.files is not None and len(a.runs) != 1:
        ap.error("--files: give one run folder")
    import torch

    torch.set_num_threads(1)  # batch-1 decisions: more threads only contend (evaluate does the same)
    chosen = []
    for run in a.runs:
        t0 = time.monotonic()
        try:
            model = a.model or model_of(run)
            c = choose_run(run, model, a.steps, again=a.again, files=a.files)
        except (ValueError, OSError) as e:
            print(f"choose: {e}", file=sys.stderr)
            return 2
        print(f"chosen: {c.weights} ({c.crashes} crashes in {c.steps} validation steps, {time.monotonic() - t0:.0f} s)")
        chosen.append(c)
    if a.across_runs and len(chosen) > 1:
        if len({c.steps for c in chosen}) != 1:
            print("choose: the runs' chosen files flew different validation budgets (--steps); choose again", file=sys.stderr)
            return 2
        winner = min(chosen, key=lambda c: c.crashes)  # min keeps the first of equal counts
        print(f"chosen across the runs: {winner.weights} ({winner.crashes} crashes in {winner.steps} validation steps)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
