"""plot_curves: training curves of several runs (models x seeds) in one figure, like the paper's Figs. 3-4.

    ros2 run uav_eval plot_curves runs/paper_*_seed* --out runs/training_curves.png

Each run's episodes.csv is binned by environment steps; the line is the mean over seeds of a
model and the band spans the seeds' minimum to maximum.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np


def binned(run: Path, bin_steps: int, total: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean episode length and reward of the episodes that ended in each bin of env steps."""
    rows = list(csv.DictReader(open(run / "episodes.csv")))
    edges = np.arange(0, total + bin_steps, bin_steps)
    steps = np.array([int(r["env_step"]) for r in rows])
    length = np.array([float(r["length"]) for r in rows])
    reward = np.array([float(r["reward"]) for r in rows])
    out_l, out_r = [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (steps > lo) & (steps <= hi)
        out_l.append(length[m].mean() if m.any() else np.nan)
        out_r.append(reward[m].mean() if m.any() else np.nan)
    return np.array(out_l), np.array(out_r)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="plot_curves", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run directories (their name must contain sam or cnn)")
    ap.add_argument("--out", default="runs/training_curves.png", help="output image (default: runs/training_curves.png)")
    ap.add_argument("--bin-steps", type=int, default=2500)
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [Path(r) for r in a.runs if (Path(r) / "episodes.csv").is_file()]
    total = max(int(list(csv.DictReader(open(r / "metrics.csv")))[-1]["env_steps"]) for r in runs)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for model, colour in (("sam", "tab:green"), ("cnn", "tab:blue")):
        mine = [r for r in runs if model in r.name]
        if not mine:
            continue
        curves = [binned(r, a.bin_steps, total) for r in mine]
        x = np.arange(1, len(curves[0][0]) + 1) * a.bin_steps
        for ax, k, label in ((axes[0], 0, "mean episode length (steps)"), (axes[1], 1, "mean episode reward")):
            ys = np.array([c[k] for c in curves])
            with np.errstate(all="ignore"):
                ax.plot(x, np.nanmean(ys, 0), color=colour, lw=2, label=f"D3QN-{model.upper()} ({len(mine)} seeds)")
                ax.fill_between(x, np.nanmin(ys, 0), np.nanmax(ys, 0), color=colour, alpha=0.2)
            ax.set_xlabel("environment steps")
            ax.set_ylabel(label)
            ax.set_yscale("symlog")
            ax.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle(f"Training in Basic: mean over seeds, band = min..max (episodes binned per {a.bin_steps} steps)")
    fig.tight_layout()
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    print(f"written: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
