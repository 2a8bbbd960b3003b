"""Re-measure every row of an `evaluate` results.csv without ROS and say which rows differ.

The simulator and a greedy policy are deterministic, so a run through the ROS nodes must give
exactly what `uav_trainer.evaluate.evaluate_inprocess` gives for the same weights, world, sim
seeds, start jitter and field of view. A difference means the lockstep loop misbehaved (e.g. a
command was applied twice). Give the same protocol flags that produced the table:

    python scripts/crosscheck_eval.py docs/results/varied_start/paper_training/results.csv \
        --start-yaw-jitter-deg 180 --repeats 5

Exit code 1 when any row differs.
"""

from __future__ import annotations

import argparse
import csv

import torch

from uav_trainer.evaluate import evaluate_inprocess, pool


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("csv")
    ap.add_argument("--start-yaw-jitter-deg", type=float, default=0.0)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hfov-deg", type=float, default=90.0)
    a = ap.parse_args()
    torch.set_num_threads(1)
    differ = 0
    for r in csv.DictReader(open(a.csv)):
        steps = int(r["steps"]) // a.repeats
        local = pool(
            [
                evaluate_inprocess(
                    r["model"],
                    r["weights"],
                    r["world"],
                    steps,
                    seed=a.seed + i,
                    start_yaw_jitter_deg=a.start_yaw_jitter_deg,
                    hfov_deg=a.hfov_deg,
                )
                for i in range(a.repeats)
            ]
        )
        same = local.crashes == int(r["crashes"]) and abs(local.mean_reward - float(r["mean_reward"])) < 1e-3
        differ += not same
        print(
            f"{'same' if same else 'DIFFERS'}  {r['model']} {r['world']} {r['weights']}: ROS {r['crashes']} crashes, "
            f"reward {float(r['mean_reward']):.4f}; in-process {local.crashes} crashes, reward {local.mean_reward:.4f}",
            flush=True,
        )
    print(f"{a.csv}: {differ} row(s) differ")
    return 1 if differ else 0


if __name__ == "__main__":
    raise SystemExit(main())
