"""The local map as the student's input: the networks' second trunk, the replay's packed maps, the simulator's map
channel, what a decision's reason covers on the map, and the explanations over image and map cells."""

import math

import numpy as np
import pytest
import torch

from uav_common.local_map import LocalMap, PinholeCamera
from uav_policy import weights as wio
from uav_policy.attention import attention_map, map_overlay
from uav_policy.insight import Insight, explanation
from uav_policy.masking import masked_states
from uav_policy.networks import NetConfig, build_network, forward_flops
from uav_sim.simulator import SimConfig, Simulator
from uav_sim.stacked_sim import StackedSim
from uav_sim.world import Obstacle, Weather, World
from uav_trainer.replay import ReplayMemory


def state_with_map(seed=0, b=2) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(b, 5, 64, 64, generator=g) * 8.0
    grid = (torch.rand(b, 1, 64, 64, generator=g) > 0.97).float()
    return torch.cat([depth, grid], dim=1)


@pytest.mark.parametrize(("model", "readout"), [("sam", "query"), ("sam", "max"), ("sam", "topk"), ("cnn", "max")])
def test_a_map_network_reads_the_map_channel_and_refuses_a_state_without_it(model, readout):
    cfg = NetConfig(model=model, sam_readout=readout, local_map=True)
    net = build_network(cfg, seed=2)
    x = state_with_map()
    q, w = net(x)
    assert q.shape == (2, 4) and torch.isfinite(q).all()
    if model == "sam":
        assert w.shape[-1] == 128, "attention over the 64 image cells and the 64 map cells"
        torch.testing.assert_close(w.sum(-1), torch.ones(w.shape[:-1]))
    moved = x.clone()
    moved[:, -1] = torch.roll(moved[:, -1], 20, dims=-1)  # the obstacles elsewhere on the map
    assert not torch.allclose(net(moved)[0], q), "the map changes the Q-values"
    with pytest.raises(ValueError, match="6 input channels"):
        net(x[:, :5])
    assert forward_flops(cfg) > forward_flops(NetConfig(model=model, sam_readout=readout))


def test_a_map_network_round_trips_through_its_weights_file(tmp_path):
    cfg = NetConfig(sam_readout="query", local_map=True)
    net = build_network(cfg, seed=3)
    path = tmp_path / "w.safetensors"
    wio.save_file(net, cfg, path)
    assert wio.config_for("sam", path).local_map, "the file's header says it takes the map"
    loaded = wio.load_file(path, wio.config_for("sam", path))
    x = state_with_map(1)
    torch.testing.assert_close(loaded(x)[0], net(x)[0])
    with pytest.raises(ValueError, match="local_map must be true or false"):
        NetConfig(local_map="yes").validate()
    with pytest.raises(ValueError, match="square input"):
        NetConfig(local_map=True, height=48).validate()


def test_the_replay_keeps_each_frames_map_packed_and_journals_it():
    rng = np.random.default_rng(0)
    maps = [(rng.random((8, 8)) > 0.8).astype(np.float32) for _ in range(30)]
    mem = ReplayMemory(20, (8, 8), frames=3, seed=0, local_map=True)
    mem.add_first(np.full((8, 8), 1.0), maps[0])
    for i in range(1, 30):
        mem.add_transition(i % 4, 1.0, i % 9 == 0, np.full((8, 8), float(i)), grid=maps[i])
    batch = mem.sample(16)
    assert batch["state"].shape == (16, 4, 8, 8)
    for state, nxt in zip(batch["state"], batch["next_state"], strict=True):
        write = int(state[-2, 0, 0])  # each frame's depth is its write number
        assert np.array_equal(state[-1], maps[write]) and np.array_equal(nxt[-1], maps[write + 1])
    again = ReplayMemory(20, (8, 8), frames=3, seed=0, local_map=True)
    again.load_segments([mem.segment(0)], mem.writes, 4)
    assert np.array_equal(again.map, mem.map) and np.array_equal(again.stacks(np.arange(20)), mem.stacks(np.arange(20)))
    with pytest.raises(ValueError, match="local map of"):
        mem.add_first(np.ones((8, 8)))  # no map: refused, not stored as an empty one


def pillar_sim(seed=0) -> Simulator:
    world = World("room", 20.0, 20.0, 3.0, (0.0, 0.0, 1.0), 0.0, (Obstacle("cylinder", 2.5, 0.3, 3.0, radius_m=0.4),), Weather())
    return Simulator(world, SimConfig(seed=seed, image_width=64, image_height=64, hfov_deg=90.0))


