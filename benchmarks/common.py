"""Helpers for benchmarks: installed nodes in a private ROS domain, and sim_node's step counter."""

from __future__ import annotations

import os
import time
from pathlib import Path

from uav_common.launching import Processes

ROOT = Path(__file__).resolve().parents[1]


def private_nodes(domain: int) -> Processes:
    """Processes started in ROS domain `domain`, discovery limited to this machine."""
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    return Processes(quiet=True, env=dict(os.environ, ROS_DOMAIN_ID=str(domain)))


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
