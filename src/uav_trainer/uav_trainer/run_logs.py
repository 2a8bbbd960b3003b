"""A training run's logs beside its metrics.csv: the metrics columns, machine.jsonl (what decides a run's
floating-point results beyond the code and seed) and curves.png (no ROS)."""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

METRICS_COLUMNS = (
    "wall_s",
    "env_steps",
    "updates",
    "episodes",
    "mean_episode_length",
    "mean_episode_reward",
    "loss",
    "q_mean",
    "epsilon",
    "env_steps_per_s",
    "updates_per_s",
)


def machine_info() -> dict:
    """What decides a run's floating-point results beyond the code, seed and packages."""
    processor = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            processor = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), processor)
    except OSError:
        pass
    return {
        "processor": processor or platform.machine(),
        "machine": platform.machine(),
        "cpu_kernels": torch.backends.cpu.get_cpu_capability(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "torch_threads": torch.get_num_threads(),
    }


def record_machine(run_dir: Path, env_steps: int) -> dict:
    """Append this start's machine_info() to run_dir/machine.jsonl; the info."""
    info = machine_info()
    line = {"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "env_steps": env_steps, **info}
    with open(Path(run_dir) / "machine.jsonl", "a") as f:
        f.write(json.dumps(line) + "\n")
    return info


def plot_curves(history: list, model: str, seed: int, run_dir: Path) -> Path | None:
    """run_dir/curves.png from (env step, episode length, episode reward) rows: mean episode length and reward
    against environment steps (paper Figs. 3-4); None with fewer than two episodes."""
    hist = list(history)
    if len(hist) < 2:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.array([h[0] for h in hist])
    k = max(1, min(20, len(hist) // 5))
    smooth = lambda x: np.convolve(x, np.ones(k) / k, mode="valid")  # noqa: E731
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, col, label in ((axes[0], 1, "mean episode length (steps)"), (axes[1], 2, "mean episode reward")):
        vals = np.array([h[col] for h in hist], dtype=float)
        ax.plot(steps, vals, alpha=0.25, lw=0.8)
        ax.plot(steps[k - 1 :], smooth(vals), lw=1.8)
        ax.set_xlabel("environment steps")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle(f"D3QN-{model.upper()} training, seed {seed} (moving mean of {k} episodes)")
    fig.tight_layout()
    out = Path(run_dir) / "curves.png"
    tmp = Path(run_dir) / ".curves.png.tmp.png"
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(out)
    return out
