"""Top-down maps of worlds: the room, its obstacles, the start pose and its weather (no ROS).

    python -m uav_eval.world_maps validation --out docs/figures/validation_worlds.png
    python -m uav_eval.world_maps basic complex random:3 my_world.yaml --out worlds.png

'validation' stands for the validation worlds (uav_sim.world.VALIDATION_WORLDS).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def draw(ax, world) -> None:
    """One world on a matplotlib axis, x forward from the start (metres)."""
    from matplotlib import patches, transforms

    L, W = world.length_m, world.width_m
    ax.add_patch(patches.Rectangle((-L / 2, -W / 2), L, W, fill=False, lw=1.5, color="0.2"))
    for o in world.obstacles:
        if o.shape == "cylinder":
            ax.add_patch(patches.Circle((o.x_m, o.y_m), o.radius_m, color="tab:brown"))
        else:
            box = patches.Rectangle((o.x_m - o.size_x_m / 2, o.y_m - o.size_y_m / 2), o.size_x_m, o.size_y_m, color="tab:gray")
            box.set_transform(transforms.Affine2D().rotate_deg_around(o.x_m, o.y_m, o.yaw_deg) + ax.transData)
            ax.add_patch(box)
    x, y, _ = world.start_xyz_m
    yaw = math.radians(world.start_yaw_deg)
    tip = (x + 1.2 * math.cos(yaw), y + 1.2 * math.sin(yaw))
    ax.annotate("", tip, (x, y), arrowprops=dict(arrowstyle="->", color="tab:blue"))
    ax.plot([x], [y], "o", color="tab:blue", ms=4)
    w = world.weather
    title = world.name + (f"\nrain {w.rain}, snow {w.snow}, leaves {w.leaves}" if w.any else "")
    ax.set_title(title, fontsize=8)
    ax.set_xlim(-L / 2 - 0.5, L / 2 + 0.5)
    ax.set_ylim(-W / 2 - 0.5, W / 2 + 0.5)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="world_maps", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("worlds", nargs="+", help="world names or files; 'validation' for the validation set")
    ap.add_argument("--out", default="runs/worlds.png")
    ap.add_argument("--columns", type=int, default=4)
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from uav_sim.world import VALIDATION, VALIDATION_WORLDS, WorldError, load_world

    names = [w for n in a.worlds for w in (VALIDATION_WORLDS if n == VALIDATION else (n,))]
    try:
        worlds = [load_world(n) for n in names]
    except WorldError as e:
        ap.error(str(e))
    cols = max(1, min(a.columns, len(worlds)))
    rows = math.ceil(len(worlds) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    for ax in axes.flat[len(worlds) :]:
        ax.axis("off")
    for ax, world in zip(axes.flat, worlds, strict=False):
        draw(ax, world)
    save(fig, a.out)
    return 0


def save(fig, out: str) -> None:
    """Lay out a figure and write it to `out` (its folder made), saying where."""
    fig.tight_layout()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"written: {out}")


if __name__ == "__main__":
    raise SystemExit(main())
