"""The measures of what a decision looks at (uav_policy.insight), on constructed inputs."""

import math

import numpy as np
import pytest
import torch

from conftest import one_region_net
from uav_policy import insight
from uav_policy.insight import Insight, InsightSummary


def test_uniform_attention_has_entropy_one_and_no_variation():
    uniform = np.full((3, 64, 64), 1 / 64)
    assert insight.normalised_entropy(uniform) == pytest.approx(1.0)
    assert insight.top_share(uniform) == pytest.approx(7 / 64), "the top tenth (7 of 64 nodes) holds its share"
    assert insight.map_correlation(np.stack([insight.received(uniform)] * 10)) == 1.0, "a map that never varies"


def test_one_hot_attention_has_entropy_zero_and_all_mass_on_top():
    w = np.zeros((2, 64, 64))
    w[:, :, 5] = 1.0
    assert insight.normalised_entropy(w) == pytest.approx(0.0, abs=1e-9)
    assert insight.top_share(w) == pytest.approx(1.0)


def test_maps_that_follow_the_scene_correlate_little_with_their_mean():
    rng = np.random.default_rng(0)
    one_hots = np.eye(64)[rng.integers(0, 64, 200)]  # each frame looks somewhere else
    assert insight.map_correlation(one_hots) < 0.2
    fixed = np.tile(np.linspace(1, 2, 64), (50, 1)) + 0.01 * rng.random((50, 64))  # a fixed gradient, whatever is seen
    assert insight.map_correlation(fixed) > 0.95


def test_near_ratio_says_where_the_mass_is_against_what_is_near():
    depth = np.full((64, 64), 8.0, np.float32)
    depth[:8, :8] = 1.0  # an obstacle at 1 m in the top-left cell, 1/64 of the image
    on = np.zeros(64)
    on[0] = 1.0
    assert insight.near_ratio(on, depth, (8, 8)) == pytest.approx(64.0)
    assert insight.near_ratio(np.full(64, 1 / 64), depth, (8, 8)) == pytest.approx(1.0)
    assert insight.near_ratio(on, np.full((64, 64), np.inf, np.float32), (8, 8)) is None, "nothing near: undefined"


def test_a_decision_that_depends_on_one_region_is_faithful_to_an_explanation_of_that_region():
    net, rng = one_region_net(), np.random.default_rng(1)
    faithful, unfaithful = Insight((8, 8)), Insight((8, 8))
    right, wrong = np.zeros((1, 64)), np.zeros((1, 64))
    right[0, 0], wrong[0, 56:] = 1.0, 1 / 8  # the region, or the bottom row
    for _ in range(200):
        state = rng.uniform(3.0, 9.0, (5, 64, 64)).astype(np.float32)
        state[:, :8, :8] = 1.0  # the obstacle the decision turns for
        faithful.observe(net, state, 1, right)
        unfaithful.observe(net, state, 1, wrong)
    good, bad = faithful.summary(), unfaithful.summary()
    assert good.deletion_top == 1.0 and bad.deletion_top == 0.0
    assert 0.02 < good.deletion_random < 0.2, "7 random nodes of 64 hit the region about 1 time in 9"
    assert good.faithfulness >= 2 and bad.faithfulness < 1
    assert good.near_ratio > 10 and bad.near_ratio == 0.0 and good.frames == 200


def test_grad_cam_is_a_distribution_over_the_cells_and_follows_the_input():
    from uav_policy import weights as wio

    cnn = wio.load_files([str(wio.packaged_weights("cnn")[0])], "cnn")
    maps = []
    for side in (slice(8, 24), slice(40, 56)):  # a pole left, then right, 1.5 m ahead in an open room
        state = np.full((5, 64, 64), 8.0, np.float32)
        state[:, 16:48, side] = 1.5
        q, _ = cnn(torch.from_numpy(state)[None])
        maps.append(insight.grad_cam(cnn, state, int(q.argmax())))
    for m in maps:
        assert m.shape == (64,) and m.sum() == pytest.approx(1.0) and (m >= 0).all()
    assert insight.normalised_entropy(maps[0]) < 0.99, "not uniform"
    assert not np.allclose(maps[0], maps[1]), "another scene, another map"


