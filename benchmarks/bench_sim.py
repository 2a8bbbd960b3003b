"""Lockstep steps/s of sim_node through ROS (a client answers every frame) vs. in-process.

Run: source .venv/bin/activate && source install/setup.bash && python benchmarks/bench_sim.py [--steps N]
Prints both rates (medians of --repeats alternating pairs) and their ratio, on the same world.
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


def through_ros(world: str, steps: int, domain: int) -> float:
    import rclpy
    from geometry_msgs.msg import Twist
    from sensor_msgs.msg import Image

    from uav_common import contract

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    exe = ROOT / "install/uav_sim/lib/uav_sim/sim_node"
    proc = subprocess.Popen(
        [str(exe), "--ros-args", "-p", f"world:={world}", "-p", "lockstep_republish_s:=0.5"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    rclpy.init(domain_id=domain)
    node = rclpy.create_node("bench_client")
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
            rclpy.spin_once(node, timeout_sec=1.0)
        rate = steps / (time.perf_counter() - state["t0"])
    finally:
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
    a = ap.parse_args()
    sys.path.insert(0, str(ROOT / "src" / "uav_sim"))
    # Two processes on two cores vary from run to run (0.54 to 0.71 in two single runs on one quiet machine): pairs,
    # in process then through ROS, alternate, and the ratio is of the medians, with every pair's ratio beside it.
    pairs = [(in_process(a.world, a.steps), through_ros(a.world, a.steps, 90 + os.getpid() % 10)) for _ in range(a.repeats)]
    base, ros = (statistics.median(x) for x in zip(*pairs, strict=True))
    from uav_sim.sim_settings import SimNodeSettings

    cfg = SimNodeSettings().sim
    print(f"world={a.world} steps={a.steps} x {a.repeats} (sim_node's default camera and sensor model: {cfg.sensor})")
    print(f"in-process (no ROS)      : {base:8.1f} steps/s (median)")
    print(f"lockstep through ROS 2   : {ros:8.1f} steps/s (median)")
    print(f"ratio ROS / in-process   : {ros / base:8.3f} (each pair: {', '.join(f'{r / b:.3f}' for b, r in pairs)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
