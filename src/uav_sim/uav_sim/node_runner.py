"""`main()` plumbing shared by every node: init, spin, clean shutdown, fail-fast on bad parameters."""

from __future__ import annotations

import sys

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from .ros_params import ParameterError


def run(node_factory, args=None) -> int:
    """Create the node, spin it until Ctrl-C or shutdown; exit code 2 for a bad parameter.

    Single-threaded on purpose: on these rclpy wheels the MultiThreadedExecutor answered a
    lockstep sim ~100x slower (measured: <2 frames/s vs 250 frames/s). Work that must not
    block the loop runs on worker threads awaited by async callbacks.
    """
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = node_factory()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except ParameterError as e:
        print(f"[FATAL] {e}", file=sys.stderr, flush=True)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            if close is not None:
                close()
            code = code or getattr(node, "exit_code", 0)
            node.destroy_node()
        rclpy.try_shutdown()
    return code
