"""`main()` plumbing shared by every node: init, spin, clean shutdown, fail-fast on bad parameters."""

from __future__ import annotations

import sys

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor

from .ros_params import ParameterError


def run(node_factory, args=None, threads: int = 1) -> int:
    """Create the node, spin it until Ctrl-C or shutdown; exit code 2 for a bad parameter."""
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = node_factory()
        executor = MultiThreadedExecutor(num_threads=threads) if threads > 1 else SingleThreadedExecutor()
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
            node.destroy_node()
        rclpy.try_shutdown()
    return code
