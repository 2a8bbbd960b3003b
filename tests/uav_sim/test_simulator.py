import math

import numpy as np
import pytest

from uav_common.kinematics import BodyTwist, Pose, TwistLimits, integrate, twist_error
from uav_sim.camera import CameraIntrinsics
from uav_sim.reward import DELTA_M, center_window_min_depth, floor_beta_m
from uav_sim.simulator import SimConfig, Simulator, obstacle_distance_m, reward_floor_problem
from uav_sim.world import Obstacle, Weather, World, load_world


def wall_world(face_x_m: float) -> World:
    """A long room with a wide wall whose near face is at x = face_x_m; start at the origin."""
    wall = Obstacle("box", face_x_m + 0.5, 0.0, 3.0, size_x_m=1.0, size_y_m=9.0)
    return World("wall", 30.0, 10.0, 3.0, (0.0, 0.0, 1.0), 0.0, (wall,), Weather())


@pytest.fixture
def sims():
    made = []

    def make(world, **cfg):
        # A 120 deg camera with the paper's window unless a test says (the node's default 150 deg sees more
        # than these small rooms' end walls).
        s = Simulator(world, SimConfig(**{"hfov_deg": 120.0, "reward_window_fraction": 0.2, **cfg}))
        made.append(s)
        return s

    yield make
    for s in made:
        s.close()


def test_intrinsics():
    k = CameraIntrinsics(64, 64, 90.0)
    assert k.focal_px == pytest.approx(32.0)
    assert k.vfov_deg == pytest.approx(90.0)


def test_depth_is_metric_along_the_optical_axis(sims):
    sim = sims(wall_world(3.0))
    depth = sim.render()
    expected = 3.0 - sim.config.camera_forward_offset_m  # camera 0.22 m ahead of the body centre
    assert depth.dtype == np.float32 and depth.shape == (64, 64)
    assert abs(depth[32, 32] - expected) < 0.01
    # A wall perpendicular to the optical axis has the same optical-axis depth everywhere on it.
    assert np.all(np.abs(depth[28:36, 10:54] - expected) < 0.01)
    assert center_window_min_depth(depth, 10.0) == pytest.approx(expected, abs=0.01)


def test_out_of_range_is_positive_infinity(sims):
    sim = sims(wall_world(12.0), max_range_m=5.0)
    depth = sim.render()
    assert np.isposinf(depth[32, 32])  # wall at 11.8 m, range 5 m
    assert np.isfinite(depth[-1, 32])  # the floor right below is in range


def test_the_floor_caps_beta_where_floor_beta_m_says_and_150_degrees_punishes_every_step():
    empty = World("empty", 40.0, 40.0, 3.0, (-15.0, 0.0, 1.0), 0.0, (), Weather())
    for hfov, size in ((90.0, 64), (120.0, 64), (150.0, 64), (120.0, 84)):
        cfg = SimConfig(hfov_deg=hfov, image_width=size, image_height=size, reward_window_fraction=0.2)
        sim = Simulator(empty, cfg)
        try:
            r = sim.observe()  # nothing but floor, ceiling and far walls in view
        finally:
            sim.close()
        floor = floor_beta_m(1.0, size, size, hfov)
        assert r.beta_m == pytest.approx(floor, rel=0.02), hfov
        problem = reward_floor_problem(cfg, 1.0)
        if hfov < 150.0:  # the floor stays beyond delta: open space earns the positive branch
            assert floor > DELTA_M and r.reward > 3.0 and problem is None
        else:  # 1.43 m: punished in an empty room
            assert floor < DELTA_M and r.reward < 0.0
            assert problem.startswith("hfov_deg=150 with 64x64 images shows the floor 1.43 m ahead")
    assert floor_beta_m(1.0, 64, 64, 120.0, fraction=0.01) == math.inf  # a window above the horizon
    narrow = SimConfig(hfov_deg=150.0, reward_window_fraction=0.078)  # 5 x 5 px
    sim = Simulator(empty, narrow)
    try:
        r = sim.observe()
    finally:
        sim.close()
    assert r.beta_m == pytest.approx(floor_beta_m(1.0, 64, 64, 150.0, 0.078), rel=0.02) and r.beta_m > 4.0
    assert r.reward > 3.0 and reward_floor_problem(narrow, 1.0) is None
    with pytest.raises(ValueError, match="reward_window_fraction=0.0 is invalid"):
        SimConfig(reward_window_fraction=0.0).validate()


def test_one_metre_per_second_for_one_second(sims):
    sim = sims(wall_world(20.0), step_duration_s=0.5)
    for _ in range(2):
        r = sim.step(BodyTwist(vx_mps=1.0))
    assert r.sim_time_s == pytest.approx(1.0)
    assert r.pose.x_m == pytest.approx(1.0, abs=1e-6) and r.pose.y_m == pytest.approx(0.0, abs=1e-6)


