"""Flying a camera alone (no simulator, no ROS): its frames go into a stack sampled one step period apart; the
newest is answered at most once per control period, and when frames stop for frame_timeout_s a stop is due
until they come back (the safety layer's job). Times are time.monotonic() seconds.

`log` is a logger with rclpy's signature (warning/info(message, throttle_duration_sec=...)).
"""

from __future__ import annotations

import math

import numpy as np

from uav_common.frame_stack import SampledStack

JITTER = 0.8  # a frame is answered at once when this share of the control period has passed (camera clocks jitter)


class CameraControl:
    def __init__(self, frames: int, step_duration_s: float, control_period_s: float, frame_timeout_s: float, log):
        self.log = log
        self.control_period_s, self.frame_timeout_s = control_period_s, frame_timeout_s
        self.sampled = SampledStack(frames, step_duration_s)
        self.pending = None  # the newest frame not yet answered: (what the caller gave, its network input)
        self.last_frame = None  # when the last frame came (None: no camera frames)
        self.last_answer = -math.inf  # when the last answered frame came (or the last stop went out)
        self.stopping_since = None  # frames stopped: stop commands go out
        self.restarts = 0  # frame stamps that went back

    @property
    def active(self) -> bool:
        """Camera frames are being flown (none yet, or a simulator found: False)."""
        return self.last_frame is not None

    def add(self, stamp_s: float, net_in: np.ndarray, item, now: float) -> bool:
        """A frame (its stamp, network input and whatever the caller answers it with); True when it is to be
        answered now (take()), else it waits for the next tick."""
        if not self.sampled.add(stamp_s, net_in):
            self.restarts += 1
            self.log.warning("depth frame stamps went back: starting a new frame stack", throttle_duration_sec=5.0)
        if self.stopping_since is not None:
            self.log.info(f"depth frames are back after {now - self.stopping_since:.1f} s: flying again")
            self.stopping_since = None
        self.last_frame = now
        self.pending = (item, now)
        return now - self.last_answer >= JITTER * self.control_period_s

    def new_stack(self) -> None:
        """Another camera is taken: nothing of the last one's is stacked with its frames or answered."""
        self.sampled.clear()
        self.pending = None

    def take(self) -> tuple[object, np.ndarray]:
        """The pending frame's item and the sampled state it is answered on."""
        (item, arrived), self.pending = self.pending, None
        self.last_answer = arrived  # the control period runs from frame to frame, not from answer to frame
        return item, self.sampled.state()

    def tick(self, now: float, stops: bool) -> str | None:
        """At twice the control rate: "answer" (take() the frame that came within the period), "stop" (frames
        stopped and `stops`: a stop command is due; call stopped()), else None."""
        if self.last_frame is None or now - self.last_answer < self.control_period_s:
            return None
        if self.pending is not None:
            return "answer"
        if stops and now - self.last_frame > self.frame_timeout_s:
            return "stop"
        return None

    def stopped(self, now: float) -> None:
        """A stop command went out."""
        if self.stopping_since is None:
            self.stopping_since = self.last_frame
            self.log.warning(f"no depth frame for {self.frame_timeout_s:g} s: commanding a stop until frames come back")
        self.last_answer = now

    def hand_over(self) -> np.ndarray | None:
        """The frames came from a simulator after all: stop sampling; the state answered so far (None if none)."""
        state = None if self.sampled.empty else self.sampled.state()
        self.last_frame, self.pending, self.stopping_since = None, None, None
        self.sampled.clear()
        return state

    def problem(self, now: float) -> str | None:
        if self.stopping_since is None:
            return None
        return f"no depth frame for {now - self.stopping_since:.1f} s: stop commanded"
