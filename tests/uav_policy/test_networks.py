import numpy as np
import pytest
import torch

from uav_common.actions import PAPER_ACTIONS, match_action
from uav_common.frame_stack import FrameStack
from uav_policy.agent import Agent
from uav_policy.attention import attention_map, overlay
from uav_policy.networks import NetConfig, QEnsemble, build_network, forward_flops, normalise_depth, parameter_count


def depth_batch(b=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(b, 5, 64, 64, generator=g) * 12.0
    x[0, 0, 0, 0] = float("inf")
    x[0, 0, 0, 1] = float("nan")
    return x


def test_sam_shapes_and_attention_rows_sum_to_one():
    net = build_network(NetConfig(model="sam"), seed=1)
    q, w = net(depth_batch())
    assert q.shape == (3, 4)
    assert w.shape == (3, 3, 64, 64)  # (batch, heads, nodes, nodes): 8x8 grid, 3 heads
    torch.testing.assert_close(w.sum(-1), torch.ones(3, 3, 64))
    assert torch.isfinite(q).all()


def test_sam_flatten_readout_sees_where_a_feature_is():
    """Readout `flatten` feeds every node, in grid order, to the CNN's hidden layer; `max` pools them."""
    cfg = NetConfig(model="sam", sam_readout="flatten")
    net = build_network(cfg, seed=1)
    q, w = net(depth_batch())
    assert q.shape == (3, 4) and w.shape == (3, 3, 64, 64)
    torch.testing.assert_close(w.sum(-1), torch.ones(3, 3, 64))
    n = parameter_count(net)
    assert 1.0 <= n / parameter_count(build_network(NetConfig(model="cnn"))) <= 1.2  # a CNN plus one relational block
    # After the relational block, swapping two nodes changes nothing for max pooling but moves the
    # features to other places of the flattened readout.
    nodes = torch.randn(2, 64, cfg.d_model)
    swapped = nodes[:, [1, 0, *range(2, 64)]]
    pooled = build_network(NetConfig(model="sam"), seed=1)
    torch.testing.assert_close(pooled.dueling_head(nodes.max(1).values), pooled.dueling_head(swapped.max(1).values))
    assert not torch.allclose(net.readout(nodes), net.readout(swapped))
    with pytest.raises(ValueError, match="sam_readout"):
        NetConfig(model="sam", sam_readout="mean").validate()
    assert NetConfig(model="cnn", sam_readout="flatten") == NetConfig(model="cnn")  # the CNN has no readout choice


def test_cnn_shapes_and_no_attention():
    net = build_network(NetConfig(model="cnn"), seed=1)
    q, w = net(depth_batch())
    assert q.shape == (3, 4) and w is None


@pytest.mark.parametrize("model", ["sam", "cnn"])
def test_dueling_identity_advantages_have_zero_mean(model):
    net = build_network(NetConfig(model=model), seed=2)
    x = depth_batch()
    q, _ = net(x)
    trunk_out = net.trunk(x)
    if model == "sam":
        nodes = trunk_out.flatten(2).transpose(1, 2)
        coords = net.coords.unsqueeze(0).expand(nodes.shape[0], -1, -1)
        feats = net.node_projection(torch.cat([nodes, coords], -1))
        for block in net.relational_blocks:
            feats, _ = block(feats)
        feats = feats.max(1).values
    else:
        feats = net.hidden(trunk_out.flatten(1))
    v = net.dueling_head.value(feats)
    # Q - V are the centred advantages: they average to zero for every state.
    torch.testing.assert_close((q - v).mean(-1), torch.zeros(3), atol=1e-5, rtol=0)


def test_q_values_can_go_below_minus_one():
    # No ELU on the output: a linear head can represent a crash's -10.
    net = build_network(NetConfig(model="sam"), seed=0)
    with torch.no_grad():
        net.dueling_head.value[-1].bias.fill_(-10.0)
    q, _ = net(depth_batch())
    assert (q < -5).all()


@pytest.mark.parametrize("model", ["sam", "cnn"])
def test_seeded_network_is_deterministic(model):
    a, b = build_network(NetConfig(model=model), seed=7), build_network(NetConfig(model=model), seed=7)
    c = build_network(NetConfig(model=model), seed=8)
    x = depth_batch()
    torch.testing.assert_close(a(x)[0], b(x)[0], rtol=0, atol=0)
    assert not torch.allclose(a(x)[0], c(x)[0])


@pytest.mark.parametrize("model", ["sam", "cnn"])
def test_an_ensemble_acts_on_the_mean_of_its_members_q_values(model):
    members = [build_network(NetConfig(model=model), seed=s) for s in (1, 2, 3)]
    x = depth_batch()
    with torch.no_grad():
        q, w = QEnsemble(members)(x)
        outs = [m(x) for m in members]
    torch.testing.assert_close(q, sum(o[0] for o in outs) / 3)
    if model == "sam":  # every member's heads side by side, rows still sum to 1
        assert w.shape == (3, 9, 64, 64)
        torch.testing.assert_close(w[:, 3:6], outs[1][1])
        torch.testing.assert_close(w.sum(-1), torch.ones(3, 9, 64))
        assert QEnsemble(members).grid_hw == (8, 8)
    else:
        assert w is None
    with torch.no_grad():  # two copies of one network act as that network
        torch.testing.assert_close(QEnsemble([members[0], members[0]])(x)[0], outs[0][0])
    with pytest.raises(ValueError, match="at least 2"):
        QEnsemble(members[:1])
    other = build_network(NetConfig(model=model, head_hidden=32), seed=1)
    with pytest.raises(ValueError, match="one architecture"):
        QEnsemble([members[0], other])


def test_normalisation_of_rep117_values():
    x = torch.tensor([float("inf"), float("-inf"), float("nan"), 5.0, 20.0])
    assert normalise_depth(x, 10.0).tolist() == [1.0, 0.0, 1.0, 0.5, 1.0]


def test_attention_map_is_on_an_absolute_scale_and_the_overlay_is_readable():
    w = np.zeros((3, 4, 4), dtype=np.float32)
    w[:, :, 2] = 1.0  # every query attends to node 2 = grid cell (row 1, col 0) of a 2x2 grid
    amap = attention_map(w, (2, 2), (8, 8))
    assert amap.shape == (8, 8) and (amap[4:, :4] == 4.0).all(), "all the mass on 1 of 4 nodes: 4x its uniform share"
    assert amap[:4].sum() == 0 and amap[4:, 4:].sum() == 0
    assert (attention_map(np.full((3, 4, 4), 0.25), (2, 2), (8, 8)) == 1.0).all(), "uniform reads 1, not a stretch"
    rgb = overlay(np.full((8, 8), 2.0, np.float32), amap, 10.0, label="a1 Q 2.00, lead +0.10")
    k = 256 // 8
    assert rgb.dtype == np.uint8 and rgb.shape == (8 * k + 40, 8 * k, 3), "upscaled to 256 px, a 40 px legend below"
    assert rgb[6 * k, 1 * k, 1] > rgb[6 * k, 1 * k, 0] and rgb[1 * k, 6 * k, 1] == rgb[1 * k, 6 * k, 0]
    legend = rgb[8 * k :]
    assert (legend[:16] == 255).any(), "the label is written"
    bar = legend[29, 4:100, 1].astype(int)
    assert bar[0] < bar[-1], "the legend bar runs from a uniform share (no colour) to full green"
    faint = overlay(np.full((8, 8), 2.0, np.float32), amap / 2, 10.0)
    assert faint[6 * k, 1 * k, 1] < rgb[6 * k, 1 * k, 1], "half the mass, a fainter green: the scale is absolute"


def test_attention_readout_weights_form_the_q_values():
    """Readout `attend`: one learned query per head over the nodes; its weights are what the forward pass returns,
    and a node given no weight cannot change the Q-values."""
    net = build_network(NetConfig(model="sam", sam_readout="attend"), seed=0)
    x = depth_batch(2)
    q, w = net(x)
    assert w.shape == (2, 3, 1, 64)
    torch.testing.assert_close(w.sum(-1), torch.ones(2, 3, 1))
    with torch.no_grad():
        net.pooling.query.zero_()
        net.pooling.query[:, 0, 0] = 1.0
        net.pooling.kv.weight.zero_()
        net.pooling.kv.bias.zero_()
        net.pooling.kv.bias[0] = -1e4  # head 0's first key feature: every node's key pushes its weight to 0 ...
    q, w = net(x)
    assert torch.allclose(w, torch.full_like(w, 1 / 64)), "equal keys: equal weights"
    # ... and values all zero: the pooled vector, hence Q, is the same whatever the depth.
    q2, _ = net(depth_batch(2, seed=5))
    torch.testing.assert_close(q, q2)


def test_frame_stack_resets_per_episode():
    fs = FrameStack(5)
    s = fs.reset(np.full((2, 2), 1.0))
    assert s.shape == (5, 2, 2) and (s == 1.0).all()
    for k in range(2, 8):
        s = fs.push(np.full((2, 2), float(k)))
    assert s[:, 0, 0].tolist() == [3.0, 4.0, 5.0, 6.0, 7.0]  # oldest first
    s = fs.reset(np.full((2, 2), 9.0))
    assert (s == 9.0).all()


def test_epsilon_greedy_agent():
    cfg = NetConfig(model="sam")
    agent = Agent(build_network(cfg, seed=0), cfg, seed=0)
    state = depth_batch(1)[0].numpy()
    a, q, w, explored = agent.act(state, 0.0)
    assert a == int(np.argmax(q)) and not explored and w.shape == (3, 64, 64)
    picks = {agent.act(state, 1.0)[0] for _ in range(100)}
    assert picks == {0, 1, 2, 3}


def test_actions_round_trip_from_twist():
    for i, a in enumerate(PAPER_ACTIONS):
        assert match_action(PAPER_ACTIONS, a.linear_x_mps, a.yaw_rate_radps(0.5), 0.5) == i
    assert match_action(PAPER_ACTIONS, 1.5, 0.0, 0.5) is None


def test_forward_flops_price_an_architecture_without_building_it():
    """Counted on the meta device: the cost grows with the nodes squared (attention) and with the layers; the
    conv trunk's first layer alone is 64 x 32 x 32 outputs x 5 x 4 x 4 inputs x 2 (multiply and add)."""
    small = forward_flops(NetConfig(model="sam"))
    assert forward_flops(NetConfig(model="cnn", conv_channels=(16,), cnn_hidden=1, head_hidden=1)) > 2 * 16 * 32 * 32 * 5 * 16
    nodes_x4 = forward_flops(NetConfig(model="sam", conv_channels=(16, 32)))  # 16 x 16 nodes, not 8 x 8
    assert 2 * small < nodes_x4 < 10 * small
    heavy = NetConfig(model="sam", conv_channels=(16,), d_model=384, heads=6, relational_blocks=2, mlp_hidden=96)
    assert forward_flops(heavy) > 400 * small
    with pytest.raises(ValueError):
        forward_flops(NetConfig(model="sam", d_model=50))  # not divisible by the heads: refused, as build_network does


@pytest.mark.parametrize("readout", ["query", "topk"])
def test_grounded_readouts_reach_the_q_values_only_through_their_attended_cells(readout):
    """Readouts `query` (one query per action and one for the value, computed from the frame) and `topk` (only each
    head's top eighth of the nodes): their weights are what the forward pass returns, and with the attended values
    silenced the Q-values are the same whatever the depth: there is no path around the attention."""
    net = build_network(NetConfig(model="sam", sam_readout=readout), seed=0)
    x = depth_batch(2)
    q, w = net(x)
    assert w.shape == ((2, 3, 5, 64) if readout == "query" else (2, 3, 1, 64))
    torch.testing.assert_close(w.sum(-1), torch.ones(w.shape[:-1]))
    if readout == "topk":
        assert ((w > 0).sum(-1) == 8).all(), "8 of 64 nodes kept per head"
    q2, _ = net(depth_batch(2, seed=5))
    assert not torch.allclose(q, q2), "the Q-values depend on the depth"
    with torch.no_grad():
        if readout == "query":
            d = net.cfg.d_model
            net.query_readout.kv.weight[d:].zero_()  # the values' half of the key/value projection
            net.query_readout.kv.bias[d:].zero_()
        else:
            net.pooling.value.weight.zero_()
            net.pooling.value.bias.zero_()
    q, _ = net(x)
    q2, _ = net(depth_batch(2, seed=5))
    torch.testing.assert_close(q, q2)
