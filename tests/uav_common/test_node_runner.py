"""node_runner.run: Ctrl-C that lands inside rclpy's C++ code still ends a node cleanly (exit 0),
while a real error in a callback still ends it with a traceback (exit 1); call_until_answered asks again when an
answer is lost."""

import os
import subprocess
import sys
import time

import pytest

from conftest import fresh_domain
from uav_common.node_runner import call_until_answered, interrupted

# A node whose first timer callback raises what the test passes in; close() proves the clean-up ran.
NODE = """
import sys
from rclpy.node import Node
from uav_common.node_runner import run

class N(Node):
    def __init__(self):
        super().__init__("runner_probe")
        self.create_timer(0.01, self.tick)

    def tick(self):
        {raise_line}

    def close(self):
        print("closed", flush=True)

sys.exit(run(N))
"""


def run_node(raise_line: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, ROS_DOMAIN_ID=str(fresh_domain()), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    code = NODE.format(raise_line=raise_line)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)


def test_ctrl_c_wrapped_by_pybind11_exits_cleanly():
    # What rclpy's take_response raises when SIGINT arrives while it builds the response message.
    p = run_node('raise SystemError("take_response returned a result with an exception set") from KeyboardInterrupt()')
    assert p.returncode == 0, p.stderr[-2000:]
    assert "closed" in p.stdout
    assert "Traceback" not in p.stderr


def test_an_error_raised_after_shutdown_began_exits_cleanly():
    # What rclpy's take_message raised once in CI when SIGINT shut the context down mid-take.
    p = run_node("import rclpy; rclpy.shutdown(); raise RuntimeError(\"Unable to convert call argument '0'\")")
    assert p.returncode == 0, p.stderr[-2000:]
    assert "closed" in p.stdout and "Traceback" not in p.stderr


def test_an_error_raised_a_moment_before_the_shutdown_it_goes_with_exits_cleanly():
    # rclpy shuts the context down on Ctrl-C from its own signal thread: the error in the main thread can come first.
    raise_line = "import rclpy, threading; threading.Timer(0.2, rclpy.shutdown).start(); "
    p = run_node(raise_line + "raise RuntimeError(\"Unable to convert call argument '0'\")")
    assert p.returncode == 0, p.stderr[-2000:]
    assert "closed" in p.stdout and "Traceback" not in p.stderr


def test_a_real_error_in_a_callback_still_fails_with_its_traceback():
    p = run_node('raise SystemError("a real bug")')
    assert p.returncode == 1
    assert "a real bug" in p.stderr and "Traceback" in p.stderr
    assert "closed" in p.stdout  # the final checkpoint is still written on the way out


@pytest.mark.parametrize(
    "chain, expected",
    [
        (KeyboardInterrupt(), True),
        (ValueError("x"), False),
        (SystemError("wrapped"), False),
    ],
)
def test_interrupted_reads_the_cause_chain(chain, expected):
    assert interrupted(chain) is expected
    outer = RuntimeError("outer")
    outer.__cause__ = SystemError("middle")
    outer.__cause__.__context__ = chain
    assert interrupted(outer) is expected


def test_interrupted_survives_a_cycle():
    a, b = ValueError("a"), ValueError("b")
    a.__context__, b.__context__ = b, a
    assert interrupted(a) is False


class LossyClient:
    """A service client whose first `lose` answers never arrive (a response sent before the server's writer matched
    our reader); `withdrawn` holds the requests given up on."""

    def __init__(self, lose: int):
        from rclpy.task import Future

        self.future_type, self.lose, self.asked, self.withdrawn = Future, lose, 0, []

    def wait_for_service(self, timeout_sec):
        return True

    def call_async(self, request):
        future = self.future_type()
        self.asked += 1
        if self.asked > self.lose:
            future.set_result(f"answer to {request}")
        return future

    def remove_pending_request(self, future):
        self.withdrawn.append(future)


class IdleExecutor:
    def spin_until_future_complete(self, future, timeout_sec):
        if not future.done():
            time.sleep(timeout_sec)


def test_a_lost_answer_is_asked_for_again_and_the_unanswered_request_withdrawn():
    client = LossyClient(lose=2)
    assert call_until_answered(IdleExecutor(), client, "pause", timeout_s=5.0, ask_every_s=0.05) == "answer to pause"
    assert client.asked == 3
    assert len(client.withdrawn) == 2 and not any(f.done() for f in client.withdrawn)


def test_no_answer_within_the_timeout_is_none():
    client = LossyClient(lose=10**6)
    start = time.monotonic()
    assert call_until_answered(IdleExecutor(), client, "pause", timeout_s=0.3, ask_every_s=0.05) is None
    assert 0.3 <= time.monotonic() - start < 2.0
    assert client.asked >= 3 and len(client.withdrawn) == client.asked
