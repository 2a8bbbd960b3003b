"""Why a map can be ignored (uav_policy.map_checks): conicity, sufficiency and the map on the planner's reason, on
constructed networks."""

import numpy as np
import pytest
import torch

from conftest import one_region_net
from uav_policy import map_checks
from uav_policy.insight import Insight
from uav_policy.networks import NetConfig, build_network


def test_conicity_is_one_for_alike_values_and_small_for_values_spread_apart():
    alike = np.tile(np.array([1.0, 2.0, -0.5]), (2, 64, 1))
    assert map_checks.conicity(alike) == pytest.approx(1.0)
    spread = np.eye(16)[None]  # 16 orthogonal values: each at cos 1/4 to their mean
    assert map_checks.conicity(spread) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="values must be"):
        map_checks.conicity(np.ones((4, 3)))


def sam_with_identical_values() -> torch.nn.Module:
    """A query-readout SAM whose value vectors are one constant vector: its attention cannot change its output."""
    net = build_network(NetConfig(model="sam", sam_readout="query"), seed=0).eval()
    kv = net.query_readout.kv
    d = kv.out_features // 2
    with torch.no_grad():
        kv.weight[d:] = 0.0
        kv.bias[d:] = torch.linspace(-1.0, 1.0, d)
    return net


def test_a_network_whose_values_are_identical_scores_conicity_one_and_the_same_sufficiency_in_every_order():
    net, rng = sam_with_identical_values(), np.random.default_rng(0)
    measures = Insight(net.grid_hw, seed=0)
    for _ in range(12):
        state = rng.uniform(0.5, 9.0, (5, 64, 64)).astype(np.float32)
        with torch.no_grad():
            q, w = net(torch.from_numpy(state)[None])
        measures.observe(net, state, int(q.argmax()), w[0].numpy())
    s = measures.summary()
    assert s.conicity == pytest.approx(1.0)
    assert s.sufficiency_top == s.sufficiency_random == s.sufficiency_mean_map == 1.0, "nothing it attends to matters"
    packaged_like = build_network(NetConfig(model="sam", sam_readout="query"), seed=1).eval()
    assert map_checks.conicity(map_checks.readout_values(packaged_like, state)) < 1.0
    cnn = build_network(NetConfig(model="cnn"), seed=0).eval()
    assert map_checks.readout_values(cnn, state) is None, "Grad-CAM weighs no values"


def test_a_network_that_reads_only_its_attended_cells_keeps_its_action_when_only_they_are_kept():
    net, rng = one_region_net(), np.random.default_rng(2)
    on_region = np.zeros(64)
    on_region[0] = 1.0
    kept_top, kept_random = [], []
    for _ in range(100):
        state = rng.uniform(3.0, 9.0, (5, 64, 64)).astype(np.float32)
        state[:, :8, :8] = 1.0
        top, random, _ = map_checks.sufficiency_test(net, state, on_region, 1, (8, 8), rng)
        kept_top.append(top)
        kept_random.append(random)
    assert all(kept_top)
    assert 0.03 < np.mean(kept_random) < 0.2, "7 random cells of 64 keep the region about 1 time in 9"


def test_the_mass_on_the_reason_and_whether_the_top_cell_sees_it():
    reason = np.zeros((64, 64), dtype=bool)
    reason[:8, :8] = True  # the top-left cell, 1/64 of the image
    on = np.zeros(64)
    on[0] = 1.0
    assert map_checks.reason_measures(on, reason, (8, 8)) == (pytest.approx(64.0), True)
    elsewhere = np.zeros(64)
    elsewhere[63] = 1.0
    assert map_checks.reason_measures(elsewhere, reason, (8, 8)) == (0.0, False)
    assert map_checks.reason_measures(on, np.zeros((64, 64), dtype=bool), (8, 8)) is None, "no reason in view"
