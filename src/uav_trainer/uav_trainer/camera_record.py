"""The camera and reward window trainer_node records in every weights file (no ROS): the depth camera's field of
view from depth/camera_info (policy_node warns when it flies another), and sim_node's reward window, read back from
step_outcome's window_fov_rad (recorded when it is not the paper's 20 %). Whichever actor says them."""

from __future__ import annotations

import math

from uav_policy.weights import HFOV_RANGE_DEG
from uav_sim.reward import center_window_slices, window_fraction_for_fov


class CameraRecord:
    def __init__(self, training, log, set_camera):
        """`training`: the run (camera_hfov_deg, reward_window_fraction); `log`: rclpy's logger signature;
        `set_camera(intrinsics, hfov_deg)`: maps frames onto the input for every actor's pairing."""
        self.training, self.log, self.set_camera = training, log, set_camera
        self.width_px = None
        self.outcome_fov_rad = None

    def on_info(self, hfov_deg: float | None, width_px: int, intrinsics) -> None:
        if hfov_deg is None or not HFOV_RANGE_DEG[0] <= hfov_deg <= HFOV_RANGE_DEG[1]:
            self.log.warning("ignoring malformed depth/camera_info (width or fx)", throttle_duration_sec=10.0)
            return
        hfov = round(hfov_deg, 3)
        if hfov == self.training.camera_hfov_deg and width_px == self.width_px:
            return  # every step sends it; only a change is news
        if hfov != self.training.camera_hfov_deg:
            self.log.info(f"depth camera: {hfov:g} deg horizontal field of view (recorded in the weights files)")
            self.training.camera_hfov_deg = hfov
        self.width_px = width_px
        self.set_camera(intrinsics, hfov)
        self._update_window()

    def on_outcome_fov(self, fov_rad: float) -> None:
        if fov_rad != self.outcome_fov_rad:
            self.outcome_fov_rad = fov_rad
            self._update_window()

    def _update_window(self) -> None:
        """The reward window sim_node reads beta over, from its arc (step_outcome) and the camera (camera_info)."""
        hfov, width, fov = self.training.camera_hfov_deg, self.width_px, self.outcome_fov_rad
        if hfov is None or not width or fov is None or not 0.0 < fov <= math.radians(hfov) + 1e-3:  # also NaN
            return
        fraction = window_fraction_for_fov(width, hfov, fov)
        paper = center_window_slices(1, width)[1] == center_window_slices(1, width, fraction)[1]
        window = None if paper else fraction
        if window != self.training.reward_window_fraction:
            what = "the paper's 20 %" if paper else f"{fraction:g} of each side, recorded in the weights files"
            self.log.info(f"reward window: {what} ({math.degrees(fov):.1f} deg of arc)")
            self.training.reward_window_fraction = window
