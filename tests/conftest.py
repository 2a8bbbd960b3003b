"""Shared fixtures: installed node processes in a private ROS domain, and an rclpy node to talk to them."""

from __future__ import annotations

import itertools
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
INSTALL = ROOT / "install"
SMALL_WORLD = str(ROOT / "tests" / "worlds" / "small.yaml")  # a small room, whatever the working directory
# Node logs go to a folder of this run, not ~/.ros/log (a test that sets its own ROS_LOG_DIR keeps it).
os.environ["ROS_LOG_DIR"] = tempfile.mkdtemp(prefix="uav_tests_roslog_")
sys.path[:0] = [str(ROOT / "src" / p) for p in ("uav_common", "uav_sim", "uav_policy", "uav_trainer", "uav_bringup")]

# A private domain per test: tests never hear each other or anything else on the machine. The harness draws
# 1-60, each pytest-xdist worker (scripts/test.sh runs two) from its own slice of it; a test that sets its own uses
# one of 61-101 that no other test uses (101 is the highest Linux allows without clashing with ephemeral ports).
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _WORKERS > 60:
    raise pytest.UsageError(f"-n {_WORKERS}: at most 60 test workers, each draws ROS domains of its own from 1-60")
_SLICE = 60 // _WORKERS
_FIRST = 1 + int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:]) * _SLICE
_domains = itertools.count(os.getpid() * 7)


def fresh_domain() -> int:
    """A ROS domain from this worker's slice of 1-60: the harness's, and the `ros_domain` fixture's."""
    return _FIRST + next(_domains) % _SLICE


@pytest.fixture
def ros_domain() -> str:
    """A domain of this test's own for the nodes it starts without the harness (a string, for environments). The
    cases of a parametrized test take this, never a fixed domain: two workers can run two cases at once."""
    return str(fresh_domain())


SHARED_DOMAIN = 99  # nodes that exit at once at start-up (run_to_exit, start_up_error): never a node that stays up
_DOMAIN_LITERALS = [
    re.compile(r"ROS_DOMAIN_ID['\"]?\s*[=:,]\s*['\"](\d+)['\"]"),  # env dicts, setenv
    re.compile(r"\bdomain(?:_id)?\s*=\s*['\"]?(\d+)['\"]?", re.IGNORECASE),  # domain="77", DOMAIN = "83"
    re.compile(r"\b(?:train_env|run_train)\([^,()]+,\s*['\"](\d+)['\"]"),
]


