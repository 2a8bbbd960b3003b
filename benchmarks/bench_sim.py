"""Lockstep steps/s of sim_node through ROS (a client answers every frame) vs. in-process.

Run: source .venv/bin/activate && source install/setup.bash && python benchmarks/bench_sim.py [--steps N]
Prints both rates (medians of --repeats alternating pairs) and their ratio, on the same world; then the same client
against an echo of sim_node's messages without the simulation (ROS alone), and the ratio that leaves at best.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def in_process(world: str, steps: int) -> float:
    """The same simulator sim_node runs by default (its camera and sensor model), without ROS."""
    from uav_common.kinematics import BodyTwist
    from uav_sim.sim_settings import SimNodeSettings
    from uav_sim.simulator import Simulator
    from uav_sim.world import load_world

    sim = Simulator(load_world(world), SimNodeSettings().sim)
    sim.observe()
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step(BodyTwist(vx_mps=1.0))
    rate = steps / (time.perf_counter() - t0)
    sim.close()
    return rate


def echo(domain: int) -> None:
    """A stand-in for sim_node without the simulation: every cmd_vel is answered with the messages sim_node sends each
    step (clock, outcome, camera info, the default sensor's depth frame, odometry), built and published as it does."""
    import numpy as np
    import rclpy
    import rclpy.executors
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CameraInfo, Image

    from uav_common import contract
    from uav_common.kinematics import BodyTwist, Pose
    from uav_interfaces.msg import StepOutcome
    from uav_sim.messages import camera_info_msg, odometry_msg
    from uav_sim.sim_settings import SimNodeSettings

    cfg = SimNodeSettings().sim
    rclpy.init(domain_id=domain)
    node = rclpy.create_node("bench_echo")
    q = contract.STREAM_QOS
    pubs = [
        node.create_publisher(t, n, q)
        for t, n in (
            (Clock, "/clock"),
            (StepOutcome, contract.OUTCOME_TOPIC),
            (CameraInfo, contract.CAMERA_INFO_TOPIC),
            (Image, contract.DEPTH_TOPIC),
            (Odometry, contract.ODOM_TOPIC),
        )
    ]
    depth = np.full((cfg.image_height, cfg.image_width), 3.0, np.float32)
    k = [50.0, 0.0, cfg.image_width / 2, 0.0, 50.0, cfg.image_height / 2, 0.0, 0.0, 1.0]
    t = {"s": 0.0}

    def on_cmd(_msg: Twist) -> None:
        t["s"] += cfg.step_duration_s
        stamp = contract.stamp_from_seconds(t["s"])
        pubs[0].publish(Clock(clock=stamp))
        pubs[1].publish(contract.make_outcome(2.0, False, stamp, "cam", cfg.min_range_m, cfg.max_range_m, 1.0))
        pubs[2].publish(camera_info_msg(stamp, "cam", cfg.image_width, cfg.image_height, k))
        pubs[3].publish(contract.depth_to_image(depth, stamp, "cam", "32FC1"))
        pubs[4].publish(odometry_msg(Pose(0.0, 0.0, 1.0, 0.0), BodyTwist(1.0), stamp, "odom", "base_link"))

    node.create_subscription(Twist, contract.CMD_VEL_TOPIC, on_cmd, q)
    ex = rclpy.executors.SingleThreadedExecutor()
    ex.add_node(node)
    try:
        while rclpy.ok():
            ex.spin_once(timeout_sec=0.5)
            if node.count_subscribers(contract.DEPTH_TOPIC) and t["s"] == 0.0:  # the first frame, once heard
                pubs[3].publish(contract.depth_to_image(depth, contract.stamp_from_seconds(0.0), "cam", "32FC1"))
    except KeyboardInterrupt:
        pass


def through_ros(world: str, steps: int, domain: int, server: list[str] | None = None) -> float:
    import rclpy
    import rclpy.executors
    from geometry_msgs.msg import Twist
    from sensor_msgs.msg import Image

    from uav_common import contract

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    exe = ROOT / "install/uav_sim/lib/uav_sim/sim_node"
    proc = subprocess.Popen(
        server or [str(exe), "--ros-args", "-p", f"world:={world}", "-p", "lockstep_republish_s:=0.5"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    rclpy.init(domain_id=domain)
    node = rclpy.create_node("bench_client")
    executor = rclpy.executors.SingleThreadedExecutor()  # one executor for the run, as a node's main() spins
    executor.add_node(node)
    pub = node.create_publisher(Twist, contract.CMD_VEL_TOPIC, contract.STREAM_QOS)
    state = {"n": 0, "last": None, "t0": None}
    cmd = Twist()
    cmd.linear.x = 1.0

    def on_frame(msg: Image) -> None:
        stamp = contract.stamp_ns(msg.header.stamp)
        if stamp == state["last"]:
            return
        contract.image_to_depth(msg)  # decode as a real consumer would
        state["last"] = stamp
        if state["n"] == 5:
            state["t0"] = time.perf_counter()  # skip warm-up steps
        state["n"] += 1
        pub.publish(cmd)

    node.create_subscription(Image, contract.DEPTH_TOPIC, on_frame, contract.STREAM_QOS)
    try:
        while state["n"] < steps + 5:
            executor.spin_once(timeout_sec=1.0)
        rate = steps / (time.perf_counter() - state["t0"])
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(10)
    return rate


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--world", default="basic")
    ap.add_argument("--repeats", type=int, default=3, help="alternating pairs of runs; the medians are compared")
    ap.add_argument("--echo", type=int, default=None, help=argparse.SUPPRESS)  # the stand-in, in a child process
    a = ap.parse_args()
    if a.echo is not None:
        echo(a.echo)
        return 0
    sys.path.insert(0, str(ROOT / "src" / "uav_sim"))
    # Two processes on two cores vary from run to run (0.54 to 0.71 in two single runs on one quiet machine): pairs,
    # in process then through ROS, alternate, and the ratio is of the medians, with every pair's ratio beside it.
    domain = 90 + os.getpid() % 10
    pairs = [(in_process(a.world, a.steps), through_ros(a.world, a.steps, domain)) for _ in range(a.repeats)]
    base, ros = (statistics.median(x) for x in zip(*pairs, strict=True))
    floor = statistics.median(
        through_ros(a.world, a.steps, domain, [sys.executable, __file__, "--echo", str(domain)]) for _ in range(a.repeats)
    )
    from uav_sim.sim_settings import SimNodeSettings

    cfg = SimNodeSettings().sim
    print(f"world={a.world} steps={a.steps} x {a.repeats} (sim_node's default camera and sensor model: {cfg.sensor})")
    print(f"in-process (no ROS)      : {base:8.1f} steps/s (median)")
    print(f"lockstep through ROS 2   : {ros:8.1f} steps/s (median)")
    print(f"ratio ROS / in-process   : {ros / base:8.3f} (each pair: {', '.join(f'{r / b:.3f}' for b, r in pairs)})")
    ros_us = 1e6 / floor
    print(f"ROS alone, no simulation : {floor:8.1f} steps/s (an echo of sim_node's five messages a step: {ros_us:.0f} us)")
    print(f"ceiling ROS / in-process : {(1e6 / base) / (1e6 / base + ros_us):8.3f} (in-process step time over it plus ROS alone)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
