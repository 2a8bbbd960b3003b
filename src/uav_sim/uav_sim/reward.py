"""The paper's reward, in one place: every package imports it from here.

R = 3 + beta/5          if beta > delta
R = -delta/(beta + 0.5) if beta <= delta
R = -10                 on collision (the episode ends)

beta is the minimum depth (m) in the central window (20% of width and height) of the
new depth frame; delta = 3 m.
"""

from __future__ import annotations

import math

import numpy as np

DELTA_M = 3.0
COLLISION_REWARD = -10.0
CENTER_WINDOW_FRACTION = 0.2


def center_window_slices(height: int, width: int, fraction: float = CENTER_WINDOW_FRACTION):
    """Row and column slices of the central window covering `fraction` of each side.

    The window is at least one pixel and is centred (for odd leftovers the extra pixel
    goes to the bottom/right edge).
    """
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    wh = max(1, int(round(height * fraction)))
    ww = max(1, int(round(width * fraction)))
    r0 = (height - wh) // 2
    c0 = (width - ww) // 2
    return slice(r0, r0 + wh), slice(c0, c0 + ww)


def center_window_min_depth(depth_m: np.ndarray, max_range_m: float, fraction: float = CENTER_WINDOW_FRACTION) -> float:
    """beta: the minimum metric depth (m) in the central window of a depth image.

    REP 117 values are honoured: +Inf (nothing within range) counts as `max_range_m`,
    -Inf (too close to measure) counts as 0, NaN (invalid) is ignored. A window with no
    valid pixel at all reads as `max_range_m`.
    """
    rows, cols = center_window_slices(*_image_shape(depth_m), fraction)
    return min(_nearest(depth_m[rows, cols]), float(max_range_m))


def floor_beta_m(
    camera_height_m: float, height: int, width: int, hfov_deg: float, fraction: float = CENTER_WINDOW_FRACTION
) -> float:
    """The depth (m) at which a flat floor enters the central window of a level pinhole camera
    `camera_height_m` above it (square pixels, so tan(vfov/2) = tan(hfov/2) * height / width):
    the window's lower edge sees the floor there, so beta can never exceed it. +Inf if the window
    does not reach below the horizon. Under DELTA_M every step's reward is negative, even in an
    empty room, and an agent learns that ending episodes early pays (e.g. 64 x 64 at 150 degrees: 1.43 m)."""
    rows, _ = center_window_slices(height, width, fraction)
    below = (rows.stop - height / 2) / (height / 2) * math.tan(math.radians(hfov_deg) / 2) * height / width
    return camera_height_m / below if below > 0 else math.inf


def window_fov_rad(width: int, hfov_deg: float, fraction: float = CENTER_WINDOW_FRACTION) -> float:
    """The horizontal angle (rad) the central window's columns cover behind a pinhole camera: the arc
    beta is read over (step_outcome's window_fov_rad). Not `fraction` of the field of view: at 120
    degrees the paper's 20 % window (13 of 64 columns) spans 38.7 degrees, not 24."""
    _, cols = center_window_slices(1, width, fraction)
    t = math.tan(math.radians(hfov_deg) / 2)
    left, right = ((c - width / 2) / (width / 2) * t for c in (cols.start, cols.stop))
    return math.atan(right) - math.atan(left)


def window_fraction_for_fov(width: int, hfov_deg: float, fov_rad: float) -> float:
    """The window (share of the image side, whole pixels: n / width) whose arc window_fov_rad is nearest
    `fov_rad`: reads a reward window back from step_outcome's window_fov_rad."""
    n = min(range(1, width + 1), key=lambda k: abs(window_fov_rad(width, hfov_deg, k / width) - fov_rad))
    return n / width


def _image_shape(depth_m: np.ndarray) -> tuple[int, int]:
    if depth_m.ndim != 2:
        raise ValueError(f"depth image must be 2-D (H, W), got shape {depth_m.shape}")
    return depth_m.shape


def _nearest(pixels: np.ndarray) -> float:
    """The nearest REP 117 return: -Inf (too close) counts as 0, NaN is ignored, +Inf when none."""
    px = np.asarray(pixels, dtype=np.float64)
    valid = np.where(np.isneginf(px), 0.0, px)[~np.isnan(px)]
    return float(max(valid.min(), 0.0)) if valid.size else math.inf


def step_reward(beta_m: float, collided: bool, delta_m: float = DELTA_M) -> float:
    """Reward of one step: -10 on collision, else the paper's distance-shaped term."""
    if collided:
        return COLLISION_REWARD
    if math.isnan(beta_m) or beta_m < 0.0:
        raise ValueError(f"beta must be a non-negative depth in metres, got {beta_m}")
    if beta_m > delta_m:
        return 3.0 + beta_m / 5.0
    return -delta_m / (beta_m + 0.5)