def test_the_simulators_map_channel_shows_the_pillar_ahead_and_forgets_at_a_new_episode():
    sim = pillar_sim()
    try:
        env = StackedSim(sim, 5, input_hw=(64, 64), map_grid=(64, 0.1))
        assert env.state.shape == (6, 64, 64)
        rows, cols = np.nonzero(env.state[-1])
        fwd = (64 - 1 - rows - 16 + 0.5) * 0.1  # a quarter of the grid lies behind the vehicle
        assert len(rows) > 3 and 1.6 <= fwd.min() <= 2.4, "the pillar's near face 2.1 m ahead of the camera"
        assert cols.mean() < 31, "its centre 0.3 m to the left (+y)"
        for _ in range(3):
            env.step(1)  # turning left: the pillar leaves the view, the map keeps it
        assert env.state[-1].sum() > 0
        env.reset()  # a new episode: only its first frame is mapped
        alone = LocalMap()
        c, k = sim.camera.intrinsics, sim.camera.intrinsics.k_matrix()
        camera = PinholeCamera(c.width, c.height, k[0], k[4], k[2], k[5])
        alone.insert(sim.measured, camera, *sim.camera_xyz(), sim.pose.yaw_rad)
        assert np.array_equal(env.state[-1], alone.egocentric(64, 0.1))
    finally:
        sim.close()


def test_a_reasons_pixels_mark_the_map_cells_they_put_there():
    sim = pillar_sim()
    try:
        sim.observe()
        m = LocalMap()
        c, k = sim.camera.intrinsics, sim.camera.intrinsics.k_matrix()
        m.insert(sim.measured, PinholeCamera(c.width, c.height, k[0], k[4], k[2], k[5]), *sim.camera_xyz(), sim.pose.yaw_rad)
        near = np.isfinite(sim.measured) & (sim.measured < 3.0)
        whole = m.egocentric(64, 0.1)
        marked = m.egocentric(64, 0.1, near_keys=m.keys_at(near))
        assert marked.sum() > 0 and np.array_equal(marked, whole), "the pillar is all there is: all of it is marked"
        assert m.egocentric(64, 0.1, near_keys=m.keys_at(~near)).sum() == 0, "the walls are beyond the map's range"
    finally:
        sim.close()


def test_explanations_of_a_map_network_remove_map_cells_as_free_and_draw_the_image_half():
    cfg = NetConfig(sam_readout="query", local_map=True)
    net = build_network(cfg, seed=5)
    state = state_with_map(2, b=1)[0].numpy()
    state[-1, 40:44, 30:34] = 1.0
    masked = masked_states(state, [np.array([0]), np.array([64 + 5 * 8 + 3])], (8, 8), 128)
    assert np.isinf(masked[0, :5, :8, :8]).all() and (masked[0, -1] == state[-1]).all(), "an image cell: no return"
    assert (masked[1, -1, 40:48, 24:32] == 0).all() and (masked[1, :5] == state[:5]).all(), "a map cell: free"
    with torch.no_grad():
        q, w = net(torch.from_numpy(state)[None])
    rows = explanation(net, state, int(q.argmax()), w[0].numpy())
    assert rows.shape[-1] == 128
    amap = attention_map(rows, (8, 8), (64, 64))
    assert amap.shape == (64, 64) and math.isclose(float(amap.mean()), 1.0, rel_tol=1e-4), "the image half, as shares"
    insight = Insight((8, 8))
    insight.observe(net, state, int(q.argmax()), rows)
    assert insight.summary().frames == 1


def test_the_map_half_of_the_attention_is_drawn_top_down_with_its_share():
    grid = np.zeros((64, 64), np.float32)
    grid[10:14, 40:44] = 1.0  # an obstacle ahead and to the right
    weights = np.zeros((3, 5, 128))
    weights[..., :64] = 0.5 / 64  # half of the mass on the image, spread
    weights[..., 64 + 1 * 8 + 5] = 0.5  # half on the map cell that holds the obstacle (row 1, column 5)
    img = map_overlay(grid, weights, (8, 8), "a1")
    assert img.shape == (256 + 40, 256, 3) and img.dtype == np.uint8
    cell = img[8 * 4 : 16 * 4, 40 * 4 : 48 * 4]
    elsewhere = img[40 * 4 : 48 * 4, 0 : 8 * 4]
    assert cell[..., 1].mean() > elsewhere[..., 1].mean() + 50, "the weighed cell is green"
    assert (img[10 * 4 + 2, 41 * 4 + 2] > 100).all() or img[10 * 4 + 2, 41 * 4 + 2, 1] > 100, "the obstacle shows"
    with pytest.raises(ValueError, match="image cells and as many map cells"):
        map_overlay(grid, weights[..., :64], (8, 8))
