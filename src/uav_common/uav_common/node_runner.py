"""`main()` plumbing shared by every node: init, spin, clean shutdown, fail-fast on bad parameters."""

from __future__ import annotations

import signal
import sys
import threading
import time

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.task import Future

from .ros_params import ParameterError


def run(node_factory, args=None) -> int:
    """Create the node, spin it until Ctrl-C or shutdown; exit code 2 for a bad parameter.

    Single-threaded on purpose: on these rclpy wheels the MultiThreadedExecutor answered a
    lockstep sim ~100x slower (measured: <2 frames/s vs 250 frames/s). Work that must not
    block the loop runs on worker threads awaited by async callbacks.
    """
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        # Ctrl-C stops the node through rclpy's handler, which shuts the context down and so ends spin(); the
        # KeyboardInterrupt it then passes on would land at a random moment in this thread, e.g. inside
        # rclpy.task.Future.__init__ (a push's call_async), whose half-built future then prints a traceback when
        # it is collected. A node with its own handler (record's DeferredInterrupt) keeps it.
        signal.signal(signal.SIGINT, lambda _signum, _frame: None)
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
    except Exception as e:
        # Shutting down (Ctrl-C invalidates the context) while rclpy takes a message, pybind11 may
        # raise a bare RuntimeError ("Unable to convert call argument '0'"): the shutdown, not a bug.
        if not interrupted(e) and not shutting_down():
            raise
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            if close is not None:
                close()
            code = code or getattr(node, "exit_code", 0)
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def in_thread(executor, fn) -> Future:
    """Run fn on a worker thread; the returned future can be awaited in an async callback, so the executor
    keeps serving other callbacks meanwhile."""
    fut = Future(executor=executor)

    def work():
        try:
            fut.set_result(fn())
        except Exception as e:  # handed to the awaiting callback
            fut.set_exception(e)

    threading.Thread(target=work, daemon=True).start()
    return fut


def call_until_answered(executor, client, request, timeout_s: float, ask_every_s: float = 2.0):
    """The response to an idempotent service request, or None if none comes within `timeout_s`. wait_for_service sees
    the server's request reader only: a response sent before the server's response writer has matched our reader is
    lost (seen on a loaded machine), so the request goes again every `ask_every_s`, the unanswered one withdrawn."""
    end = time.monotonic() + timeout_s
    while (left := end - time.monotonic()) > 0:
        if not client.wait_for_service(timeout_sec=min(ask_every_s, left)):
            continue
        future = client.call_async(request)
        executor.spin_until_future_complete(future, timeout_sec=max(0.01, min(ask_every_s, end - time.monotonic())))
        if future.done():
            return future.result()
        client.remove_pending_request(future)
    return None


def shutting_down(within_s: float = 1.0, context=None) -> bool:
    """Whether the context is shut down, or goes down within `within_s`. rclpy shuts it down on Ctrl-C from its
    own signal thread, while the KeyboardInterrupt lands in the main thread: an error that Ctrl-C caused there
    can come a moment before the shutdown it goes with. An error of our own comes with no shutdown."""
    end = time.monotonic() + within_s
    while rclpy.ok(context=context):
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


def interrupted(e: BaseException | None) -> bool:
    """Whether `e` is Ctrl-C in disguise. The signal can land while rclpy's C++ code builds a
    message (taking a service request or response); pybind11 then raises SystemError with the
    KeyboardInterrupt as its cause, and a node stopped with Ctrl-C would exit 1 with a traceback."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, (KeyboardInterrupt, ExternalShutdownException)):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


class DeferredInterrupt:
    """Ctrl-C as usual (KeyboardInterrupt), except inside `with hold:`, where it lands when the block ends:
    work that must not stop half-way (a record being written to a bag) finishes first.

    `install()` before rclpy.init: rclpy's own handler (which wakes the executor) then passes the signal on
    to this one."""

    def __init__(self):
        self.depth = 0
        self.pending = False

    def install(self) -> DeferredInterrupt:
        signal.signal(signal.SIGINT, self._on_signal)
        return self

    def _on_signal(self, _signum, _frame) -> None:
        if self.depth:
            self.pending = True
        else:
            raise KeyboardInterrupt

    def __enter__(self) -> None:
        self.depth += 1

    def __exit__(self, *_exc) -> None:
        self.depth -= 1
        if not self.depth and self.pending:
            self.pending = False
            raise KeyboardInterrupt
