"""The local map: measured depth moved by odometry into the current body frame, weather filtered, forgotten on reset."""

import math

import numpy as np
import pytest

from uav_common.kinematics import BodyTwist
from uav_common.local_map import LocalMap, MapConfig, PinholeCamera
from uav_sim.sensor import TRAINING_SCALE
from uav_sim.simulator import SimConfig, Simulator
from uav_sim.world import Obstacle, Weather, World

D435 = dict(sensor="realsense_d435", sensor_scale=TRAINING_SCALE)
TURN_LEFT = BodyTwist(1.0, yaw_rate_radps=math.radians(30.0) / 0.5)  # a2: 30 deg left in a 0.5 s step, 1 m/s


def room(pillar_xy=(2.0, 0.0), weather=Weather()) -> World:
    """A large room (walls 10 m away), the vehicle at the origin facing +x, one pillar of radius 0.4 m."""
    return World("room", 20.0, 20.0, 3.0, (0.0, 0.0, 1.0), 0.0, (Obstacle("cylinder", *pillar_xy, 3.0, radius_m=0.4),), weather)


def camera_of(sim: Simulator) -> PinholeCamera:
    c = sim.camera.intrinsics
    return PinholeCamera.from_fov(c.width, c.height, c.hfov_deg)


def insert(m: LocalMap, sim: Simulator) -> None:
    x, y, z = sim.camera_xyz()
    m.insert(sim.measured, camera_of(sim), x, y, z, sim.pose.yaw_rad)


def near(m: LocalMap, xy, within_m: float) -> np.ndarray:
    """The occupied cells' centres within `within_m` of a point."""
    cells = m.occupied_xy()
    return cells[np.hypot(cells[:, 0] - xy[0], cells[:, 1] - xy[1]) < within_m]


def test_a_pillar_seen_frames_ago_stays_where_it_is_after_a_turn_and_a_move():
    sim = Simulator(room((2.0, 0.5)), SimConfig(**D435))
    try:
        m = LocalMap()
        sim.observe()
        insert(m, sim)
        for _ in range(3):  # 90 deg left and about 1.4 m on: the pillar leaves the view
            sim.step(TURN_LEFT)
            insert(m, sim)
        cols = np.flatnonzero((np.isfinite(sim.measured) & (sim.measured < 1.5)).any(axis=0))
        assert not len(cols), "the pillar is out of the current frame"
        cells = near(m, (2.0, 0.5), 1.0)
        assert len(cells) > 5, "it is remembered"
        r = np.hypot(cells[:, 0] - 2.0, cells[:, 1] - 0.5)
        assert np.all(np.abs(r - 0.4) <= 0.05 + 0.05), "on the pillar's surface, within a cell"
        # In the body frame of the current pose, the egocentric grid shows it where the pillar now is.
        pose = sim.pose
        dx, dy = 2.0 - pose.x_m, 0.5 - pose.y_m
        fwd = math.cos(pose.yaw_rad) * dx + math.sin(pose.yaw_rad) * dy
        left = -math.sin(pose.yaw_rad) * dx + math.cos(pose.yaw_rad) * dy
        assert left < -0.5, "the pillar is now to the right"
        grid = m.egocentric(128, 0.1)
        rows, cols = np.nonzero(grid)
        cell_fwd = (128 - 1 - rows - 32 + 0.5) * 0.1
        cell_left = (128 // 2 - 1 - cols + 0.5) * 0.1
        d = np.hypot(cell_fwd - fwd, cell_left - left)
        assert (d < 0.6).sum() > 3 and d.min() <= 0.45, "the grid has the pillar at its place in the body frame"
    finally:
        sim.close()


def test_weather_leaves_no_occupied_cell_while_the_pillar_stays():
    weather = Weather(rain=40, snow=40, leaves=25)
    sim = Simulator(room((5.0, 0.0), weather), SimConfig(seed=1, **D435))
    unfiltered = LocalMap(MapConfig(solid_m=0.0, confirm_frames=1, carve_m=100.0))
    try:
        m = LocalMap()
        sim.observe()
        for _ in range(5):
            insert(m, sim)
            insert(unfiltered, sim)
            sim.step(BodyTwist(0.5))  # slowly towards the pillar
        insert(m, sim)
        insert(unfiltered, sim)
        x, y, _ = sim.camera_xyz()
        cells = m.occupied_xy()
        off_pillar = np.hypot(cells[:, 0] - 5.0, cells[:, 1]) > 0.4 + 0.2
        in_range = np.hypot(cells[:, 0] - x, cells[:, 1] - y) < 4.0
        raw = unfiltered.occupied_xy()
        raw_off = (np.hypot(raw[:, 0] - 5.0, raw[:, 1]) > 0.6) & (np.hypot(raw[:, 0] - x, raw[:, 1] - y) < 4.0)
        assert raw_off.sum() > 20, "the weather puts returns into the frames"
        assert not (off_pillar & in_range).any(), "none of them is an obstacle after filtering"
        assert len(near(m, (5.0, 0.0), 0.6)) > 5, "the pillar stays"
    finally:
        sim.close()


def test_a_reset_forgets_and_clearance_measures_to_the_nearest_cell():
    sim = Simulator(room((2.0, 0.0)), SimConfig(**D435))
    try:
        m = LocalMap()
        sim.observe()
        insert(m, sim)
        d, key = m.clearance(np.array([0.0, 1.0]), np.array([0.0, 0.0]))
        assert d[0] == pytest.approx(1.6, abs=0.1) and d[1] == pytest.approx(0.6, abs=0.1), "to the pillar's face"
        assert (key >= 0).all()
        m.reset()
        d, key = m.clearance(np.array([1.0]), np.array([0.0]))
        assert np.isinf(d).all() and (key == -1).all() and not len(m.occupied())
    finally:
        sim.close()


def test_bad_frames_and_settings_are_refused_by_name():
    m = LocalMap()
    with pytest.raises(ValueError, match="does not match"):
        m.insert(np.ones((10, 10)), PinholeCamera.from_fov(20, 10, 87.0), 0, 0, 1, 0)
    with pytest.raises(ValueError, match="confirm_frames"):
        LocalMap(MapConfig(frames=2, confirm_frames=3))
    m.insert(np.full((10, 20), np.nan), PinholeCamera.from_fov(20, 10, 87.0), 0, 0, 1, 0)  # no returns: nothing known
    assert not len(m.occupied())
