"""The counterfactual grounding test (uav_eval.grounding): obstacles placed in an empty room, the explanation's
mass on them, and the cascading-randomisation sanity check, on constructed and built networks."""

import numpy as np
import pytest
import torch

from uav_eval import grounding
from uav_policy.networks import NetConfig, build_network

HFOV = 90.0


class LooksAtNear(torch.nn.Module):
    """Attends to the nearest cells above the horizon in the newest frame (a softmax over minus their depth; the floor
    below is ignored); its Q-values come from a linear head on the frame's mean depth, so re-initialising that head
    leaves the explanation as it is."""

    def __init__(self, sharpness: float = 4.0):
        super().__init__()
        self.cfg = NetConfig(model="sam")
        self.sharpness = sharpness
        self.head = torch.nn.Linear(1, 4)

    @property
    def grid_hw(self):
        return (8, 8)

    def forward(self, x):
        d = torch.nan_to_num(x[:, -1:], posinf=10.0).clamp(max=10.0)
        cells = -torch.nn.functional.max_pool2d(-d, 8)  # each cell's nearest depth
        cells[:, :, 4:] = 10.0  # the lower half (the floor) as far
        cells = cells.flatten(1)
        w = torch.softmax(-self.sharpness * cells, dim=-1)[:, None, None, :]
        return self.head(d.mean(dim=(1, 2, 3))[:, None]), w


class Uniform(LooksAtNear):
    def forward(self, x):
        q, w = super().forward(x)
        return q, torch.full_like(w, 1 / 64)


@pytest.fixture(scope="module")
def rendered():
    return grounding.run(LooksAtNear(), HFOV, "ideal", 1.0, log=lambda s: None)


def test_the_scene_set_covers_pillars_boxes_walls_and_pairs_in_view(rendered):
    listed, frames, empty = rendered
    assert {s.kind for s in listed} == {"pillar", "box", "wall", "pair"} and len(listed) == 26
    shares = [grounding.obstacle_mask(f, empty).mean() for _, f in frames]
    assert min(shares) > 0.0, "every obstacle is in view"
    pillars = [s for s, (scene, _) in zip(shares, frames, strict=True) if scene.kind == "pillar"]
    assert pillars[0] > pillars[-1], "a pillar at 1.5 m fills more of the image than one at 4 m"
    assert np.isinf(empty.exact).mean() > 0.4, "the empty room's walls are beyond range: only the floor returns"


def test_a_network_that_looks_at_the_obstacle_scores_high_and_a_constant_map_scores_one(rendered):
    _, frames, empty = rendered
    looks = grounding.summarise(grounding.measure(LooksAtNear(), frames, empty))
    flat = grounding.summarise(grounding.measure(Uniform(), frames, empty))
    assert looks["scenes"] == 26 and looks["ratio"] > 3.0 and looks["hits"] > 0.9
    assert flat["ratio"] == pytest.approx(1.0) and flat["hits"] == 0.0
    # The planner's reason: the obstacle that bounds the decision from the hovering pose, in the near scenes.
    near = [f for scene, f in frames if scene.kind == "pillar" and "1.5 m" in scene.name]
    assert all(
        f.reason is not None and (f.reason & grounding.obstacle_mask(f, empty)).sum() > 0.95 * f.reason.sum() for f in near
    )
    assert looks["reason_scenes"] >= len(near) and looks["reason_mass"] > 2.0 and looks["reason_top"] > 0.8
    assert flat["reason_mass"] == pytest.approx(1.0) and flat["reason_scenes"] == looks["reason_scenes"]


def test_the_pair_scenes_are_measured_on_the_nearer_obstacle(rendered):
    _, frames, empty = rendered
    (scene, frame), *_ = [(s, f) for s, f in frames if s.kind == "pair"]
    mask = grounding.obstacle_mask(frame, empty)
    both = np.nan_to_num(frame.exact, posinf=1e6) < np.nan_to_num(empty.exact, posinf=1e6) - 0.05
    assert mask.sum() < both.sum() and (mask <= both).all(), "the far pillar's pixels are not the obstacle's"
    assert np.nanmin(np.where(mask, frame.exact, np.nan)) < 1.6


def test_randomisation_changes_a_learnt_explanation_and_not_one_that_ignores_the_weights(rendered):
    """Adebayo et al. 2018: randomising the layers must change a map that depends on them (a built SAM's attention,
    the CNN's Grad-CAM); a map computed from the input alone survives and the check says so (correlation 1)."""
    _, frames, empty = rendered
    rows = grounding.sanity(LooksAtNear(), frames, empty)
    assert [r.randomised for r in rows] == ["head"] and rows[0].rank_correlation == pytest.approx(1.0)
    for model, readout in (("sam", "query"), ("sam", "topk"), ("cnn", "max")):
        net = build_network(NetConfig(model=model, sam_readout=readout), seed=0)
        rows = grounding.sanity(net, frames, empty)
        assert rows[-1].randomised == "trunk.0" and rows[0].randomised in ("query_readout", "dueling_head")
        assert rows[-1].rank_correlation < 0.5, (model, readout, [(r.randomised, r.rank_correlation) for r in rows])