def test_summaries_pool_by_frames_and_survive_diagnostics():
    a = InsightSummary(100, 0.5, 0.3, 0.4, 0.6, 0.2, 2.0)
    b = InsightSummary(300, 0.9, 0.1, 0.8, 0.2, 0.2, math.nan)
    p = InsightSummary.pool([a, b])
    assert p.frames == 400 and p.entropy == pytest.approx(0.8) and p.near_ratio == 2.0
    assert p.faithfulness == pytest.approx(0.3 / 0.2)
    back = InsightSummary.from_values(a.values())
    assert back == a and InsightSummary.from_values({}) is None
    assert InsightSummary(10, 1, 0.1, 1, 0.5, 0.0, 1).values()["insight_faithfulness"] == "inf"
    assert InsightSummary.pool([a, None]) is None, "a run not measured leaves the pool unmeasured"


class NearAnywhere(torch.nn.Module):
    """Turns (action 1) when any pixel of the newest frame is nearer than 2 m, else flies on (action 0): its decision
    depends on every cell, so the cell the obstacle is in is what it depends on."""

    grid_hw = (8, 8)

    def __init__(self):
        super().__init__()
        self.dummy = torch.nn.Parameter(torch.zeros(1))

    def forward(self, x):
        near = (torch.nan_to_num(x[:, -1], posinf=10.0).flatten(1).min(dim=1).values < 2.0).float()
        return torch.stack([1 - near, near, torch.zeros_like(near), torch.zeros_like(near)], dim=1), None


def scene(rng, rows=range(8)) -> tuple[np.ndarray, int]:
    """A state with one obstacle cell at 1 m (in one of `rows`) before an 8 m background, and its node index."""
    state = np.full((5, 64, 64), 8.0, np.float32)
    node = int(rng.choice(list(rows))) * 8 + int(rng.integers(0, 8))
    r, c = divmod(node, 8)
    state[:, 8 * r : 8 * r + 8, 8 * c : 8 * c + 8] = 1.0
    return state, node


def test_a_map_that_follows_what_the_decision_reads_is_faithful_against_random_and_mean_map_cells():
    """The explanation is the obstacle's cell: masking it changes the decision every time, random cells and the
    mean map's top cells seldom."""
    rng, net, meter = np.random.default_rng(1), NearAnywhere(), Insight((8, 8), seed=0)
    for _ in range(150):
        state, node = scene(rng)
        rows = np.full((1, 64), 0.01 / 63)
        rows[0, node] = 0.99
        meter.observe(net, state, 1, rows)
    s = meter.summary()
    assert s.deletion_top == 1.0 and s.faithfulness > 4 and s.faithfulness_vs_mean_map > 4, s
    # RISE curves on the lead (+1 turning, -1 not): removing the map's first eighth ends the decision, restoring it
    # brings it back; in the mean map's or a random order that takes half the curve on average.
    assert s.deletion_area == pytest.approx(-0.875) and s.insertion_area == pytest.approx(0.875), s
    for other in (s.deletion_area_mean_map, s.deletion_area_random):
        assert other > s.deletion_area + 0.5, s
    for other in (s.insertion_area_mean_map, s.insertion_area_random):
        assert other < s.insertion_area - 0.5, s


def test_a_fixed_map_with_a_skip_path_scores_one_against_the_mean_map_however_it_scores_against_random_cells():
    """A fixed floor band (the bottom rows, ranked by a fixed gradient) whatever is seen, while the decision reads
    every cell: obstacles often in the band make it look faithful against random cells; against the mean map, whose
    top cells are the band itself, it scores 1."""
    rng, net, meter = np.random.default_rng(2), NearAnywhere(), Insight((8, 8), seed=0)
    band = np.zeros(64)
    band[48:] = np.linspace(2.0, 1.0, 16)  # the bottom two rows, fixed ranks
    band /= band.sum()
    for _ in range(150):
        state, _ = scene(rng, rows=(6, 6, 7, 3))
        meter.observe(net, state, 1, band[None])
    s = meter.summary()
    assert s.faithfulness > 2, f"the fixed band passes the random-cell test: {s.faithfulness:.2f}"
    assert s.faithfulness_vs_mean_map == pytest.approx(1.0, abs=0.02), s
    assert s.map_correlation == 1.0
    # Its curves are the mean map's (the same order but for ties among the cells off the band, drawn at random).
    assert s.deletion_area == pytest.approx(s.deletion_area_mean_map, abs=0.15), s
    assert s.insertion_area == pytest.approx(s.insertion_area_mean_map, abs=0.15), s
    assert s.deletion_area < s.deletion_area_random - 0.2, "it beats random cells on the curves too"