def test_yaw_action_turns_thirty_degrees(sims):
    sim = sims(wall_world(20.0), step_duration_s=0.5)
    r = sim.step(BodyTwist(vx_mps=1.0, yaw_rate_radps=-math.radians(30) / 0.5))  # a1: yaw right
    assert math.degrees(r.pose.yaw_rad) == pytest.approx(-30.0, abs=1e-6)
    assert r.pose.y_m < 0  # turned right (REP 103: y left)
    assert math.hypot(r.pose.x_m, r.pose.y_m) == pytest.approx(0.5, abs=0.01)  # 1 m/s for 0.5 s


def test_integrate_is_exact_for_arcs():
    pose = Pose(0.0, 0.0, 1.0, 0.0)
    cmd = BodyTwist(vx_mps=1.0, yaw_rate_radps=math.pi)  # half circle of radius 1/pi in 1 s
    end = integrate(pose, cmd, 1.0)
    assert end.x_m == pytest.approx(0.0, abs=1e-9) and end.y_m == pytest.approx(2 / math.pi)
    chunks = pose
    for _ in range(10):
        chunks = integrate(chunks, cmd, 0.1)
    assert chunks.x_m == pytest.approx(end.x_m, abs=1e-9) and chunks.y_m == pytest.approx(end.y_m)


def test_twist_limits():
    lim = TwistLimits(max_speed_mps=3.0, max_climb_mps=1.0, max_yaw_rate_radps=2.0)
    assert twist_error(BodyTwist(2.0, 0, 0, 1.0), lim) is None
    assert "linear.x" in twist_error(BodyTwist(float("nan")), lim)
    assert "angular.z" in twist_error(BodyTwist(yaw_rate_radps=math.inf), lim)
    assert "exceeds" in twist_error(BodyTwist(vx_mps=3.5), lim)


def test_flying_into_a_wall_is_a_collision_and_resets(sims):
    sim = sims(wall_world(2.0))
    outcomes = [sim.step(BodyTwist(vx_mps=1.0)) for _ in range(6)]
    crash_index = next(i for i, r in enumerate(outcomes) if r.collided)
    crash = outcomes[crash_index]
    assert crash.reward == -10.0
    assert crash.episode == 1 and crash.step_in_episode == 0
    assert crash.pose.x_m == pytest.approx(0.0) and sim.collisions == 1  # back at the start
    # Body front touches the face at x = 1.8 m: steps to 0.5, 1.0, 1.5 m are free, the 4th hits.
    assert crash_index == 3


def test_time_limit_ends_an_episode_without_a_collision(sims):
    sim = sims(wall_world(20.0), max_episode_steps=3)
    results = [sim.step(BodyTwist(vx_mps=1.0)) for _ in range(7)]
    assert [r.truncated for r in results] == [False, False, True, False, False, True, False]
    assert not any(r.collided for r in results) and sim.collisions == 0
    cut = results[2]
    assert (cut.episode, cut.step_in_episode, cut.pose.x_m) == (1, 0, 0.0)  # back at the start
    assert np.array_equal(cut.depth_m, sims(wall_world(20.0)).observe().depth_m)  # the new episode's first frame
    assert results[3].pose.x_m == pytest.approx(0.5) and sim.total_steps == 7
    # A collision before the limit is a collision, and restarts the count.
    sim = sims(wall_world(2.0), max_episode_steps=10)
    outcomes = [sim.step(BodyTwist(vx_mps=1.0)) for _ in range(14)]
    assert [i for i, r in enumerate(outcomes) if r.collided] == [3, 7, 11]
    assert not any(r.truncated for r in outcomes)
    # reset() is also an episode end without a collision.
    r = sim.reset()
    assert r.truncated and not r.collided and r.step_in_episode == 0


def test_time_limit_moves_on_to_the_next_layout(sims):
    worlds = iter([load_world("basic"), load_world("complex")])
    sim = Simulator(wall_world(20.0), SimConfig(max_episode_steps=2), next_worlds=worlds)
    try:
        names = [(sim.step(BodyTwist(vx_mps=1.0)).truncated, sim.world.name) for _ in range(4)]
    finally:
        sim.close()
    assert names == [(False, "wall"), (True, "basic"), (False, "basic"), (True, "complex")]


def test_obstacle_distance_of_a_rotated_box_and_a_cylinder():
    box = Obstacle("box", 1.0, 2.0, 3.0, size_x_m=2.0, size_y_m=1.0, yaw_deg=90.0)  # long side along y
    assert obstacle_distance_m(box, 1.0, 2.0) == 0.0  # inside
    assert obstacle_distance_m(box, 1.0, 4.0) == pytest.approx(1.0)  # 1 m beyond the end of the long side
    assert obstacle_distance_m(box, 3.5, 2.0) == pytest.approx(2.0)  # 2 m off the long side (half width 0.5)
    assert obstacle_distance_m(box, 2.5, 6.0) == pytest.approx(math.hypot(1.0, 3.0))  # off a corner
    cyl = Obstacle("cylinder", 0.0, 0.0, 3.0, radius_m=0.5)
    assert obstacle_distance_m(cyl, 3.0, 4.0) == pytest.approx(4.5) and obstacle_distance_m(cyl, 0.1, 0.0) == 0.0


