"""Helpers for benchmarks: start installed nodes in a private domain, read sim_node's diagnostics."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


class Nodes:
    """Installed executables as processes in one private ROS domain, stopped with SIGINT."""

    def __init__(self, domain: int):
        self.domain = domain
        self.env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.procs = []

    def start(self, pkg: str, exe: str, *ros_args: str, log: Path | None = None) -> subprocess.Popen:
        out = log.open("w") if log else subprocess.DEVNULL
        cmd = [str(ROOT / "install" / pkg / "lib" / pkg / exe)] + (["--ros-args", *ros_args] if ros_args else [])
        p = subprocess.Popen(cmd, env=self.env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs.append(p)
        return p

    def stop_all(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        for p in self.procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
        self.procs.clear()


def sim_steps_reader(node):
    """Subscribe to /diagnostics; returns a callable giving (wall time, sim steps) of the latest report."""
    from diagnostic_msgs.msg import DiagnosticArray

    latest = {"t": None, "steps": None}

    def on(msg):
        for st in msg.status:
            if st.name == "uav_sim":
                for kv in st.values:
                    if kv.key == "steps":
                        latest["t"], latest["steps"] = time.perf_counter(), int(kv.value)

    node.create_subscription(DiagnosticArray, "/diagnostics", on, 10)
    return lambda: (latest["t"], latest["steps"])
