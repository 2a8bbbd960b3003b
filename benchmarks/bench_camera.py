"""Camera-to-command latency of policy_node flying from a depth camera alone (no simulator): a RealSense-like
stream (848x480 16UC1 millimetres, 15 Hz, sensor-data QoS, an 87 deg CameraInfo) against, in the same run,
a simulator-sized stream (64x64 32FC1) as the baseline; each without the shield and with it (odometry published
with every frame: the vehicle flying on at 1 m/s); the RealSense-like stream once more with the packaged Fast DDS
profile (docs/REAL_CAMERA.md) in both processes. Each stream runs in a process of its own.

Figures, per stream: frames received and lost on the way (policy_node's /diagnostics), frames answered; in
policy_node, frame arrival to cmd_vel published (p50/p99, its /diagnostics: decode, mapping onto the trained field
of view, stack, network, safety layer, publishing); end to end, this process publishing the frame to it receiving
cmd_vel_stamped (p50/p99, DDS both ways).

Run: source .venv/bin/activate && source install/setup.bash && python benchmarks/bench_camera.py [--model sam]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from common import private_nodes

import uav_common
from uav_common import contract


def camera_info(width: int, height: int, hfov_deg: float, stamp, frame_id: str):
    from sensor_msgs.msg import CameraInfo

    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    info = CameraInfo(width=width, height=height, distortion_model="plumb_bob")
    info.header.stamp, info.header.frame_id = stamp, frame_id
    info.k = [f, 0.0, width / 2.0, 0.0, f, height / 2.0, 0.0, 0.0, 1.0]
    return info


def scene(width: int, height: int, t_s: float) -> np.ndarray:
    """A wall at 4 m with a post drifting across it at 1.5 m (metres)."""
    depth = np.full((height, width), 4.0, dtype=np.float32)
    x = int((0.5 + 0.4 * math.sin(t_s)) * width)
    depth[:, max(0, x - width // 40) : x + width // 40] = 1.5
    return depth


def odometry(stamp, t_s: float):
    """The vehicle 1 m/s along x, level (what the MAVLink bridge or any nav_msgs/Odometry gives)."""
    from nav_msgs.msg import Odometry

    odom = Odometry()
    odom.header.stamp, odom.header.frame_id, odom.child_frame_id = stamp, "odom", "base_link"
    odom.pose.pose.position.x, odom.pose.pose.position.z, odom.pose.pose.orientation.w = t_s, 1.0, 1.0
    return odom


def measure(model, weights, width, height, encoding, frames, rate_hz, domain, shield: bool) -> dict:
    import rclpy
    import rclpy.executors
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TwistStamped
    from sensor_msgs.msg import CameraInfo, Image

    procs = private_nodes(domain)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("bench_camera", context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    pub = node.create_publisher(Image, contract.DEPTH_TOPIC, contract.SENSOR_QOS)
    pub_info = node.create_publisher(CameraInfo, contract.CAMERA_INFO_TOPIC, contract.SENSOR_QOS)
    from nav_msgs.msg import Odometry

    pub_odom = node.create_publisher(Odometry, contract.ODOM_TOPIC, contract.SENSOR_QOS)
    sent, e2e, diag = {}, [], {}
    on_cmd = lambda m: e2e.append(time.perf_counter() - sent.pop(contract.stamp_ns(m.header.stamp), math.nan))  # noqa: E731
    node.create_subscription(TwistStamped, contract.CMD_VEL_STAMPED_TOPIC, on_cmd, 100)

    def on_diag(msg):
        for st in msg.status:
            if st.name == "uav_policy":
                diag.update({kv.key: kv.value for kv in st.values})

    node.create_subscription(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, on_diag, 10)
    try:
        args = ["-p", f"model:={model}", "-p", "publish_stamped:=true", "-p", f"shield:={'auto' if shield else 'never'}"]
        args += ["-p", f"weights:={weights}"] if weights else []
        procs.start("policy", "uav_policy", "policy_node", args)
        deadline = time.monotonic() + 60
        while pub.get_subscription_count() == 0 or not diag:
            ex.spin_once(timeout_sec=0.1)
            if time.monotonic() > deadline:
                raise TimeoutError("policy_node did not come up in 60 s")
        depth_frames = [scene(width, height, i / rate_hz) for i in range(30)]
        next_t = time.monotonic()
        for i in range(frames):
            stamp = node.get_clock().now().to_msg()
            frame_id = "camera_depth_optical_frame"
            pub_info.publish(camera_info(width, height, 87.0, stamp, frame_id))
            pub_odom.publish(odometry(stamp, i / rate_hz))
            msg = contract.depth_to_image(depth_frames[i % len(depth_frames)], stamp, frame_id, encoding)
            sent[contract.stamp_ns(stamp)] = time.perf_counter()
            pub.publish(msg)
            next_t += 1.0 / rate_hz
            while time.monotonic() < next_t:
                ex.spin_once(timeout_sec=max(0.0, next_t - time.monotonic()))
        end = time.monotonic() + 2.5  # the last answers and a /diagnostics report after them
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
    finally:
        procs.stop_all()
        ex.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
    e2e_ms = np.array([v for v in e2e if math.isfinite(v)]) * 1e3
    return {
        "frames": frames,
        "answered": len(e2e_ms),
        "received": diag.get("frames_received", "?"),
        "lost": diag.get("frames_lost", "?"),
        "node_p50": diag.get("latency_ms_p50"),
        "node_p99": diag.get("latency_ms_p99"),
        "e2e_p50": float(np.percentile(e2e_ms, 50)) if len(e2e_ms) else math.nan,
        "e2e_p99": float(np.percentile(e2e_ms, 99)) if len(e2e_ms) else math.nan,
        "overridden": diag.get("shield_overridden", "-"),
        "no_odometry": diag.get("shield_frames_without_odometry", "-"),
    }


STREAMS = (  # (width, height, encoding, shield, the packaged Fast DDS profile)
    (848, 480, "16UC1", False, False),
    (848, 480, "16UC1", True, False),
    (848, 480, "16UC1", False, True),
    (64, 64, "32FC1", False, False),
    (64, 64, "32FC1", True, False),
)


def measure_in_child(a, row: int) -> dict:
    """One stream in a process of its own: Fast DDS reads its profile once per process, so a stream with the packaged
    profile (docs/REAL_CAMERA.md) is set up as a user would, the variable exported for this publisher and policy_node."""
    env = dict(os.environ)
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    if STREAMS[row][4]:
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(Path(uav_common.__file__).parent / "fastdds_large_frames.xml")
    cmd = [sys.executable, __file__, "--model", a.model, "--weights", a.weights, "--frames", str(a.frames)]
    cmd += ["--domain", str(a.domain), "--row", str(row)]
    out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="sam", choices=("sam", "cnn"))
    ap.add_argument("--weights", default="", help="policy_node weights (default: the packaged ten networks)")
    ap.add_argument("--frames", type=int, default=450, help="frames per stream (15 Hz)")
    ap.add_argument("--domain", type=int, default=173)
    ap.add_argument("--row", type=int, default=None, help=argparse.SUPPRESS)  # one stream, in a child process
    a = ap.parse_args()
    if a.row is not None:
        w, h, enc, shield, _profile = STREAMS[a.row]
        print(json.dumps(measure(a.model, a.weights, w, h, enc, a.frames, 15.0, a.domain, shield)))
        return 0
    names = [f"{w}x{h} {enc}{' + shield' if sh else ''}{' + profile' if pr else ''}" for w, h, enc, sh, pr in STREAMS]
    rows = [(name, measure_in_child(a, i)) for i, name in enumerate(names)]
    print(f"policy_node model {a.model}, weights {a.weights or 'packaged'}, no simulator, 15 Hz, safety layer on")
    print("+ profile: FASTRTPS_DEFAULT_PROFILES_FILE=src/uav_common/uav_common/fastdds_large_frames.xml, both processes")
    head = f"{'stream':34s} {'received':>9s} {'lost':>5s} {'answered':>9s} {'in node p50/p99 ms':>20s}"
    print(head + f" {'end to end p50/p99 ms':>23s}  shield overrides / frames without odometry")
    for name, r in rows:
        print(
            f"{name:34s} {r['received']:>9s} {r['lost']:>5s} {r['answered']:4d}/{r['frames']:<4d} {r['node_p50']:>9s} / "
            f"{r['node_p99']:<8s} {r['e2e_p50']:10.2f} / {r['e2e_p99']:<8.2f}  {r['overridden']} / {r['no_odometry']}"
        )
    p99 = [float(r["node_p99"]) for _, r in rows]
    came = [int(r["received"]) for _, r in rows]
    print(
        f"ratio camera / baseline, in node p99: {p99[0] / p99[3]:.2f}; with the shield / without: {p99[1] / p99[0]:.2f}; "
        f"frames received with the profile / without: {came[2] / max(came[0], 1):.2f} (848x480, rows as in STREAMS)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
