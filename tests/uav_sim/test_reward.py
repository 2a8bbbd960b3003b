import math

import numpy as np
import pytest

from uav_sim.reward import (
    center_window_min_depth,
    center_window_slices,
    step_reward,
    window_fov_rad,
    window_fraction_for_fov,
)


def test_reward_hand_computed_values():
    assert step_reward(5.0, False) == pytest.approx(3.0 + 1.0)  # safe: 3 + beta/5
    assert step_reward(10.0, False) == pytest.approx(5.0)
    assert step_reward(3.0, False) == pytest.approx(-3.0 / 3.5)  # beta == delta counts as too close
    assert step_reward(1.0, False) == pytest.approx(-2.0)  # -3 / 1.5
    assert step_reward(0.0, False) == pytest.approx(-6.0)  # -3 / 0.5: finite at contact
    assert step_reward(7.0, True) == -10.0  # a collision overrides the distance term


def test_reward_rejects_invalid_beta():
    with pytest.raises(ValueError):
        step_reward(float("nan"), False)
    with pytest.raises(ValueError):
        step_reward(-1.0, False)


def test_center_window_is_central_20_percent():
    rows, cols = center_window_slices(64, 64)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (25, 38, 25, 38)  # 13 px = round(12.8); margins 25 and 26
    rows, cols = center_window_slices(100, 50)
    assert rows.stop - rows.start == 20 and cols.stop - cols.start == 10
    assert rows.start == 40 and cols.start == 20


def test_window_fov_is_the_arc_of_the_window_columns():
    assert math.degrees(window_fov_rad(64, 120.0, 1.0)) == pytest.approx(120.0)  # the whole image: the camera's fov
    fx = 32 / math.tan(math.radians(60))  # 120 deg, 64 px; the window's 13 columns are 25-37 (edges 25 and 38), centre 32
    expect = math.atan((38 - 32) / fx) - math.atan((25 - 32) / fx)
    assert window_fov_rad(64, 120.0) == pytest.approx(expect) and math.degrees(expect) == pytest.approx(38.74, abs=0.01)
    assert math.degrees(window_fov_rad(64, 150.0, 0.078)) == pytest.approx(32.41, abs=0.01)  # 5 columns at 150 deg
    # Read back (trainer_node, from step_outcome's window_fov_rad): the same window, in whole pixels.
    for width, hfov, fraction in ((64, 120.0, 0.2), (64, 150.0, 0.078), (84, 90.0, 0.5), (64, 100.0, 1.0), (48, 120.0, 0.01)):
        back = window_fraction_for_fov(width, hfov, float(np.float32(window_fov_rad(width, hfov, fraction))))  # Range: float32
        assert center_window_slices(width, width, back) == center_window_slices(width, width, fraction)
    assert window_fraction_for_fov(64, 150.0, window_fov_rad(64, 150.0, 0.078)) == 5 / 64


def test_center_window_min_depth_reads_only_the_window_and_rep117():
    d = np.full((64, 64), 8.0, dtype=np.float32)
    d[0, 0] = 0.2  # outside the window: ignored
    assert center_window_min_depth(d, 10.0) == pytest.approx(8.0)
    d[30, 30] = 2.5
    assert center_window_min_depth(d, 10.0) == pytest.approx(2.5)
    d[30, 30] = np.nan  # invalid pixels are ignored
    assert center_window_min_depth(d, 10.0) == pytest.approx(8.0)
    d[:] = np.inf  # nothing in range: beta is the max range
    assert center_window_min_depth(d, 10.0) == 10.0
    d[32, 32] = -np.inf  # too close to measure: 0
    assert center_window_min_depth(d, 10.0) == 0.0
    assert math.isfinite(step_reward(center_window_min_depth(d, 10.0), False))
