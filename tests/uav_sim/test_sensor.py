"""Sensor presets: their noise statistics on a flat wall match their specification, seeded; the simulator
renders at the preset's resolution and field of view."""

import numpy as np
import pytest

from uav_sim.sensor import PRESETS, SensorModel, preset


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_noise_on_a_flat_wall_grows_with_distance_squared_as_specified(name):
    p = PRESETS[name]
    model = SensorModel(p, seed=3)
    for z in (1.0, 2.0, p.max_range_m * 0.8):
        wall = np.full((p.height, p.width), z, np.float32)
        got = model.measure(wall)
        seen = got[np.isfinite(got)]
        assert abs(seen.mean() - z) < 3 * p.noise_per_m2 * z**2 / np.sqrt(seen.size) + p.quantum_m, (z, seen.mean())
        assert seen.std() == pytest.approx(p.noise_per_m2 * z**2, rel=0.1, abs=p.quantum_m), (z, seen.std())
        assert 1 - seen.size / got.size == pytest.approx(p.dropout, abs=0.005), "only dropout is missing on a flat wall"
        np.testing.assert_allclose(seen / p.quantum_m, np.round(seen / p.quantum_m), atol=1e-3)
    near = model.measure(np.full((8, 8), p.min_range_m * 0.5, np.float32))
    far = model.measure(np.full((8, 8), p.max_range_m * 1.5, np.float32))
    assert np.isinf(near).all() and np.isinf(far).all(), "outside the range: no return"
    again = SensorModel(p, seed=3).measure(np.full((p.height, p.width), 1.0, np.float32))
    first = SensorModel(p, seed=3).measure(np.full((p.height, p.width), 1.0, np.float32))
    np.testing.assert_array_equal(again, first)


def test_the_far_side_of_a_depth_edge_returns_nothing():
    p = PRESETS["realsense_d435"]
    scene = np.full((20, 40), 4.0, np.float32)
    scene[:, 10:20] = 1.0  # a post in front of a wall
    got = SensorModel(p, seed=0).measure(scene)
    assert np.isinf(got[:, 9]).all() and np.isinf(got[:, 20]).all(), "the wall beside the post is shadowed"
    assert np.isfinite(got[:, 12:18]).mean() > 0.9


def test_a_preset_simulator_renders_the_preset_camera():
    from uav_sim.simulator import SimConfig, Simulator
    from uav_sim.world import load_world

    sim = Simulator(load_world("basic"), SimConfig(sensor="realsense_d435", sensor_scale=0.1))
    try:
        r = sim.observe()
        assert r.depth_m.shape == (48, 85) and sim.config.hfov_deg == 87.0
        seen = r.depth_m[np.isfinite(r.depth_m)]
        np.testing.assert_allclose(seen * 1000, np.round(seen * 1000), atol=1e-2)
    finally:
        sim.close()
    assert preset("ideal") is None
    with pytest.raises(ValueError, match="sensor must be one of ideal, realsense_d435"):
        preset("kinect")
