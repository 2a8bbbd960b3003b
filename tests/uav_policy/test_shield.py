"""The shield: the network chooses among the actions the local map says are safe."""

import numpy as np
import pytest

from uav_common.actions import PAPER_ACTIONS
from uav_common.kinematics import BodyTwist
from uav_common.local_map import PinholeCamera
from uav_policy.pilot import Pilot
from uav_policy.shield import Shield
from uav_sim.sensor import TRAINING_SCALE
from uav_sim.simulator import SimConfig, Simulator
from uav_sim.world import Obstacle, Weather, World

D435 = dict(sensor="realsense_d435", sensor_scale=TRAINING_SCALE)
LEFT = np.array([0.0, 0.0, 10.0, 0.0])  # Q-values of a network that wants to turn left


def room(*obstacles) -> World:
    return World("room", 20.0, 20.0, 3.0, (0.0, 0.0, 1.0), 0.0, tuple(obstacles), Weather())


def show(shield: Shield, sim: Simulator) -> None:
    c, p = sim.camera.intrinsics, sim.pose
    shield.observe(sim.measured, PinholeCamera.from_fov(c.width, c.height, c.hfov_deg), p.x_m, p.y_m, p.z_m, p.yaw_rad)


def fly_straight(world: World, steps: int) -> tuple[Simulator, Shield]:
    sim = Simulator(world, SimConfig(**D435))
    shield = Shield(PAPER_ACTIONS, 0.5)
    sim.observe()
    show(shield, sim)
    for _ in range(steps):
        sim.step(BodyTwist(1.0))
        show(shield, sim)
    return sim, shield


def test_a_pillar_seen_frames_ago_beside_the_vehicle_vetoes_the_turn_into_it():
    sim, shield = fly_straight(room(Obstacle("cylinder", 2.0, 0.6, 3.0, radius_m=0.2)), 3)
    try:
        sim.see_bodies = True
        sim.render()
        assert 0 not in sim.visible, "the pillar, 0.5 m ahead and 0.6 m left, is out of the current frame"
        verdict = shield.check(LEFT, 2)
        assert not verdict.safe[2], "turning left runs into it"
        assert verdict.safe[1], "turning right away from it is safe"
        assert verdict.action != 2 and verdict.why.startswith("shield: action 2 unsafe")
        assert shield.counts.overridden == 1 and shield.counts.checked == 1
    finally:
        sim.close()


def test_an_open_room_vetoes_nothing():
    sim, shield = fly_straight(room(), 4)
    try:
        for choice in range(4):
            verdict = shield.check(np.eye(4)[choice], choice)
            assert verdict.safe.all() and verdict.action == choice and verdict.why == ""
        assert shield.counts.overridden == 0
    finally:
        sim.close()


class WantsLeft:
    def act(self, state, epsilon=0.0):
        return 2, LEFT, None, False


def test_without_fresh_odometry_nothing_is_vouched_for_and_forward_flight_stops():
    sim, shield = fly_straight(room(), 1)
    try:
        pilot = Pilot(WantsLeft(), PAPER_ACTIONS, 0.5, shield=shield)
        flown = pilot.decide(np.zeros((5, 8, 8)), np.zeros((8, 8)))
        assert flown.action == 2 and flown.linear_x_mps == 1.0 and flown.unshielded == 2 and flown.shield == ""
        shield.forget_pose()
        stopped = pilot.decide(np.zeros((5, 8, 8)), np.zeros((8, 8)))
        assert (stopped.linear_x_mps, stopped.yaw_rate_radps) == (0.0, 0.0)
        assert "no fresh odometry" in stopped.safety and shield.counts.no_odometry == 1
    finally:
        sim.close()


def test_a_jump_of_odometry_forgets_the_map():
    sim, shield = fly_straight(room(Obstacle("cylinder", 3.0, 0.0, 3.0, radius_m=0.3)), 1)
    try:
        assert len(shield.map.occupied()), "the pillar ahead is mapped"
        shield.observe(np.full_like(sim.measured, np.inf), PinholeCamera.from_fov(85, 48, 87.0), 50.0, 0.0, 1.0, 0.0)
        assert not len(shield.map.occupied()), "odometry jumped 50 m: a reset, what was mapped is forgotten"
    finally:
        sim.close()


class Log:
    def __init__(self):
        self.said = []

    def warning(self, message, throttle_duration_sec=0.0):
        self.said.append(message)


def test_the_feed_matches_a_camera_frame_with_fresh_odometry_and_pools_large_frames():
    from builtin_interfaces.msg import Time

    from uav_policy.shield import ShieldFeed, ShieldSettings, pooled

    log = Log()
    feed = ShieldFeed(PAPER_ACTIONS, 0.5, ShieldSettings(), log)  # auto: a camera's frames are shielded
    f = 424 / np.tan(np.radians(87 / 2))
    intrinsics = (f, f, 424.0, 240.0, 848, 480)
    wall = np.full((480, 848), 3.0, np.float32)
    assert feed.frame(wall, intrinsics, 1_000_000_000, camera=False) is None, "auto: a simulator's frames are not"
    shield = feed.frame(wall, intrinsics, 1_000_000_000)
    assert shield is not None and shield.check(np.zeros(4), 0).why.startswith("shield: no fresh odometry")
    assert "no odometry within odom_timeout_s" in log.said[-1] and feed.stale == 1
    assert feed.odometry(Time(sec=1, nanosec=200_000_000), (0.0, 0.0, 1.0, 0.0))
    assert not feed.odometry(Time(sec=1), None), "a malformed pose is ignored"
    feed.frame(wall, intrinsics, 1_000_000_000)  # 0.2 s from the odometry: fresh
    assert len(shield.map.occupied()) > 0 and shield.check(np.zeros(4), 0).safe.any()
    d, cam = pooled(wall, PinholeCamera(848, 480, f, f, 424.0, 240.0))
    assert d.shape[1] <= 128 and cam.width == d.shape[1] and cam.fx == pytest.approx(f / 7)
    feed.frame(wall, intrinsics, 2_000_000_000)  # 0.8 s: stale
    assert feed.stale == 2 and shield.check(np.zeros(4), 0).why.startswith("shield: no fresh odometry")
