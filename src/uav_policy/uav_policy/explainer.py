"""What each decision looks at, measured (no ROS): SAM's attention is at hand; the CNN's Grad-CAM saliency costs a
backward pass, so it is computed only for a subscriber or a measurement. Every `every`-th decision is measured
(insight.Insight). The costly part runs at once for a simulator's frames (the simulator waits for the answer) and on
a worker thread for a camera's, so the next frame is not delayed; a camera frame that comes while the worker is busy
is not measured (counted as skipped).

`log` is a logger with rclpy's signature (warning(message, throttle_duration_sec=...)).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from .insight import Insight, explanation


class Explainer:
    def __init__(self, grid_hw: tuple[int, int], every: int, window: int, seed: int, log):
        self.every, self.window, self.seed, self.log = every, window, seed, log
        self.insight = Insight(grid_hw, window, seed)
        self.lock = threading.Lock()  # the insight is measured on a worker thread and read by diagnostics
        self.busy = threading.Lock()  # held while the worker measures
        self.skipped = 0  # camera frames due a measurement that came while the worker was busy

    def explain(
        self,
        net,
        state: np.ndarray,
        q: np.ndarray,
        attention: np.ndarray | None,
        decision: int,
        saliency: Callable[[np.ndarray], None] | None,
        inline: bool,
    ) -> None:
        """After the `decision`-th decision (on `state`, with `q` and SAM's `attention`): `saliency(rows)`, when
        given, publishes the CNN's map; the decision is measured when due. `inline`: now, else on the worker."""
        measure = self.every > 0 and decision % self.every == 0
        if not (measure or saliency):
            return

        def job():
            try:
                greedy = int(np.argmax(q))
                rows = explanation(net, state, greedy, attention)
                if saliency:
                    saliency(rows)
                if measure:
                    with self.lock:
                        self.insight.observe(net, state, greedy, rows)
            except Exception as e:  # an explanation is never worth the flight
                self.log.warning(f"measuring a decision failed: {e!r}", throttle_duration_sec=10.0)

        if inline:
            job()
        elif self.busy.acquire(blocking=False):

            def work():
                try:
                    job()
                finally:
                    self.busy.release()

            threading.Thread(target=work, daemon=True).start()
        else:
            self.skipped += 1

    def regrid(self, grid_hw: tuple[int, int]) -> None:
        """A network of another attention grid: measured maps of the old one do not compare."""
        with self.lock:
            if grid_hw != self.insight.grid_hw:
                self.insight = Insight(grid_hw, self.window, self.seed)

    def values(self) -> dict:
        with self.lock:
            summary = self.insight.summary()
        return {} if summary is None else {**summary.values(), "insight_skipped": self.skipped}