def fixed_domains(root: Path = ROOT / "tests") -> dict[int, set[str]]:
    """Each ROS domain a test file writes as a literal -> the tests (or module helpers) that use it."""
    out: dict[int, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        owner = f"{path.name} (module)"
        for line in path.read_text().splitlines():
            if line.startswith(("def ", "async def ", "class ")):
                owner = f"{path.name}::{line.split('(')[0].split()[-1].rstrip(':')}"
            for pattern in _DOMAIN_LITERALS:
                for m in pattern.finditer(line):
                    out.setdefault(int(m.group(1)), set()).add(owner)
    return out


def pytest_configure(config):
    """One torch intra-op thread in each test process, as the nodes and `train` have (torch_threads): two workers share
    the 2 cores, and torch's threads wait for each other at every operation, so a second thread held off its core (by
    the other worker, or the main job beside the suite) stalls the first (an in-process training test took 123 s
    beside `train`, against 14 s alone)."""
    import torch

    torch.set_num_threads(1)


def pytest_collection_finish(session):
    """Each test that starts nodes on a fixed domain has it to itself, outside the harness's 1-60 (below)."""
    problems = []
    for domain, owners in sorted(fixed_domains().items()):
        owners = {o for o in owners if not o.startswith("conftest.py")}
        if domain == SHARED_DOMAIN or not owners:
            continue
        if len(owners) > 1:
            problems.append(f"domain {domain} is used by {sorted(owners)}")
        if not 61 <= domain <= 101:
            problems.append(f"domain {domain} ({sorted(owners)}) lies outside 61-101")
    fixed = {o for d, owners in fixed_domains().items() if d != SHARED_DOMAIN for o in owners}
    cases = {f"{item.path.name}::{item.originalname}" for item in session.items if hasattr(item, "callspec")}
    for owner in sorted(cases & fixed):
        problems.append(f"{owner} is parametrized: its cases take the ros_domain fixture (they can run at once)")
    if problems:
        raise pytest.UsageError("fixed ROS domains must be one test's each: " + "; ".join(problems))


def deep_qos():
    """Reliable with a deep reader history: a slow Python reader loses nothing to the 250 Hz loop."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=10000)


def read_bag(path):
    """{topic: (msgtype, [deserialized messages])} of a recorded bag, through rosbags' reader."""
    from rosbags.highlevel import AnyReader

    out = {}
    with AnyReader([Path(path)]) as reader:
        for conn, _t, raw in reader.messages():
            entry = out.setdefault(conn.topic, (conn.msgtype, []))
            entry[1].append(reader.deserialize(raw, conn.msgtype))
    return out


def executable(pkg: str, exe: str) -> Path:
    """What `ros2 run pkg exe` runs."""
    path = INSTALL / pkg / "lib" / pkg / exe
    if not path.exists():
        pytest.fail(f"{path} is missing: run scripts/setup.sh (colcon build) first")
    return path


class RosHarness:
    def __init__(self, tmp_path: Path):
        import rclpy

        self.domain_id = fresh_domain()
        self.env = dict(
            os.environ,
            ROS_DOMAIN_ID=str(self.domain_id),
            ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
            PYTHONUNBUFFERED="1",
        )
        self.tmp = tmp_path
        self.procs: list[tuple[subprocess.Popen, Path]] = []
        self.context = rclpy.Context()
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.node = rclpy.create_node(f"test_client_{os.getpid()}", context=self.context)
        from rclpy.executors import SingleThreadedExecutor

        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def start(self, pkg: str, exe: str, *ros_args: str, name: str | None = None, args=()) -> subprocess.Popen:
        log = self.tmp / f"{name or exe}.log"
        cmd = [str(executable(pkg, exe)), *args]
        if ros_args:
            cmd += ["--ros-args", *ros_args]
        proc = subprocess.Popen(cmd, env=self.env, stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True)
        self.procs.append((proc, log))
        return proc

    def log_of(self, proc: subprocess.Popen) -> str:
        for p, log in self.procs:
            if p is proc:
                return log.read_text()
        raise KeyError(proc)

    def spin_until(self, predicate, timeout_s: float = 20.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.02)
        return predicate()

    def call(self, client, request, timeout_s: float = 20.0):
        """The response to an idempotent service request, asked again until answered; the test fails after
        `timeout_s`."""
        from uav_common.node_runner import call_until_answered

        response = call_until_answered(self.executor, client, request, timeout_s)
        if response is None:
            pytest.fail(f"{client.srv_name}: no answer within {timeout_s:g} s")
        return response

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def stop(self, proc: subprocess.Popen, timeout_s: float = 10.0) -> int:
        from uav_common.launching import stop_process

        return stop_process(proc, timeout_s)

    def close(self) -> None:
        for proc, _ in self.procs:
            self.stop(proc)
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


@pytest.fixture
def ros(tmp_path):
    h = RosHarness(tmp_path)
    try:
        yield h
    finally:
        h.close()


def run_to_exit(pkg: str, exe: str, *ros_args: str, timeout_s: float = 30.0) -> subprocess.CompletedProcess:
    """Run an installed node expected to exit by itself (e.g. on a bad parameter). Each start loads
    Python, rclpy and torch (seconds): test each node's exit path once this way, its many bad
    parameters with start_up_error."""
    env = dict(os.environ, ROS_DOMAIN_ID="99", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    cmd = [str(executable(pkg, exe))] + (["--ros-args", *ros_args] if ros_args else [])
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout_s)


def start_up_error(node_class, *ros_args: str) -> str:
    """The ParameterError `node_class` fails with at start-up under these --ros-args (what its process
    prints after "[FATAL]" before exiting 2), with the node built in this process and its own context."""
    import rclpy
    import torch

    from uav_common.ros_params import ParameterError

    context = rclpy.Context()
    rclpy.init(args=["test", "--ros-args", *ros_args], context=context, domain_id=99)
    threads = torch.get_num_threads()  # a node sets its own: keep this process's
    try:
        try:
            node = node_class(context=context)
        except ParameterError as e:
            return str(e)
        node.destroy_node()
        pytest.fail(f"{node_class.__name__} started with {ros_args}")
    finally:
        torch.set_num_threads(threads)
        context.try_shutdown()


def one_region_net():
    """A constructed network for the map measures: it turns (action 1) when anything in the top-left 8x8 pixels is
    nearer than 2 m, else flies straight (0)."""
    import torch

    class OneRegionNet(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.dummy = torch.nn.Parameter(torch.zeros(1))

        def forward(self, x):
            near = (x[:, :, :8, :8] < 2.0).flatten(1).any(dim=1).float()
            return torch.stack([1 - near, near, 0 * near, 0 * near], dim=1), None

    return OneRegionNet()
