"""How policy_node answers frames (no ROS): frames received, lost on the way, answered and malformed, the latency from a
frame's arrival to its command, and per report the answers per second and the time each took."""

from __future__ import annotations

import time
from collections import deque

import numpy as np

from uav_common import contract


class AnswerStats:
    def __init__(self):
        self.received = self.answered = self.malformed = self.lost = 0
        self.last_sequence = None  # the depth publisher's sequence number of the last frame that came
        self.spent_s = 0.0  # answering frames since the last report (network and publishing)
        self.latency_ms = deque(maxlen=1000)  # frame arrival to cmd_vel published
        self.reported = (time.monotonic(), 0, 0, 0, 0)  # (when, answered, malformed, received, lost) at the last report
        self.recent = 0  # frames answered between the last two reports

    def arrived(self, sequence: int | None, publishers) -> None:
        """A depth frame came with its publisher's sequence number: a gap since the last one counts the frames lost
        between the camera and this node (dropped best effort, a large frame's fragment lost). Only with one publisher
        on the topic (`publishers()`, asked only at a gap): several interleave their numbers. A publisher that
        restarts counts from 1 again: no gap."""
        last, self.last_sequence = self.last_sequence, sequence
        if sequence is not None and last is not None and sequence > last + 1 and publishers() == 1:
            self.lost += sequence - last - 1

    def decode(self, img, log) -> np.ndarray | None:
        """A depth Image in metres, or None: a malformed one is counted and logged (throttled)."""
        try:
            return contract.image_to_depth(img)
        except ValueError as e:
            self.malformed += 1
            log.warning(f"ignoring malformed depth frame: {e}", throttle_duration_sec=2.0)
            return None

    def answer(self, t_in: float, t0: float, t_out: float) -> None:
        """A frame that arrived at `t_in` was answered: its decision began at `t0`, its command went out at `t_out`,
        and all that goes with it is done now (time.perf_counter())."""
        now = time.perf_counter()
        self.latency_ms.append(1e3 * (t_out - t_in))
        self.answered += 1
        self.spent_s += now - t0

    def report(self, now: float, waiting: bool) -> tuple[list[str], dict]:
        """Since the last report: problems in words (`waiting`: frames are held on purpose) and the values."""
        when, answered, malformed, received, lost = self.reported
        acts, bad, came = self.answered - answered, self.malformed - malformed, self.received - received
        self.reported, self.recent = (now, self.answered, self.malformed, self.received, self.lost), acts
        problems = []
        if bad:
            problems.append(f"{bad} malformed depth frame(s) ignored in the last {now - when:.1f} s")
        if self.lost > lost:
            problems.append(
                f"{self.lost - lost} depth frame(s) lost on the way from the camera in the last {now - when:.1f} s "
                "(large frames: the Fast DDS profile in docs/REAL_CAMERA.md)"
            )
        if came and not acts and not waiting:
            problems.append(f"{came} depth frame(s) in the last {now - when:.1f} s and none answered")
        lat = np.percentile(self.latency_ms, (50, 99)) if self.latency_ms else None
        values = {
            "frames_answered": self.answered,
            "malformed_frames": self.malformed,
            "frames_received": self.received,
            "frames_lost": self.lost,
            "latency_ms_p50": f"{lat[0]:.2f}" if lat is not None else "-",
            "latency_ms_p99": f"{lat[1]:.2f}" if lat is not None else "-",
            "answers_per_s": f"{acts / max(now - when, 1e-6):.1f}",
            "ms_per_answer": f"{1e3 * self.spent_s / acts:.2f}" if acts else "-",
        }
        self.spent_s = 0.0
        return problems, values
