"""Why a map can be ignored, measured (PyTorch and numpy, no ROS): the conicity of the values the attention weighs,
and a sufficiency test.

- Conicity (Mohankumar et al., ACL 2020): the mean cosine of each node's value vector with the mean of them, per head
  and averaged (0 for values spread in every direction, 1 when they are all alike). When the values are alike any
  weighting of them gives the same output, so no attention map over them can be faithful, whatever it looks like.
- Sufficiency (the complement of the deletion test): keep only the top 10 % of the nodes, the rest of the image set to
  "no return", and see whether the decision stays; in the map's order, the mean map's and a random order. A map that
  carries the decision keeps it more often from its own top nodes than from the mean map's or random ones.
- The reason (uav_sim.planner): the mass on the pixels of what the planner's decision is about over their share of
  the image, and whether the map's top node sees one of them.
"""

from __future__ import annotations

import numpy as np
import torch

from uav_common.frame_stack import node_slices

from .masking import RANDOM_DRAWS, compared_sets, decisions_with, mass_ratio, received


def conicity(values: np.ndarray) -> float:
    """(heads, nodes, d) -> the mean over heads of the mean cosine of each node's vector with the nodes' mean vector."""
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 3 or v.shape[1] < 2:
        raise ValueError(f"values must be (heads, nodes >= 2, d), got shape {v.shape}")
    mean = v.mean(axis=1, keepdims=True)
    norms = np.linalg.norm(v, axis=2) * np.linalg.norm(mean, axis=2)
    cos = (v * mean).sum(axis=2) / np.where(norms > 0, norms, 1.0)
    return float(np.where(norms > 0, cos, 1.0).mean())


@torch.no_grad()
def readout_values(net: torch.nn.Module, state: np.ndarray) -> np.ndarray | None:
    """(members x heads, nodes, d_head): the value vectors the shown attention weighs, for SAM's `query` readout (the
    shipped one); None for a network whose map weighs no values (the CNN's Grad-CAM, SAM's other readouts)."""
    members = list(getattr(net, "members", [net]))
    if not all(getattr(m, "query_readout", None) is not None for m in members):
        return None
    device = next(net.parameters()).device
    x = torch.from_numpy(np.ascontiguousarray(state, dtype=np.float32)).unsqueeze(0).to(device)
    out = []
    for m in members:
        unmixed = m.unmixed_nodes(*m.features(x))
        r = m.query_readout
        _, v = r.kv(r.norm(unmixed)).view(1, unmixed.shape[1], 2, r.heads, r.d_head).permute(2, 0, 3, 1, 4)
        out.append(v[0].cpu().numpy())  # (heads, nodes, d_head)
    return np.concatenate(out)


def sufficiency_test(net, state: np.ndarray, dist: np.ndarray, action: int, grid_hw, rng, prior=None) -> tuple:
    """(does keeping only the map's top 10 % of the nodes keep the greedy action, the share of RANDOM_DRAWS sets of as
    many random nodes that keep it, does keeping the top 10 % of `prior` keep it (None without a prior))."""
    everything = np.arange(received(dist).size)
    gone = [np.setdiff1d(everything, keep) for keep in compared_sets(dist, rng, prior)]
    same = decisions_with(net, state, gone, grid_hw, everything.size) == action
    return bool(same[0]), float(same[1 : 1 + RANDOM_DRAWS].mean()), None if prior is None else bool(same[-1])


def reason_measures(dist: np.ndarray, reason: np.ndarray, grid_hw) -> tuple[float, bool] | None:
    """(the map's mass on the reason's pixels over their share of the image, does its top node see one of them) for an
    image-sized bool mask `reason`; None when the reason shows no pixel."""
    ratio = mass_ratio(dist, reason, grid_hw)
    if ratio is None:
        return None
    rs, cs = node_slices(grid_hw, reason.shape)[int(np.argmax(received(dist)))]
    return ratio, bool(np.asarray(reason, dtype=bool)[rs, cs].any())
