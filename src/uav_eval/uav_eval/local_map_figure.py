"""A picture of the local map (uav_common.local_map): what the last frames showed, and what the weather filter keeps.

    python -m uav_eval.local_map_figure --worlds complex turbulent --out docs/figures/local_map.png

For each world the map planner flies `--steps` steps behind the packaged networks' camera (a RealSense D435-like
preset), then three panels show its last moment: the newest measured depth frame; every return of the remembered
frames within the height band (unfiltered, the weather's included); and the cells the map keeps, over the world's
true obstacles (outlines) with the vehicle's pose.
"""

from __future__ import annotations

import argparse
import math

import numpy as np


def fly(world_name: str, steps: int, seed: int):
    """(simulator, the planner's SimPlanner, an unfiltered map of the same frames) after `steps` map-planner steps."""
    from uav_common.local_map import LocalMap, MapConfig, PinholeCamera
    from uav_policy.rollout import Flight
    from uav_sim.planner import PlannerAgent, PlannerConfig, SimPlanner
    from uav_sim.sensor import TRAINING_SCALE
    from uav_sim.simulator import SimConfig, Simulator
    from uav_sim.stacked_sim import StackedSim
    from uav_sim.world import load_world

    cfg = SimConfig(seed=seed, start_yaw_jitter_deg=180.0, sensor="realsense_d435", sensor_scale=TRAINING_SCALE)
    sim = Simulator(load_world(world_name), cfg)
    planner = SimPlanner(sim, PlannerConfig(knowledge="map"))
    raw = LocalMap(MapConfig(solid_m=0.0, confirm_frames=1, carve_m=100.0))  # every return, nothing filtered
    flight = Flight(StackedSim(sim, 5), PlannerAgent(planner))
    c = sim.camera.intrinsics
    camera = PinholeCamera.from_fov(c.width, c.height, c.hfov_deg)
    episode = sim.episode
    for _ in range(steps):
        if sim.episode != episode:
            raw.reset()
            episode = sim.episode
        x, y, z = sim.camera_xyz()
        raw.insert(sim.measured, camera, x, y, z, sim.pose.yaw_rad)
        flight.step(0.0)
    planner.label()  # the newest frame into the planner's map
    x, y, z = sim.camera_xyz()
    raw.insert(sim.measured, camera, x, y, z, sim.pose.yaw_rad)
    return sim, planner, raw


def draw(axes, sim, planner, raw) -> None:
    from .world_maps import draw as draw_world

    depth = np.where(np.isfinite(sim.measured), sim.measured, np.nan)
    axes[0].imshow(depth, cmap="viridis_r", vmin=0.0, vmax=sim.config.max_range_m)
    axes[0].set_title(f"{sim.world.name}: newest depth frame", fontsize=8)
    axes[0].axis("off")
    pose = sim.pose
    for ax, m, title, colour in (
        (axes[1], raw, "every return in the band, 5 frames", "0.4"),
        (axes[2], planner.map, "the local map (weather filtered)", "tab:red"),
    ):
        draw_world(ax, sim.world)
        xy = m.occupied_xy()
        ax.scatter(xy[:, 0], xy[:, 1], s=1.5, c=colour, marker="s", linewidths=0)
        tip = (pose.x_m + 0.8 * math.cos(pose.yaw_rad), pose.y_m + 0.8 * math.sin(pose.yaw_rad))
        ax.annotate("", tip, (pose.x_m, pose.y_m), arrowprops=dict(arrowstyle="->", color="tab:blue", lw=1.5))
        ax.set_xlim(pose.x_m - 5, pose.x_m + 5)
        ax.set_ylim(pose.y_m - 4, pose.y_m + 4)
        ax.set_title(f"{title}: {len(xy)} cells", fontsize=8)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="local_map_figure", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--worlds", nargs="+", default=["complex", "turbulent"])
    ap.add_argument("--steps", type=int, default=40, help="map-planner steps flown before the picture")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", default="runs/figures/local_map.png")
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .world_maps import save

    fig, axes = plt.subplots(len(a.worlds), 3, figsize=(11, 3.4 * len(a.worlds)), squeeze=False)
    for row, name in zip(axes, a.worlds, strict=True):
        sim, planner, raw = fly(name, a.steps, a.seed)
        try:
            draw(row, sim, planner, raw)
        finally:
            sim.close()
    save(fig, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
