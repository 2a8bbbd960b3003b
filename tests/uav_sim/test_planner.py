"""The privileged planner: it flies without crashing, knows only what the frames showed, labels what it flies, and
names the obstacle its decision is about."""

import math

import numpy as np
import pytest

from uav_common.kinematics import BodyTwist
from uav_common.plan_search import Planner
from uav_policy.rollout import Flight
from uav_sim.planner import Geometry, KnownGeometry, PlannerAgent, PlannerConfig, SimPlanner
from uav_sim.sensor import TRAINING_SCALE
from uav_sim.simulator import SimConfig, Simulator
from uav_sim.stacked_sim import StackedSim
from uav_sim.world import Obstacle, Weather, World, load_world, wall_code

D435 = dict(sensor="realsense_d435", sensor_scale=TRAINING_SCALE)


def pillar_world(x_m: float = 2.0, y_m: float = 0.0) -> World:
    """A large room (its far wall 8 m ahead, in range), the vehicle at the origin facing +x, one pillar."""
    pillar = Obstacle("cylinder", x_m, y_m, 3.0, radius_m=0.4)
    return World("pillar", 16.0, 20.0, 3.0, (0.0, 0.0, 1.0), 0.0, (pillar,), Weather())


def everything(world: World) -> KnownGeometry:
    """All of a world's footprints and walls, as the planner's knowledge."""
    geometry = Geometry(world)
    return KnownGeometry(geometry, np.ones(len(geometry.codes), dtype=bool))


def fly_planner(world: str, knowledge: str, steps: int, seed: int) -> tuple[int, float, list[int]]:
    """(crashes, metres per step, actions) of the planner flying `world` from random headings behind the D435."""
    sim = Simulator(load_world(world), SimConfig(seed=seed, start_yaw_jitter_deg=180.0, **D435))
    try:
        flight = Flight(StackedSim(sim, 5), PlannerAgent(SimPlanner(sim, PlannerConfig(knowledge=knowledge))))
        crashes, dist, actions = 0, 0.0, []
        for _ in range(steps):
            s = flight.step(0.0)
            actions.append(s.action)
            crashes += s.after.collided
            if not s.after.collided:
                dist += math.hypot(s.after.pose.x_m - s.before.pose.x_m, s.after.pose.y_m - s.before.pose.y_m)
        return crashes, dist / steps, actions
    finally:
        sim.close()


def test_the_planner_knowing_only_the_last_five_frames_flies_complex_without_crashing_and_is_deterministic():
    crashes, m_per_step, actions = fly_planner("complex", "stack", 300, seed=11)
    assert crashes == 0
    assert m_per_step > 0.6, "it does not hover or circle its way to safety"
    assert fly_planner("complex", "stack", 60, seed=11)[2] == actions[:60], "deterministic for a seed"


@pytest.mark.slow
def test_the_planner_flies_2000_random_start_steps_of_complex_without_a_crash():
    for knowledge in ("stack", "all"):
        crashes, m_per_step, _ = fly_planner("complex", knowledge, 2000, seed=12)
        assert crashes == 0, knowledge
        assert m_per_step > 0.6, knowledge


def test_the_planner_on_the_local_map_flies_through_weather_and_is_deterministic():
    """Knowing only the measured depth of the last five frames and odometry (the local map, weather filtered)."""
    crashes, m_per_step, actions = fly_planner("turbulent", "map", 300, seed=5)
    assert crashes == 0 and m_per_step > 0.6
    assert fly_planner("turbulent", "map", 60, seed=5)[2] == actions[:60], "deterministic for a seed"


@pytest.mark.slow
def test_the_planner_on_the_local_map_flies_2000_random_start_steps_of_complex_and_turbulent_without_a_crash():
    for world in ("complex", "turbulent"):
        crashes, m_per_step, _ = fly_planner(world, "map", 2000, seed=12)
        assert crashes == 0, world
        assert m_per_step > 0.6, world


