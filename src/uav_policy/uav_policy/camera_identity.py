"""One camera per frame stack (no ROS): frames are stacked only with frames of the camera they came from.

Two cameras publishing on one topic (a remap or namespace mistake) would otherwise be stacked into one state, and
the network would act on a mixture of two views. The first frame's `header.frame_id` is the camera kept. A frame
with another frame id is dropped and counted; /diagnostics is ERROR while such frames come (and ERROR_HOLD_S
after). A camera whose frame id changes for good (a driver restarted under another name) is taken once the kept
camera has sent nothing for `switch_after_s` while the new one keeps sending: its frames then start a new stack.
Times are time.monotonic() seconds; `log` has rclpy's signature.
"""

from __future__ import annotations

ERROR_HOLD_S = 2.0  # /diagnostics stays ERROR this long after the last foreign frame


class CameraIdentity:
    def __init__(self, switch_after_s: float, log, stacks=()):
        """`stacks`: what stacks frames (each with new_stack()), restarted when another camera is taken."""
        self.switch_after_s, self.log, self.stacks = switch_after_s, log, stacks
        self.frame_id: str | None = None  # the camera whose frames are stacked
        self.last_own = 0.0  # when its last frame came
        self.foreign: dict[str, int] = {}  # other frame ids -> frames dropped
        self.last_foreign: float | None = None
        self.switches = 0

    def admit(self, frame_id: str, now: float) -> bool:
        """True to stack the frame; False for another camera's, dropped. When the kept camera is gone this one is
        taken (True), and the stacks restart first."""
        if self.frame_id is None or frame_id == self.frame_id:
            self.frame_id, self.last_own = frame_id, now
            return True
        if now - self.last_own >= self.switch_after_s:
            self.log.warning(
                f"depth frames from camera '{self.frame_id}' stopped {now - self.last_own:.1f} s ago and '{frame_id}' "
                "sends: taking it, with a new frame stack"
            )
            self.frame_id, self.last_own = frame_id, now
            self.switches += 1
            for stack in self.stacks:
                stack.new_stack()
            return True
        self.foreign[frame_id] = self.foreign.get(frame_id, 0) + 1
        self.last_foreign = now
        self.log.error(
            f"dropping depth frames of camera '{frame_id}': this stack holds camera '{self.frame_id}' (two cameras on "
            "one topic?)",
            throttle_duration_sec=5.0,
        )
        return False

    def problem(self, now: float) -> str | None:
        """An ERROR while another camera's frames come on the topic, else None."""
        if self.last_foreign is None or now - self.last_foreign > ERROR_HOLD_S:
            return None
        return f"frames of another camera ({', '.join(sorted(self.foreign))}) on the depth topic: dropped"

    def values(self) -> dict:
        return {
            "camera_frame_id": "-" if self.frame_id is None else self.frame_id,
            "other_camera_frames_dropped": sum(self.foreign.values()),
            "other_camera_frame_ids": ", ".join(sorted(self.foreign)) or "-",
            "camera_switches": self.switches,
        }