def test_every_training_layout_starts_at_the_runs_first_heading_draw():
    from uav_sim.world import training_layouts

    layouts = training_layouts(3)
    cfg = SimConfig(max_episode_steps=1, start_yaw_jitter_deg=90.0, seed=3)
    sim = Simulator(next(layouts), cfg, next_worlds=layouts)
    try:
        starts = []
        for _ in range(20):
            sim.step()  # one step per episode: every step ends with the next layout's start
            starts.append(((sim.pose.x_m, sim.pose.y_m) == sim.world.start_xyz_m[:2], sim.pose.yaw_rad))
            assert sim._max_penetration_m() == 0.0
    finally:
        sim.close()
    assert all(at_start for at_start, _ in starts) and len({yaw for _, yaw in starts}) == 1


def test_change_world_rebuilds_the_scene_and_keeps_the_counters(sims):
    sim = sims(load_world("turbulent"))
    for _ in range(3):
        sim.step(BodyTwist(vx_mps=1.0))
    r = sim.change_world(wall_world(2.0))
    assert (sim.total_steps, sim.episode, r.step_in_episode, r.sim_time_s) == (3, 0, 0, 1.5)
    assert r.pose.x_m == 0.0 and r.pose.y_m == 0.0
    # Nothing of turbulent is left (obstacles, walls, particles): the frame is a fresh wall world's.
    assert np.array_equal(r.depth_m, sims(wall_world(2.0)).observe().depth_m)
    crashes = [sim.step(BodyTwist(vx_mps=1.0)).collided for _ in range(4)]
    assert crashes == [False, False, False, True] and sim.collisions == 1  # the new wall collides


def test_a_graze_along_a_wall_is_a_brush_not_a_collision(sims):
    # Body half width 0.2 m; fly parallel to a wall whose face is 0.19 m from the centre line.
    wall = Obstacle("box", 0.0, 0.69, 3.0, size_x_m=20.0, size_y_m=1.0)
    world = World("graze", 30.0, 10.0, 3.0, (-5.0, 0.0, 1.0), 0.0, (wall,), Weather())
    sim = sims(world, collision_penetration_m=0.03)
    r = sim.step(BodyTwist(vx_mps=1.0))
    assert not r.collided and r.brushes > 0
    # The same graze with a 5 mm threshold is a collision.
    strict = sims(world, collision_penetration_m=0.005)
    assert strict.step(BodyTwist(vx_mps=1.0)).collided


def test_builtin_worlds_load_and_differ():
    basic, complex_, turbulent = (load_world(n) for n in ("basic", "complex", "turbulent"))
    assert basic.obstacles and complex_.obstacles and basic.obstacles != complex_.obstacles
    assert {o.shape for o in complex_.obstacles} == {"box", "cylinder"}
    assert turbulent.obstacles == basic.obstacles and turbulent.weather.any and not basic.weather.any


def test_random_worlds_are_seeded():
    assert load_world("random:5") == load_world("random:5")
    assert load_world("random:5").obstacles != load_world("random:6").obstacles


def test_weather_puts_near_returns_into_the_depth_image(sims):
    clear = sims(load_world("basic"), seed=3)
    stormy = sims(load_world("turbulent"), seed=3)
    near_clear, near_storm = [], []
    for _ in range(10):
        near_clear.append(np.sum(clear.step(BodyTwist(vx_mps=0.5)).depth_m < 2.0))
        near_storm.append(np.sum(stormy.step(BodyTwist(vx_mps=0.5)).depth_m < 2.0))
    assert np.mean(near_storm) > np.mean(near_clear) + 20  # particles show up as close pixels
    # Seeded: the same seed gives the same storm.
    again = sims(load_world("turbulent"), seed=3)
    first = again.step(BodyTwist(vx_mps=0.5)).depth_m
    replay = sims(load_world("turbulent"), seed=3).step(BodyTwist(vx_mps=0.5)).depth_m
    np.testing.assert_array_equal(first, replay)


def test_invalid_command_raises_and_config_is_validated(sims):
    sim = sims(wall_world(5.0))
    with pytest.raises(ValueError, match="linear.x"):
        sim.step(BodyTwist(vx_mps=float("nan")))
    with pytest.raises(ValueError, match="step_duration_s"):
        Simulator(wall_world(5.0), SimConfig(step_duration_s=0.0))
    with pytest.raises(ValueError, match="max_episode_steps"):
        Simulator(wall_world(5.0), SimConfig(max_episode_steps=-1))
