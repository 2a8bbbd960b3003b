"""Forward-looking depth camera rendered with pybullet's TinyRenderer, in REP 118/117 form."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pybullet as p


@dataclasses.dataclass(frozen=True)
class CameraIntrinsics:
    width: int
    height: int
    hfov_deg: float

    @property
    def focal_px(self) -> float:
        """fx = fy = (w/2) / tan(hfov/2): square pixels."""
        return (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan((self.height / 2.0) / self.focal_px))

    def k_matrix(self) -> list[float]:
        """Row-major 3x3 K for sensor_msgs/CameraInfo (principal point at the image centre)."""
        f = self.focal_px
        return [f, 0.0, self.width / 2.0, 0.0, f, self.height / 2.0, 0.0, 0.0, 1.0]


def zbuffer_to_depth_m(zbuf: np.ndarray, near_m: float, far_m: float) -> np.ndarray:
    """Metric depth along the optical axis from OpenGL's non-linear z-buffer in [0, 1]."""
    zbuf = np.asarray(zbuf, dtype=np.float64)
    return (far_m * near_m / (far_m - (far_m - near_m) * zbuf)).astype(np.float32)


class DepthCamera:
    """Renders metric depth (m) from a pose; +Inf where nothing is within `max_range_m`."""

    def __init__(self, client: int, intrinsics: CameraIntrinsics, min_range_m: float, max_range_m: float):
        if not 0.0 < min_range_m < max_range_m:
            raise ValueError(f"need 0 < min_range_m < max_range_m, got {min_range_m}, {max_range_m}")
        self.client = client
        self.intrinsics = intrinsics
        self.min_range_m = min_range_m
        self.max_range_m = max_range_m
        # A slightly farther far plane so that a surface exactly at max range is still seen.
        self._far_m = max_range_m * 1.001
        self._projection = p.computeProjectionMatrixFOV(
            fov=intrinsics.vfov_deg,
            aspect=intrinsics.width / intrinsics.height,
            nearVal=min_range_m,
            farVal=self._far_m,
            physicsClientId=client,
        )

    def render(self, eye_xyz: tuple[float, float, float], yaw_rad: float) -> np.ndarray:
        """Depth image (H, W) float32 for a camera at `eye_xyz` looking along `yaw_rad` (level)."""
        return self._render(eye_xyz, yaw_rad, False)[0]

    def render_with_ids(self, eye_xyz: tuple[float, float, float], yaw_rad: float) -> tuple[np.ndarray, np.ndarray]:
        """The depth image and, per pixel, the pybullet body id it shows (-1 where nothing is within range)."""
        depth, seg = self._render(eye_xyz, yaw_rad, True)
        ids = np.where(seg >= 0, seg & ((1 << 24) - 1), -1)  # the mask packs the link index above bit 24
        ids[~np.isfinite(depth)] = -1
        return depth, ids

    def _render(self, eye_xyz, yaw_rad: float, with_ids: bool) -> tuple[np.ndarray, np.ndarray | None]:
        fwd = (math.cos(yaw_rad), math.sin(yaw_rad), 0.0)
        target = (eye_xyz[0] + fwd[0], eye_xyz[1] + fwd[1], eye_xyz[2])
        view = p.computeViewMatrix(eye_xyz, target, (0.0, 0.0, 1.0), physicsClientId=self.client)
        w, h = self.intrinsics.width, self.intrinsics.height
        _, _, _, zbuf, seg = p.getCameraImage(
            w,
            h,
            view,
            self._projection,
            renderer=p.ER_TINY_RENDERER,
            flags=0 if with_ids else p.ER_NO_SEGMENTATION_MASK,
            physicsClientId=self.client,
        )
        depth = zbuffer_to_depth_m(np.reshape(zbuf, (h, w)), self.min_range_m, self._far_m)
        depth[depth > self.max_range_m] = np.inf
        return depth, np.reshape(np.asarray(seg, dtype=np.int64), (h, w)) if with_ids else None
