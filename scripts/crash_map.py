#!/usr/bin/env python3
"""Plan views of worlds, with the crashes of an evaluation's crash log drawn where they happened.

    python scripts/crash_map.py --crashes docs/results/round16_basic_mix/varied_start/crashes.csv \\
        --out crash_map.png
    python scripts/crash_map.py --worlds basic random:7 random_partitions:7 --out layouts.png

Each crash (a row of `evaluate --inprocess --crash-log`'s crashes.csv) is a dot at the pose where the
crashing step began, with a short line along the heading, coloured by run (the folder of its weights
file). Prints the crash count per world and run, and how many crashes were nearest a wall, a
cylinder or a box.
"""

from __future__ import annotations

import argparse
import collections
import math
import sys
from pathlib import Path

from csv_input import read_csv

COLUMNS = ("world", "weights", "x_m", "y_m", "yaw_deg")


def read_crashes(path: str) -> list[dict]:
    rows = read_csv(path, COLUMNS, "a crash log")[1]
    for i, r in enumerate(rows, start=2):
        try:
            r["x"], r["y"], r["yaw"] = float(r["x_m"]), float(r["y_m"]), math.radians(float(r["yaw_deg"]))
        except ValueError:
            raise SystemExit(f"{path} line {i}: x_m, y_m and yaw_deg must be numbers") from None
        r["run"] = Path(r["weights"]).parent.name or r["weights"]
    return rows


def nearest_surface(world, x: float, y: float, yaw: float) -> str:
    """'wall', 'cylinder' or 'box': the surface nearest the crashing step's path, approximated by the
    points 0, 0.25 and 0.5 m (a step at 1 m/s) ahead of the pose the step began at."""
    from uav_sim.simulator import obstacle_distance_m

    best = (math.inf, "wall")
    for ahead in (0.0, 0.25, 0.5):
        px, py = x + ahead * math.cos(yaw), y + ahead * math.sin(yaw)
        wall = min(world.length_m / 2 - abs(px), world.width_m / 2 - abs(py))
        best = min(best, (wall, "wall"), *((obstacle_distance_m(o, px, py), o.shape) for o in world.obstacles))
    return best[1]


def draw_world(ax, world) -> None:
    from matplotlib.patches import Circle, Rectangle

    hl, hw = world.length_m / 2, world.width_m / 2
    ax.add_patch(Rectangle((-hl, -hw), world.length_m, world.width_m, fill=False, lw=2, ec="k"))
    for o in world.obstacles:
        if o.shape == "cylinder":
            ax.add_patch(Circle((o.x_m, o.y_m), o.radius_m, color="0.45"))
        else:
            corner = (o.x_m - o.size_x_m / 2, o.y_m - o.size_y_m / 2)
            ax.add_patch(Rectangle(corner, o.size_x_m, o.size_y_m, angle=o.yaw_deg, rotation_point="center", color="0.45"))
    sx, sy, _ = world.start_xyz_m
    yaw = math.radians(world.start_yaw_deg)
    ax.annotate("", (sx + 0.8 * math.cos(yaw), sy + 0.8 * math.sin(yaw)), (sx, sy), arrowprops={"arrowstyle": "->", "lw": 2})
    ax.plot([sx], [sy], "k^", ms=8, label="start")
    ax.set_xlim(-hl - 0.5, hl + 0.5)
    ax.set_ylim(-hw - 0.5, hw + 0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--crashes", nargs="*", default=[], metavar="CSV", help="crash logs (evaluate --crash-log)")
    ap.add_argument("--worlds", nargs="*", default=None, help="worlds to draw (default: those in the crash logs)")
    ap.add_argument("--out", default="crash_map.png", help="PNG to write")
    ap.add_argument("--title", default="", help="figure title")
    a = ap.parse_args(argv)
    rows = [r for path in a.crashes for r in read_crashes(path)]
    names = a.worlds if a.worlds is not None else list(dict.fromkeys(r["world"] for r in rows))
    if not names:
        ap.error("nothing to draw: give --worlds, or --crashes with at least one crash")

    from uav_sim.world import WorldError, load_world

    try:
        worlds = [load_world(n) for n in names]
    except WorldError as e:
        raise SystemExit(f"cannot draw a world: {e}") from None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = list(dict.fromkeys(r["run"] for r in rows))
    colours = {run: plt.get_cmap("tab10" if len(runs) <= 10 else "tab20")(i % 20) for i, run in enumerate(runs)}
    fig, axes = plt.subplots(1, len(worlds), figsize=(6.0 * len(worlds), 5.0), squeeze=False)
    for ax, name, world in zip(axes[0], names, worlds, strict=True):
        draw_world(ax, world)
        here = [r for r in rows if r["world"] == name]
        counts = collections.Counter(r["run"] for r in here)
        for run in runs:
            mine = [r for r in here if r["run"] == run]
            if not mine:
                continue
            ax.scatter(
                [r["x"] for r in mine], [r["y"] for r in mine], s=22, color=colours[run], label=f"{run} ({len(mine)})", zorder=3
            )
            for r in mine:
                ax.plot(
                    [r["x"], r["x"] + 0.4 * math.cos(r["yaw"])],
                    [r["y"], r["y"] + 0.4 * math.sin(r["yaw"])],
                    color=colours[run],
                    lw=1,
                )
        ax.set_title(f"{name}: {len(here)} crashes" if a.crashes else name)
        if here:
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
        if a.crashes:
            kinds = collections.Counter(nearest_surface(world, r["x"], r["y"], r["yaw"]) for r in here)
            print(
                f"{name}: {len(here)} crashes"
                + (f" (nearest surface: {', '.join(f'{k} {n}' for k, n in kinds.most_common())})" if here else "")
                + "".join(f"; {run} {n}" for run, n in counts.most_common())
            )
    if a.title:
        fig.suptitle(a.title)
    fig.tight_layout()
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=90)
    print(f"written: {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
