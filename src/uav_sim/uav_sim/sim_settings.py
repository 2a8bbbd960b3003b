"""sim_node's parameters, declared once (uav_common.settings): the ROS declarations, params/sim.yaml and
docs/PARAMETERS.md come from here; and its start-up line."""

from __future__ import annotations

import dataclasses

from uav_common import contract
from uav_common.settings import setting

from .sensor import TRAINING_SCALE
from .simulator import SimConfig
from .world import World, WorldChoice

# Parameters retired, and why: a node given one stops at start-up and says so.
REMOVED = {
    "max_rate_hz": "lockstep training waits for learning, so no step-rate cap is needed; use mode:=realtime to watch",
    "random_start_fraction": "random start places did not help (docs/RESULTS.md); start_yaw_jitter_deg varies the heading",
    "random_start_clearance_m": "random start places did not help (docs/RESULTS.md)",
    "redraw_start_heading": "a new heading per layout trained worse (docs/RESULTS.md)",
    "layout_partitions": "training on partition layouts did not help (docs/RESULTS.md); random_partitions:SEED worlds remain",
}


@dataclasses.dataclass(frozen=True)
class SimNodeSettings:
    """sim_node's parameters: the simulator's, the world's and the node's own."""

    # The camera the packaged policy was trained behind (a drone's depth camera), at the scale it was trained at, and
    # its reward window (the paper's 20 %); the in-process core's default stays the exact camera. Recipes name
    # theirs (paper, wide150: sensor ideal).
    sim: SimConfig = SimConfig(sensor="realsense_d435", sensor_scale=TRAINING_SCALE, reward_window_fraction=0.2)
    worlds: WorldChoice = WorldChoice()
    mode: str = setting(
        "lockstep", "lockstep: one step per cmd_vel; realtime: fixed rate with watchdog", choices=("lockstep", "realtime")
    )
    watchdog_timeout_s: float = setting(1.0, "realtime: hover when no cmd_vel came for this long (s)", 0.05, 60.0)
    lockstep_republish_s: float = setting(
        1.0, "lockstep: publish the current frame again when no command came for this long (s)", 0.05, 60.0
    )
    wait_for_subscribers: int = setting(
        0,
        "lockstep: hold the first frame until depth and outcome each have this many subscribers (train sets 2, policy "
        "and trainer, so that the trainer learns from the first step); 0 = at once",
        0,
        100,
    )
    step_budget: int = setting(
        0,
        "lockstep: steps flown before the simulator holds position and takes no more commands; the last step's outcome "
        "and odometry go out, but no frame to answer (evaluate sets it: a measurement of N steps flies and explains exactly "
        "N); 0 = no limit",
        0,
        10**9,
    )
    camera_frame_id: str = setting(
        "camera_depth_optical_frame", "frame of depth and camera_info (REP 118); prefixed with the namespace"
    )
    odom_frame_id: str = setting(
        "odom", "the world frame: Odometry header, markers and trajectory (REP 105); prefixed with the namespace"
    )
    base_frame_id: str = setting("base_link", "Odometry child frame (REP 105); prefixed with the namespace")
    publish_clock: bool = setting(
        True,
        "publish the simulated time on /clock; false when several simulators share a graph (train --actors N with "
        "N > 1 sets it: each actor's stamps are its own sim time, and no one clock fits them all)",
    )
    teacher: str = setting(
        "none",
        "training with a teacher: publish on teacher_label, stamped as each frame, the action uav_sim.planner flies from "
        "it, its score for every action and the pixels its decision is about (stack: knowing what the last teacher_frames frames "
        "showed; all: the whole world; map: the local map of the last teacher_frames measured frames and odometry); "
        "train sets it from the trainer's teacher. none: no planning",
        choices=contract.TEACHERS,
    )
    teacher_frames: int = setting(5, "the frames the stack teacher remembers (the trainer's frame_stack; train sets it)", 1, 16)
    depth_encoding: str = setting(
        "32FC1",
        "depth/image_raw encoding: 32FC1 (metres) or 16UC1 (millimetres, 0 = no return, as camera drivers)",
        choices=tuple(contract.DEPTH_ENCODINGS),
    )


def describe(world: World, layouts, worlds: WorldChoice, mode: str, cfg: SimConfig, depth_encoding: str) -> str:
    """sim_node's start-up line: the world, the mode and the camera."""
    mixed = f" ('{worlds.mix_world}' every {worlds.mix_world_every} episodes)" if worlds.mix_world_every else ""
    w = world.weather
    return (
        (f"a new layout every episode{mixed}, first " if layouts else "")
        + f"world '{world.name}' ({len(world.obstacles)} obstacles, weather rain={w.rain} snow={w.snow} leaves={w.leaves}), "
        f"mode {mode}, {cfg.image_width}x{cfg.image_height} depth ({depth_encoding}, {cfg.hfov_deg:g} deg, sensor "
        f"{cfg.sensor}), step {cfg.step_duration_s} s"
    )
