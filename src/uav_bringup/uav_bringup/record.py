"""record: keep a flight as a rosbag2 bag (MCAP storage), as `ros2 bag record -o NAME` would.

    ros2 run uav_bringup record -o runs/bags/flight1                 # the stack's topics
    ros2 run uav_bringup record -o flight2 --topics odom cmd_vel --ros-args -r __ns:=/uav1

Writes the folder NAME with metadata.yaml and NAME_0.mcap (rosbags' rosbag2 writer), which Foxglove
opens and a full ROS install's `ros2 bag info` / `ros2 bag play` read. Messages are stored as they
arrive on the wire (serialized CDR, receive time), so recording costs the stack little. Topics are
taken as they appear; relative names resolve in the recorder's namespace. Ctrl-C (or SIGTERM) closes
the bag: it is complete and readable.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.utilities import remove_ros_args

from uav_common import contract
from uav_common.node_runner import DeferredInterrupt, run
from uav_common.ros_params import ParameterError

from .taps import DEFAULT_TOPICS, TopicTap, typestore

PROGRESS_S = 5.0
# The policy's per-step topics: a launcher that wants every step on record starts the simulator only
# once the recorder has matched these publishers (`recorder_publishers`).
POLICY_TOPICS = (contract.ACTION_TOPIC, contract.CMD_VEL_TOPIC, contract.Q_VALUES_TOPIC)


def open_bag(path: Path):
    """A rosbags rosbag2 writer (MCAP storage) opened at `path`; ParameterError if it cannot be."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    if path.exists():
        raise ParameterError(f"-o {path}: already exists (a bag is never overwritten; choose another name)")
    if not path.parent.is_dir():
        try:
            path.parent.mkdir(parents=True)
        except OSError as e:
            raise ParameterError(f"-o {path}: cannot create its folder ({e.strerror})") from None
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    try:
        writer.open()
    except Exception as e:  # rosbags raises its own WriterError for an unwritable folder
        raise ParameterError(f"-o {path}: cannot write the bag ({e})") from None
    return writer


class Recorder(Node):
    def __init__(self, out: Path, topics, quiet: bool = False, hold=None):
        super().__init__("recorder")
        self.out = out
        self.hold = hold or DeferredInterrupt()  # Ctrl-C never lands inside a write: the bag stays whole
        self.quiet = quiet
        self.writer = open_bag(out)
        self.connections = {}
        self.counts: dict[str, int] = {}
        self.bytes = 0
        self.started = time.monotonic()
        self.pub_diag = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, 10)
        self.tap = TopicTap(self, topics, self.on_message, self.on_new)
        self.create_timer(PROGRESS_S, self.progress)
        self.create_timer(1.0, self.publish_diagnostics)
        names = " ".join(self.tap.wanted)
        self.get_logger().info(f"recording to {out}: {names}")

    def on_new(self, topic: str, msgtype: str) -> bool:
        ts = typestore()
        if msgtype not in ts.types:
            self.get_logger().warning(f"skipping {topic}: {msgtype} has no definition in the ROS 2 Jazzy type store")
            return False
        self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=ts)
        self.counts[topic] = 0
        return True

    def on_message(self, topic: str, _msgtype: str, data: bytes, receive_ns: int) -> None:
        if self.writer is None:
            return
        with self.hold:
            self.writer.write(self.connections[topic], receive_ns, data)
        self.counts[topic] += 1
        self.bytes += len(data)

    def summary(self) -> str:
        n = sum(self.counts.values())
        return f"{time.monotonic() - self.started:.0f} s, {n} messages on {len(self.counts)} topics, {self.bytes / 1e6:.1f} MB"

    def progress(self) -> None:
        if not self.quiet:
            quiet = [t for t in self.tap.wanted if not self.counts.get(t) and t not in self.tap.skipped]
            wait = f"; nothing yet on {' '.join(quiet)}" if quiet else ""
            print(f"record {self.out}: {self.summary()}{wait}", flush=True)

    def publish_diagnostics(self) -> None:
        """Messages written per topic (by name) and in all, and the publishers matched per topic
        (`publishers TOPIC`: a launcher can wait for them before the flight starts)."""
        values = {"bag": str(self.out), "messages": sum(self.counts.values()), "megabytes": f"{self.bytes / 1e6:.2f}"}
        values.update(self.counts)
        values.update({f"publishers {t}": n for t, n in self.tap.publishers().items()})
        self.pub_diag.publish(contract.diagnostics(self, "uav_bringup/record", "OK", "recording", values))

    def close(self) -> None:
        if self.writer is None:
            return
        writer, self.writer = self.writer, None
        writer.close()
        counts = ", ".join(f"{t} {c}" for t, c in self.counts.items())
        print(f"bag {self.out} closed: {self.summary()} ({counts})", flush=True)


def recorder_publishers(node, written: dict[str, int] | None = None) -> dict[str, int]:
    """{topic: publishers the recorder has matched}, kept up to date from its /diagnostics; `written`, when
    given, gets {topic: messages the recorder has written}."""
    heard: dict[str, int] = {}

    def on(msg) -> None:
        for st in msg.status:
            if st.name == "uav_bringup/record":
                heard.update(
                    {kv.key[len("publishers ") :]: int(kv.value) for kv in st.values if kv.key.startswith("publishers ")}
                )
                if written is not None:
                    written.update({kv.key: int(kv.value) for kv in st.values if kv.key.startswith("/")})

    node.create_subscription(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, on, 10)
    return heard


def wait_for_policy(heard: dict[str, int], node, executor, procs: dict, timeout_s: float, stopped=lambda: False) -> bool:
    """Spin `executor` until the recorder has matched policy_node's publishers (POLICY_TOPICS, resolved in
    `node`'s namespace; `heard` from recorder_publishers(node)); False if `stopped()` first. RuntimeError
    when a process of `procs` (name: Popen) exits, TimeoutError after `timeout_s`."""
    wanted = [node.resolve_topic_name(t) for t in POLICY_TOPICS]
    end = time.monotonic() + timeout_s
    while not all(heard.get(t, 0) >= 1 for t in wanted):
        executor.spin_once(timeout_sec=0.05)
        if stopped():
            return False
        for name, p in procs.items():
            if p.poll() is not None:
                raise RuntimeError(f"{name} exited early (code {p.returncode})")
        if time.monotonic() > end:
            raise TimeoutError(f"the recorder did not hear policy_node within {timeout_s:g} s (it hears {heard})")
    return True


def main(argv=None) -> int:
    argv = list(sys.argv if argv is None else ["record", *argv])
    ap = argparse.ArgumentParser(prog="record", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", required=True, help="the bag folder to create (must not exist)")
    ap.add_argument(
        "--topics",
        nargs="+",
        default=list(DEFAULT_TOPICS),
        metavar="TOPIC",
        help=f"topics to record (default: {' '.join(DEFAULT_TOPICS)})",
    )
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    a = ap.parse_args(remove_ros_args(argv)[1:])
    hold = DeferredInterrupt().install()
    return run(lambda: Recorder(Path(a.output), a.topics, a.quiet, hold), argv)


if __name__ == "__main__":
    raise SystemExit(main())
