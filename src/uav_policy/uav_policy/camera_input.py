"""Depth frames onto the network's input (no ROS): through the camera's intrinsics (depth/camera_info) onto the
field of view the weights were trained with, whole (stretched) while the camera is unknown, and a frame of another
size held for its first CameraInfo for CAMERA_INFO_WAIT_S at most.

`log` is a logger with rclpy's signature (warning/info(message, throttle_duration_sec=..., once=...)).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from uav_common.frame_stack import CameraView, NetworkInput

from . import weights as wio

CAMERA_INFO_WAIT_S = 2.0  # how long frames wait for their first CameraInfo (CameraInput.should_wait)


class CameraInput:
    def __init__(self, height: int, width: int, weights_hfov_deg: float | None, log, on_view: Callable[[float], None]):
        self.log, self.on_view = log, on_view  # on_view(hfov): the field of view frames are mapped onto changed
        self.weights_hfov_deg = weights_hfov_deg
        self.hfov_deg = None  # the camera's, from depth/camera_info
        self.intrinsics = None  # (fx, fy, cx, cy, width, height) from depth/camera_info
        self.to_input = NetworkInput(height, width)
        self.warned_mismatch = None
        self.warned_stretch = False
        self.wait_since = None  # when the first frame waited for depth/camera_info
        self.frames_before_info = 0
        self.bad_info = 0

    @property
    def trained_hfov_deg(self) -> float | None:
        """The field of view frames are mapped onto: the weights', else (a file that records none, or a
        network not trained yet) the camera's own, so that nothing is cropped; None while neither is known."""
        return self.weights_hfov_deg if self.weights_hfov_deg is not None else self.hfov_deg

    @property
    def view(self) -> CameraView | None:
        return self.to_input.view

    def on_info(self, intrinsics, hfov_deg: float | None) -> bool:
        """A CameraInfo's intrinsics (None: malformed, counted and ignored); False when it was ignored."""
        if intrinsics is None:
            self.bad_info += 1
            self.log.warning(
                "ignoring malformed depth/camera_info (size or focal length): frames fill the network's input whole",
                throttle_duration_sec=10.0,
            )
            return False
        if intrinsics != self.intrinsics:
            self.intrinsics, self.hfov_deg = intrinsics, hfov_deg
            self._map()
        self._check()
        return True

    def set_weights(self, height: int, width: int, weights_hfov_deg: float | None) -> None:
        """New weights (a push): their input size and camera."""
        self.weights_hfov_deg = weights_hfov_deg
        self.to_input = NetworkInput(height, width)
        self._map()
        self._check()

    def _map(self) -> None:
        hfov = self.trained_hfov_deg
        if hfov is None:
            return
        if self.intrinsics is not None:
            self.to_input.set_camera(self.intrinsics, hfov)
        self.on_view(hfov)

    def _check(self) -> None:
        """Warn once per mismatch between the camera and the camera the weights were trained with."""
        key = wio.camera_mismatch(self.weights_hfov_deg, self.hfov_deg)
        if key is None or key == self.warned_mismatch:
            return
        self.warned_mismatch = key
        fx, fy, cx, cy, w, h = self.intrinsics
        height, width = self.to_input.hw
        view = CameraView.from_intrinsics(fx, fy, cx, cy, w, h, key[0], height, width)
        how = (
            f"frames are cropped to it (it sees {100 * view.coverage:.0f}% of the trained view)"
            if key[1] > key[0]
            else f"frames cover {100 * view.coverage:.0f}% of the trained view, the rest reads as no return"
        )
        self.log.warning(
            f"the weights were trained with a {key[0]:g} deg camera, but depth/camera_info says {key[1]:.1f} deg: "
            f"{how}; expect more crashes. Weights trained behind this camera fly it better (docs/REAL_CAMERA.md)"
        )

    def should_wait(self, height: int, width: int, now: float, info_offered: Callable[[], bool]) -> bool:
        """A frame of another size than the network's input is not used before its CameraInfo (it would be
        stretched over the wrong field of view) while a publisher offers one (`info_offered()`), for
        CAMERA_INFO_WAIT_S at most: a driver that sent its CameraInfo only once, before we listened, still gets
        flown (stretched)."""
        if self.intrinsics is not None or (height, width) == self.to_input.hw:
            return False
        self.wait_since = now if self.wait_since is None else self.wait_since
        if now - self.wait_since > CAMERA_INFO_WAIT_S or not info_offered():
            return False
        self.frames_before_info += 1
        return True

    def __call__(self, depth: np.ndarray) -> np.ndarray:
        """The frame on the network's input: through CameraInfo onto the trained field of view, else whole."""
        hw = self.to_input.hw
        if self.intrinsics is None and depth.shape != hw and not self.warned_stretch:
            self.warned_stretch = True
            self.log.warning(
                f"no depth/camera_info yet: {depth.shape[1]}x{depth.shape[0]} frames fill the "
                f"{hw[1]}x{hw[0]} input whole (their field of view is unknown)"
            )
        return self.to_input(depth)

    def problem(self) -> str | None:
        """The camera differs from the weights' (a WARN on /diagnostics), in words."""
        mismatch = wio.camera_mismatch(self.weights_hfov_deg, self.hfov_deg)
        if mismatch is None:
            return None
        cover = f", covering {100 * self.view.coverage:.0f}% of it" if self.view is not None else ""
        return f"camera {mismatch[1]:g} deg, but the weights were trained with a {mismatch[0]:g} deg camera{cover}"

    def values(self) -> dict:
        return {
            "malformed_camera_info": self.bad_info,
            "frames_before_camera_info": self.frames_before_info,
            "camera_coverage": f"{self.view.coverage:.2f}" if self.view is not None else "-",
        }
