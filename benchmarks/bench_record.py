"""Recording figures: the lockstep loop (sim_node + policy_node flying the packaged SAM through ROS, as
`evaluate` and `fly --lockstep` run it) in steps/s with `record` keeping every default topic against
without it, in the same run (alternating, so drift hits both), and the bag's size per 1000 steps.

Run: source .venv/bin/activate && source install/setup.bash && python benchmarks/bench_record.py
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from uav_eval.flights import FlightSpec
from uav_eval.ros_flights import evaluate_once

WARMUP = 100  # steps before the clock starts: start-up and discovery are not the loop


def loop_rate(steps: int, bag: Path | None) -> float:
    """Steps/s of the lockstep loop between step WARMUP and step `steps`."""
    marks = {}
    done = [0]

    def progress(n: int) -> None:
        done[0] += n
        if done[0] >= WARMUP and "t0" not in marks:
            marks["t0"], marks["s0"] = time.perf_counter(), done[0]

    evaluate_once(FlightSpec("sam", "", "basic", steps), progress=progress, record_to=bag)
    return (done[0] - marks["s0"]) / (time.perf_counter() - marks["t0"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--pairs", type=int, default=2, help="runs without and with the recorder, alternating")
    a = ap.parse_args()
    os.environ.update(ROS_DOMAIN_ID="224", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    plain, recorded, sizes = [], [], []
    with tempfile.TemporaryDirectory() as d:
        for i in range(a.pairs):
            plain.append(loop_rate(a.steps, None))
            bag = Path(d) / f"bag{i}"
            recorded.append(loop_rate(a.steps, bag))
            sizes.append(sum(f.stat().st_size for f in bag.iterdir()) / 1e6)
    base, rec = sum(plain) / len(plain), sum(recorded) / len(recorded)
    print(f"lockstep loop without the recorder: {base:7.1f} steps/s  (runs: {', '.join(f'{r:.1f}' for r in plain)})")
    print(f"lockstep loop with the recorder   : {rec:7.1f} steps/s  (runs: {', '.join(f'{r:.1f}' for r in recorded)})")
    print(f"ratio with/without                : {rec / base:7.2f}  (target >= 0.9)")
    per_1000 = sum(sizes) / len(sizes) * 1000 / a.steps
    print(f"bag size per 1000 steps           : {per_1000:7.1f} MB (all default topics, 64x64 depth)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
