"""A simulator's frames and step outcomes (no ROS): joined by stamp, stacked (a new stack when an outcome starts an
episode or the stamps go back), and with wait_for_trainer held until trainer_node releases them (push.ReleaseGate),
each answered once.

`log` is a logger with rclpy's signature (warning(message, throttle_duration_sec=...)).
"""

from __future__ import annotations

import numpy as np

from uav_common import contract
from uav_common.frame_stack import FrameStack

from .push import ReleaseGate


class SimulatorLink:
    def __init__(self, frames: int, hold: bool, wait_timeout_s: float, log, odom: bool = False):
        """With `odom` (a shield), a frame is answered once the odometry of its stamp has come too."""
        self.log, self.hold, self.wait_timeout_s = log, hold, wait_timeout_s
        self.joiner = contract.StampJoiner(("frame", "outcome", "odom") if odom else ("frame", "outcome"))
        self.stack = FrameStack(frames)
        self.gate = ReleaseGate(wait_timeout_s)
        self.last_stamp = None  # the last frame answered (the caller sets it, a camera's frames included)

    def add(self, stream: str, stamp: int, msg, now: float) -> tuple[dict | None, bool]:
        """A frame, outcome or odometry -> (the joined messages to answer now or None, whether the stamps went back: the
        source restarted, and nothing from before is answered or stacked with what comes now)."""
        restarts = self.joiner.restarts
        joined = self.joiner.add(stream, stamp, msg)
        restarted = self.joiner.restarts != restarts
        if restarted:
            before = self.last_stamp
            self.stack = FrameStack(self.stack.frames)
            self.last_stamp = None
            held = self.gate.restart()
            self.log.warning(
                f"{stream} stamps went back ({stamp / 1e9:.3f} s after {before / 1e9 if before is not None else 0:.3f} s): "
                f"the source restarted; starting a new frame stack" + (f" ({held} held frames dropped)" if held else ""),
                throttle_duration_sec=5.0,
            )
        if joined is not None and self.hold and self.gate.hold(stamp, joined, now):
            return None, restarted
        return joined, restarted

    def new_stack(self) -> None:
        """Another camera is taken: its frames start a new stack."""
        self.stack = FrameStack(self.stack.frames)

    def state(self, net_in: np.ndarray, new_episode: bool) -> np.ndarray:
        """The stack with a frame's network input on top: the state it is answered on."""
        return self.stack.reset(net_in) if new_episode or self.stack.empty else self.stack.push(net_in)

    def expired(self, now: float) -> list:
        """wait_for_trainer: frames the trainer has not released in time, to answer anyway (so the vehicle never
        stalls; the run has left lockstep and the warning says so)."""
        stamp, released = self.gate.expired(now)
        if stamp is not None:
            self.log.warning(
                f"trainer_node did not release the frame at {stamp / 1e9:.1f} s sim time within {self.wait_timeout_s:g} s: "
                f"answering it anyway ({self.gate.timed_out} so far; learning is no longer in lockstep)",
                throttle_duration_sec=10.0,
            )
        return released

    def values(self) -> dict:
        return {
            "frames_without_outcome": self.joiner.dropped["outcome"],
            "outcomes_without_frame": self.joiner.dropped["frame"],
            "duplicate_messages": self.joiner.duplicates,
            "frames_said_again": self.joiner.late,
            "stamp_restarts": self.joiner.restarts,
            "frames_held": len(self.gate.held),
            "released_by_timeout": self.gate.timed_out,
        }
