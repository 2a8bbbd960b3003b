"""record: keep a flight as a rosbag2 bag (MCAP storage), as `ros2 bag record -o NAME` would.

    ros2 run uav_bringup record -o runs/bags/flight1                 # the stack's topics
    ros2 run uav_bringup record -o flight2 --topics odom cmd_vel --ros-args -r __ns:=/uav1

Writes the folder NAME with metadata.yaml and NAME_0.mcap (rosbags' rosbag2 writer), which Foxglove
opens and a full ROS install's `ros2 bag info` / `ros2 bag play` read. Messages are stored as they
arrive on the wire (serialized CDR, receive time), so recording costs the stack little. Topics are
taken as they appear; relative names resolve in the recorder's namespace. Ctrl-C (or SIGTERM) closes
the bag: it is complete and readable.

Nothing is lost silently: every message's publication sequence number is checked (uav_bringup.accounting), and
what a publisher sent that never reached the bag is counted per topic, exactly: on /diagnostics (`lost TOPIC`, WARN),
in the progress and closing lines, and in the bag's metadata (custom_data: written, lost and before_recording per
topic), which `attention_figures --bag` reads back.
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

from .accounting import Accounting
from .taps import DEFAULT_TOPICS, TopicTap, typestore

PROGRESS_S = 5.0
# The policy's per-step topics: a launcher that wants every step on record starts the simulator only
# once the recorder has matched these publishers and the policy has matched the recorder's subscriptions
# (discovery matches each side at its own time: `RecorderReports.wait_for_policy`).
POLICY_TOPICS = (contract.ACTION_TOPIC, contract.CMD_VEL_TOPIC, contract.Q_VALUES_TOPIC)
BEFORE_KEY = "before_recording "


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
    def __init__(self, out: Path, topics, quiet: bool = False, hold=None, **node_options):  # context=: a test's
        super().__init__("recorder", **node_options)
        self.out = out
        self.hold = hold or DeferredInterrupt()  # Ctrl-C never lands inside a write: the bag stays whole
        self.quiet = quiet
        self.writer = open_bag(out)
        self.connections = {}
        self.accounting = Accounting()  # what each topic's publishers sent, written or lost
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
        self.accounting.track(topic)
        return True

    @property
    def counts(self) -> dict[str, int]:
        """{topic: messages written} of every topic recorded."""
        return self.accounting.written

    @property
    def lost(self) -> dict[str, int]:
        """{topic: messages its publishers sent that never reached the bag}, where any were."""
        return self.accounting.lost

    def on_message(self, topic: str, _msgtype: str, data: bytes, receive_ns: int, seq: int | None = None) -> None:
        if self.writer is None:
            return
        with self.hold:
            self.writer.write(self.connections[topic], receive_ns, data)
        self.bytes += len(data)
        n = self.accounting.add(topic, seq)
        if n > 0:
            self.get_logger().warning(
                f"{sum(self.lost.values())} message(s) lost so far ({n} on {topic}): the recorder fell behind its "
                "publishers' queues (a slow disk or a busy machine)",
                throttle_duration_sec=2.0,
            )

    def summary(self) -> str:
        n = sum(self.counts.values())
        lost = f", {sum(self.lost.values())} lost" if self.lost else ""
        return (
            f"{time.monotonic() - self.started:.0f} s, {n} messages on {len(self.counts)} topics{lost}, {self.bytes / 1e6:.1f} MB"
        )

    def progress(self) -> None:
        if not self.quiet:
            quiet = [t for t in self.tap.wanted if not self.counts.get(t) and t not in self.tap.skipped]
            wait = f"; nothing yet on {' '.join(quiet)}" if quiet else ""
            print(f"record {self.out}: {self.summary()}{wait}", flush=True)

    def publish_diagnostics(self) -> None:
        """Messages written per topic (by name) and in all, lost per topic (`lost TOPIC`; WARN while any are), sent
        before the recorder heard their publisher (`before_recording TOPIC`, where any were), and the publishers matched
        per topic (`publishers TOPIC`: a launcher can wait for them before the flight starts)."""
        values = {"bag": str(self.out), "messages": sum(self.counts.values()), "megabytes": f"{self.bytes / 1e6:.2f}"}
        values.update(self.counts)
        values.update({f"{contract.LOST_KEY}{t}": n for t, n in self.lost.items()})
        values.update({f"{BEFORE_KEY}{t}": n for t, n in self.accounting.before.items()})
        values.update({f"publishers {t}": n for t, n in self.tap.publishers().items()})
        level, text = ("WARN", "recording; messages lost") if self.lost else ("OK", "recording")
        self.pub_diag.publish(contract.diagnostics(self, "uav_bringup/record", level, text, values))

    def close(self) -> None:
        if self.writer is None:
            return
        writer, self.writer = self.writer, None
        for key, value in self.accounting.metadata().items():
            writer.set_custom_data(key, value)
        writer.close()
        counts = ", ".join(f"{t} {c}" + (f" ({self.lost[t]} lost)" if t in self.lost else "") for t, c in self.counts.items())
        print(f"bag {self.out} closed: {self.summary()} ({counts})", flush=True)


def counts(status, prefix: str) -> dict[str, int]:
    """{topic: n} of a diagnostics status' `PREFIX TOPIC` keys."""
    return {kv.key[len(prefix) :]: int(kv.value) for kv in status.values if kv.key.startswith(prefix)}