def test_its_labels_are_what_it_flies():
    """The teacher's label for a frame (SimPlanner.label) is the action the planner flies from that frame."""
    flown = Simulator(load_world("complex"), SimConfig(seed=3, start_yaw_jitter_deg=180.0, **D435))
    labelled = Simulator(load_world("complex"), SimConfig(seed=3, start_yaw_jitter_deg=180.0, **D435))
    try:
        flight = Flight(StackedSim(flown, 5), PlannerAgent(SimPlanner(flown)))
        teacher = SimPlanner(labelled)
        for _ in range(80):
            label = teacher.label().action
            assert teacher.label().action == label, "asked twice for one frame, the same answer"
            action = flight.step(0.0).action
            assert label == action
            a = flight.actions[action]
            labelled.step(BodyTwist(a.linear_x_mps, yaw_rate_radps=a.yaw_rate_radps(labelled.config.step_duration_s)))
    finally:
        flown.close()
        labelled.close()


def test_knowing_the_last_frames_means_not_knowing_what_is_behind():
    behind = pillar_world(-2.0)
    sim = Simulator(behind, SimConfig(**D435))
    try:
        stack, everything = SimPlanner(sim), SimPlanner(sim, PlannerConfig(knowledge="all"))
        stack.label(), everything.label()
        assert 0 not in sim.visible, "the camera looks away from the pillar"
        codes = list(stack.geometry.codes)
        assert not stack.known()[codes.index(0)]
        assert everything.known()[codes.index(0)]
    finally:
        sim.close()


def test_one_pillar_in_front_is_the_reason_and_its_pixels_are_the_mask():
    sim = Simulator(pillar_world(2.0), SimConfig(**D435))
    try:
        plan = SimPlanner(sim).label()
        assert plan.action in (1, 2), "it turns away from the pillar ahead"
        assert plan.reason == (0,), "the decision is about the pillar, nothing else"
        assert plan.clearance_m[[0, 3]].max() < plan.clearance_m[plan.action], "straight on, it would pass nearer"
        mask = sim.body_ids == 0
        h, w = mask.shape
        assert mask[h // 2, w // 2], "the pillar is in the middle of the image"
        assert mask.mean() < 0.3 and not mask[:, 0].any() and not mask[:, -1].any(), "and nowhere else"
        assert wall_code(0) in sim.visible, "the far wall shows beside it"
    finally:
        sim.close()


def test_a_plan_ends_where_it_could_circle_for_ever():
    """In a corridor too narrow to turn round in, flying on towards its end wall is worse than turning in time: a plan
    whose horizon ends without room to circle ranks below one that keeps that room."""
    corridor = World("corridor", 12.0, 1.6, 3.0, (0.0, 0.0, 1.0), 0.0, (), Weather())
    plan = Planner(0.5, 40.0).plan(3.0, 0.0, 0.0, everything(corridor))
    assert plan.scores.max() < 1e7 and not plan.safe.any(), "no plan can end on a free turning circle in a 1.6 m corridor"
    room = World("room", 30.0, 30.0, 3.0, (0.0, 0.0, 1.0), 0.0, (), Weather())
    assert Planner(0.5, 40.0).plan(0.0, 0.0, 0.0, everything(room)).action == 3, "in an empty room it flies the fast action"


def test_bad_planner_settings_are_refused_by_name():
    for bad, field in ((dict(knowledge="psychic"), "knowledge"), (dict(horizon=0), "horizon")):
        with pytest.raises(ValueError, match=field):
            PlannerConfig(**bad).validate()
    assert np.isfinite(Planner(0.5, 40.0).plan(0.0, 0.0, 0.0, everything(pillar_world())).scores).all()


def test_the_reason_maps_onto_the_network_input_where_its_depth_shows():
    sim = Simulator(pillar_world(2.0), SimConfig(**D435))
    try:
        env = StackedSim(sim, 5, input_hw=(64, 64), trained_hfov_deg=87.0)
        plan = SimPlanner(sim).label()
        mask = env.input_mask(np.isin(sim.body_ids, plan.reason))
        assert mask.shape == (64, 64) and 0 < mask.mean() < 0.3
        depth = env.last_input
        assert np.nanmedian(depth[mask]) < 2.0 < np.nanmedian(depth[~mask & np.isfinite(depth)]), "the pillar is nearest"
    finally:
        sim.close()
