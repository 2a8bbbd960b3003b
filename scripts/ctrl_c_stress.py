"""Stop a busy node with Ctrl-C many times and count its exit codes (all should be 0).

The node runs uav_sim.node_runner.run, like every node of the stack, and keeps rclpy taking
service requests and responses, where a SIGINT used to surface as a SystemError: before
node_runner.interrupted, 6 of 202 stops exited 1 with a traceback. Run with the workspace sourced:

    python scripts/ctrl_c_stress.py --runs 100
"""

from __future__ import annotations

import argparse
import collections
import os
import random
import signal
import subprocess
import sys
import time

NODE = """
import sys
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from uav_common.node_runner import run

class Busy(Node):
    def __init__(self):
        super().__init__("ctrl_c_stress")
        self.client = self.create_client(SetParameters, "ctrl_c_stress/set_parameters")
        self.create_timer(0.0005, self.tick)
        print("ready", flush=True)

    def tick(self):
        sum(range(3000))
        if self.client.service_is_ready():
            self.client.call_async(SetParameters.Request())

sys.exit(run(Busy))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--domain-id", type=int, default=97)
    a = ap.parse_args()
    env = dict(os.environ, ROS_DOMAIN_ID=str(a.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    codes: collections.Counter[int] = collections.Counter()
    first_failure = None
    for i in range(a.runs):
        p = subprocess.Popen([sys.executable, "-c", NODE], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if p.stdout.readline().strip() != "ready":
            print(p.communicate()[1], file=sys.stderr)
            return 1
        time.sleep(random.uniform(0.1, 0.4))
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=30)
        codes[p.returncode] += 1
        if p.returncode and first_failure is None:
            first_failure = err[-2000:]
        print(f"\rrun {i + 1}/{a.runs}: exit codes {dict(codes)}", end="", flush=True)
    print()
    if first_failure:
        print(f"first failure:\n{first_failure}")
    return 0 if set(codes) == {0} else 1


if __name__ == "__main__":
    raise SystemExit(main())