class RecorderReports:
    """What the recorder says on /diagnostics, kept up to date through `node`: `heard` {topic: publishers matched},
    `written` {topic: messages written}, `lost` {topic: messages lost to it}, `before` {topic: messages sent before it
    heard their publisher}, and `reports`, how many reports came; what policy_node says: `heard_by_policy` {topic:
    subscriptions its publishers matched}, `published` {topic: messages it sent} of the decision's record, and
    `policy_reports`; and what sim_node says: `sim_published` {topic: messages it sent} and `sim_paused`."""

    def __init__(self, node):
        self.node = node
        self.heard: dict[str, int] = {}
        self.heard_by_policy: dict[str, int] = {}
        self.published: dict[str, int] = {}
        self.policy_reports = 0
        self.sim_published: dict[str, int] = {}
        self.sim_paused = False
        self.written: dict[str, int] = {}
        self.lost: dict[str, int] = {}
        self.before: dict[str, int] = {}
        self.reports = 0
        node.create_subscription(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, self._on, 10)

    def _on(self, msg) -> None:
        for st in msg.status:
            if st.name == "uav_bringup/record":
                self.heard.update(counts(st, "publishers "))
                self.written.update({kv.key: int(kv.value) for kv in st.values if kv.key.startswith("/")})
                self.lost.update(counts(st, contract.LOST_KEY))
                self.before.update(counts(st, BEFORE_KEY))
                self.reports += 1
            elif st.name == "uav_policy":
                self.heard_by_policy.update(counts(st, "subscribers "))
                self.published.update(counts(st, "published "))
                self.policy_reports += 1
            elif st.name == "uav_sim":
                self.sim_published.update(counts(st, "published "))
                self.sim_paused = any(kv.key == "paused" and kv.value == "true" for kv in st.values)

    def ready(self, topics) -> bool:
        """The recorder and policy_node have matched each other on every one of `topics` (resolved names)."""
        return all(self.heard.get(t, 0) >= 1 and self.heard_by_policy.get(t, 0) >= 1 for t in topics)

    def wait_for_policy(self, executor, procs: dict, timeout_s: float, stopped=lambda: False) -> bool:
        """Spin `executor` until the recorder has matched policy_node's publishers (POLICY_TOPICS, resolved in
        the node's namespace) and the policy has matched the recorder's subscriptions (else its first answers are
        sent to no recorder); False if `stopped()` first. RuntimeError when a process of `procs` (name: Popen)
        exits, TimeoutError after `timeout_s`."""
        wanted = [self.node.resolve_topic_name(t) for t in POLICY_TOPICS]
        end = time.monotonic() + timeout_s
        while not self.ready(wanted):
            executor.spin_once(timeout_sec=0.05)
            if stopped():
                return False
            for name, p in procs.items():
                if p.poll() is not None:
                    raise RuntimeError(f"{name} exited early (code {p.returncode})")
            if time.monotonic() > end:
                raise TimeoutError(
                    f"the recorder and policy_node did not hear each other within {timeout_s:g} s (the recorder hears "
                    f"{self.heard}, the policy's publishers {self.heard_by_policy})"
                )
        return True

    def missing(self) -> dict[str, int]:
        """{topic: messages policy_node published (and a paused sim_node, of the topics the recorder takes) that the
        recorder has neither written nor counted (lost, or sent before it heard their publisher)}, where any."""
        sim = {t: n for t, n in self.sim_published.items() if self.sim_paused and t in self.heard}
        got = lambda t: self.written.get(t, 0) + self.lost.get(t, 0) + self.before.get(t, 0)  # noqa: E731
        short = {t: n - got(t) for t, n in (self.published | sim).items()}
        return {t: n for t, n in short.items() if n > 0}

    def wait_until_idle(self, executor, timeout_s: float) -> bool:
        """Spin `executor` until the recorder holds all policy_node said (and sim_node's, once it reports it is
        paused): two policy reports in a row count the same messages published (it answers nothing more), the
        recorder has written (or counted lost) every one of them, and two of its reports in a row count the same
        messages written (/diagnostics aside: the nodes report on). Call it once the simulator is paused (or has
        stopped), before any other node exits: a reliable message still on its way (one resent after a loss, say) is
        lost with its publisher, and at the end of a stream no later message shows the gap. False if not so within
        `timeout_s` (`missing()` then says what the bag lacks)."""
        end = time.monotonic() + timeout_s
        counts = lambda: {t: n for t, n in self.written.items() if t != contract.DIAGNOSTICS_TOPIC}  # noqa: E731
        seen = (self.reports, counts())
        said = (self.policy_reports, None)  # two reports after this call: the last frame has a second to be answered
        idle = settled = False
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
            if self.policy_reports != said[0]:
                settled = self.published == said[1]
                said = (self.policy_reports, dict(self.published))
            if self.reports != seen[0]:
                idle = seen[0] > 0 and counts() == seen[1]
                seen = (self.reports, counts())
            if idle and settled and not self.missing():
                return True
        return False


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
