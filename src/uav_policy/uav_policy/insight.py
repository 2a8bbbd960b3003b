"""What a decision looks at, and whether that explains it: explanations over the network's grid cells,
measured (PyTorch and numpy, no ROS).

An explanation is one distribution per frame over the nodes (the grid cells of the conv trunk, row-major):
- SAM: the attention the decision uses, as the network returns it, averaged into what each node receives (`received`);
- CNN: Grad-CAM on the trunk's last conv layer for the chosen action (`grad_cam`), named saliency.

Measured per frame and summarised by `Insight` (policy_node's /diagnostics, evaluate's tables):
- sharpness: the mean normalised entropy of each query's weights (1 = uniform, 0 = one node) and the share of
  the mass on the top 10 % of nodes;
- variation: the median correlation of each frame's map with the mean map over the frames (1 = the same map
  whatever is seen; a map that does not vary at all counts as 1);
- faithfulness, a deletion test: how often the greedy action changes when the image regions of the top-k
  explained nodes are masked to "no return", against masking k random nodes; the ratio of the two rates;
- faithfulness against the mean map: the same, against masking the top-k nodes of the mean of the maps seen
  before (a position-only baseline: a fixed prior, the same band on every frame, scores about 1 here however
  it scores against random nodes);
- deletion and insertion curves (RISE, Petsiuk et al. 2018) on the decision's lead, Q of the chosen action over the
  best other: the nodes are removed ("no return") in the map's order, an eighth of the grid at a time, from the whole
  image (deletion; the lower its area, the sooner the decision goes), or restored into an image of no return
  (insertion; the higher, the sooner it comes back); each against the same curves in the mean map's order and in a
  random order. The areas are the curve's mean lead (Q units);
- grounding: the explanation's mass on pixels nearer than NEAR_M against their share of the image (1 = no
  preference; above 1 = looks at what is near); `mass_ratio` and `increase_on` measure it on an object placed in a
  scene (uav_eval.grounding's counterfactual test).
"""

from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np
import torch

from uav_common.frame_stack import node_slices

from .map_checks import conicity, readout_values, reason_measures, sufficiency_test
from .masking import (
    RANDOM_DRAWS,
    compared_sets,
    decisions_with,
    mass_ratio,
    newest_depth,
    ranked,
    received,
    rows_of,
    state_nodes,
    top_count,
)

NEAR_M = 3.0  # grounding: "near" is nearer than this
CURVE_LEVELS = 8  # deletion and insertion curves: the nodes removed or restored an eighth of the grid at a time


def normalised_entropy(weights: np.ndarray) -> float:
    """Mean over rows (heads x queries) of H(row) / log(nodes): 1 for uniform rows, 0 for one-hot rows."""
    rows = rows_of(weights)
    p = rows / np.maximum(rows.sum(axis=1, keepdims=True), 1e-12)
    h = -(p * np.log(np.where(p > 0, p, 1.0))).sum(axis=1)
    return float(h.mean() / math.log(rows.shape[1]))


def top_share(dist: np.ndarray) -> float:
    """The share of the mass on the top 10 % of nodes (0.1 for a uniform map)."""
    d = received(dist)
    return float(np.sort(d)[::-1][: top_count(d.size)].sum())


def map_correlation(maps: np.ndarray) -> float:
    """The median over frames of each map's Pearson correlation with the mean map; a map, or a mean map,
    that does not vary over the nodes counts as 1 (it says nothing about the frame)."""
    m = np.asarray(maps, dtype=np.float64)
    if m.ndim != 2 or len(m) == 0:
        raise ValueError(f"maps must be (frames, nodes), got {m.shape}")
    mean = m.mean(axis=0)
    dm = mean - mean.mean()
    dx = m - m.mean(axis=1, keepdims=True)
    den = np.linalg.norm(dx, axis=1) * np.linalg.norm(dm)
    flat = den < 1e-12 * max(1.0, float(np.abs(m).max()))
    corr = np.where(flat, 1.0, (dx @ dm) / np.where(flat, 1.0, den))
    return float(np.median(corr))


def increase_on(dist: np.ndarray, reference: np.ndarray, mask: np.ndarray, grid_hw: tuple[int, int]) -> bool:
    """Does the node whose mass grew most over `reference` (the explanation without the object) see a pixel of
    `mask` (the object)? False when no node grew (a map that does not move with the scene finds nothing)."""
    rise = received(dist) - received(reference)
    best = int(np.argmax(rise))
    if rise[best] <= 1e-9:
        return False
    rs, cs = node_slices(grid_hw, np.shape(mask))[best]
    return bool(np.asarray(mask, dtype=bool)[rs, cs].any())


def near_ratio(dist: np.ndarray, depth_m: np.ndarray, grid_hw: tuple[int, int], near_m: float = NEAR_M) -> float | None:
    """The mass on pixels nearer than near_m over their share of the image; None when nothing is near."""
    return mass_ratio(dist, np.nan_to_num(np.asarray(depth_m, dtype=np.float32), nan=np.inf) < near_m, grid_hw)


@torch.no_grad()
def deletion_test(
    net: torch.nn.Module,
    state: np.ndarray,
    dist: np.ndarray,
    action: int,
    grid_hw,
    rng: np.random.Generator,
    prior: np.ndarray | None = None,
) -> tuple[bool, float, bool | None]:
    """(does masking the top-k explained nodes change the greedy action, the share of RANDOM_DRAWS masks of
    k random nodes that change it, does masking the top-k nodes of `prior` change it (None without a prior)),
    k = the top 10 % of the nodes."""
    changed = decisions_with(net, state, compared_sets(dist, rng, prior), grid_hw, received(dist).size) != action
    return bool(changed[0]), float(changed[1 : 1 + RANDOM_DRAWS].mean()), None if prior is None else bool(changed[-1])


def q_lead(q: torch.Tensor, action: int) -> torch.Tensor:
    """(batch,) Q of `action` over the best other action: positive while `action` is chosen."""
    others = torch.cat([q[:, :action], q[:, action + 1 :]], dim=1)
    return q[:, action] - others.max(dim=1).values


@torch.no_grad()
def curve_areas(net: torch.nn.Module, state: np.ndarray, orders: list[np.ndarray], action: int, grid_hw) -> np.ndarray:
    """(len(orders), 2): the deletion and the insertion curve's area (mean lead, trapezoids over CURVE_LEVELS + 1
    points) of the decision `action` on `state` (channels, H, W), the nodes removed or restored in each order."""
    nodes = len(orders[0])
    k = np.array([round(i * nodes / CURVE_LEVELS) for i in range(CURVE_LEVELS + 1)])[:, None, None, None]
    pixel_node, fill = state_nodes(state, grid_hw, nodes)
    x0 = np.asarray(state, dtype=np.float32)[None]
    device = next(net.parameters()).device
    out = np.empty((len(orders), 2))
    for i, order in enumerate(orders):
        rank = np.empty(nodes, dtype=np.int64)  # each node's place in the order
        rank[order] = np.arange(nodes)
        pixel_rank = rank[pixel_node][None]  # (1, channels, H, W)
        gone = np.concatenate([pixel_rank < k, pixel_rank >= k])  # deletion levels, then insertion levels
        x = np.where(gone, fill[None], x0)  # (2 * levels, channels, H, W)
        q, _ = net(torch.from_numpy(x).to(device))
        m = q_lead(q, action).cpu().numpy().reshape(2, CURVE_LEVELS + 1)
        out[i] = ((m[:, :-1] + m[:, 1:]) / 2).mean(axis=1)
    return out


def grad_cam(net: torch.nn.Module, state: np.ndarray, action: int) -> np.ndarray:
    """Grad-CAM (Selvaraju et al. 2017) on the conv trunk's last layer for the decision: the target is `action`'s
    lead over the best other action (Q_a - max Q_b), what makes it win; Q_a alone gave all-negative maps with the
    packaged CNN. (nodes,) summing to 1, uniform when no cell raises the lead. A QEnsemble: the mean of its
    members' maps."""
    members = list(getattr(net, "members", [net]))
    device = next(net.parameters()).device
    x = torch.from_numpy(np.ascontiguousarray(state, dtype=np.float32)).unsqueeze(0).to(device)
    maps = []
    with torch.enable_grad():
        for m in members:
            fmap, map_fmap = m.features(x)
            fmap = fmap.detach().requires_grad_(True)
            q, _ = m.from_features(fmap, map_fmap)
            others = torch.cat([q[0, :action], q[0, action + 1 :]])
            (grad,) = torch.autograd.grad(q[0, action] - others.max(), fmap)
            cam = torch.relu((grad.mean(dim=(2, 3), keepdim=True) * fmap).sum(dim=1))[0].flatten()
            maps.append(received(cam.detach().cpu().numpy()))
    return np.mean(maps, axis=0)


def explanation(net: torch.nn.Module, state: np.ndarray, action: int, weights: np.ndarray | None) -> np.ndarray:
    """The rows (heads x queries, nodes) the decision is explained by: SAM's attention weights as the network
    returns them, else Grad-CAM as one row."""
    if weights is not None:
        return rows_of(weights)
    return grad_cam(net, state, action)[None]


@dataclasses.dataclass
class InsightSummary:
    frames: int
    entropy: float  # mean normalised entropy per query
    top_share: float  # mass on the top 10 % of nodes
    map_correlation: float  # median correlation with the mean map
    deletion_top: float  # share of frames whose action changes with the top-k nodes masked
    deletion_random: float  # ... with k random nodes masked
    near_ratio: float  # mass on near pixels over their share (mean over frames with something near); nan if none
    deletion_mean_map: float = math.nan  # ... with the top-k nodes of the mean map so far masked (nan: not measured)
    # The deletion and insertion curves' areas (mean lead) in the map's, the mean map's and a random order.
    deletion_area: float = math.nan
    deletion_area_mean_map: float = math.nan
    deletion_area_random: float = math.nan
    insertion_area: float = math.nan
    insertion_area_mean_map: float = math.nan
    insertion_area_random: float = math.nan
    # Why a map can be ignored, and its ground truth (uav_policy.map_checks): the conicity of the values it weighs, the
    # share of frames that keep their action from the top 10 % of the nodes alone in the map's, a random and the mean
    # map's order; the mass on the planner's reason over its share, the share of frames whose top node sees it.
    conicity: float = math.nan
    sufficiency_top: float = math.nan
    sufficiency_random: float = math.nan
    sufficiency_mean_map: float = math.nan
    reason_mass: float = math.nan
    reason_top: float = math.nan

    @staticmethod
    def ratio(top: float, baseline: float) -> float:
        """top / baseline (inf when only the top-k masks change the action; nan when none do)."""
        if baseline > 0:
            return top / baseline
        return math.inf if top > 0 else math.nan

    @property
    def faithfulness(self) -> float:
        """deletion_top / deletion_random."""
        return self.ratio(self.deletion_top, self.deletion_random)

    @property
    def faithfulness_vs_mean_map(self) -> float:
        """deletion_top / deletion_mean_map: about 1 for a map that is a fixed prior."""
        return self.ratio(self.deletion_top, self.deletion_mean_map)

    CURVES = tuple(f"{c}_area{b}" for c in ("deletion", "insertion") for b in ("", "_mean_map", "_random"))
    FIELDS = ("entropy", "top_share", "map_correlation", "deletion_top", "deletion_random", "near_ratio", "deletion_mean_map")
    CHECKS = ("conicity", "sufficiency_top", "sufficiency_random", "sufficiency_mean_map", "reason_mass", "reason_top")
    FIELDS += CURVES + CHECKS
    # Their names in values() (after "insight_") and in evaluate's results.csv, in FIELDS' order.
    NAMES = ("entropy", "top10_share", "map_correlation", "deletion_top", "deletion_random", "near_ratio", "deletion_mean_map")
    NAMES += CURVES + CHECKS

    @staticmethod
    def from_values(values: dict) -> InsightSummary | None:
        """The summary from its values() (policy_node's /diagnostics); None when they hold none."""
        if "insight_frames" not in values:
            return None
        num = lambda k: math.nan if values.get(k, "-") in ("-", "") else float(values[k])  # noqa: E731
        return InsightSummary(int(values["insight_frames"]), *(num(f"insight_{k}") for k in InsightSummary.NAMES))

    @staticmethod
    def pool(summaries: list[InsightSummary]) -> InsightSummary | None:
        """Several runs' summaries as one: each measure averaged, weighted by the frames measured (nan-aware)."""
        got = [s for s in summaries if s is not None and s.frames > 0]
        if len(got) != len(summaries) or not got:
            return None
        frames = np.array([s.frames for s in got], dtype=float)

        def mean(field: str) -> float:
            v = np.array([getattr(s, field) for s in got], dtype=float)
            ok = ~np.isnan(v)
            return float((v[ok] * frames[ok]).sum() / frames[ok].sum()) if ok.any() else math.nan

        return InsightSummary(int(frames.sum()), *(mean(f) for f in InsightSummary.FIELDS))

    def values(self) -> dict[str, str]:
        f = lambda v: "-" if math.isnan(v) else f"{v:.3f}"  # noqa: E731
        out = {"insight_frames": str(self.frames)}
        out.update({f"insight_{n}": f(getattr(self, k)) for k, n in zip(self.FIELDS, self.NAMES, strict=True)})
        for name in ("faithfulness", "faithfulness_vs_mean_map"):
            v = getattr(self, name)
            out[f"insight_{name}"] = "inf" if math.isinf(v) else f(v)
        return out


class Insight:
    """The measures over the last `window` frames observed (every frame when window is None)."""

    def __init__(self, grid_hw: tuple[int, int], window: int | None = None, seed: int = 0):
        self.grid_hw = grid_hw
        self.rng = np.random.default_rng(seed)
        # (map, entropy, top share, top changed, random changed, near, mean map's top changed or None,
        #  curve areas: deletion and insertion in the map's, a random and the mean map's order (nan without a mean map))
        self.frames = collections.deque(maxlen=window)

    def observe(self, net, state: np.ndarray, action: int, rows: np.ndarray, reason: np.ndarray | None = None) -> None:
        """Measure one decision: `state` (frames, H, W) in metres, its greedy `action`, and the `explanation` of it;
        `reason`, when known (in simulation), the pixels of the newest frame the planner's decision is about, on the
        network's input. The mean-map baseline is the mean of the maps observed before it (none for the first frame)."""

        dist = received(rows)
        prior = np.mean([f[0] for f in self.frames], axis=0) if self.frames else None
        top, rand, by_prior = deletion_test(net, state, dist, action, self.grid_hw, self.rng, prior)
        image = dist[: self.grid_hw[0] * self.grid_hw[1]]  # with the local map, the image's cells (the first half)
        near = near_ratio(image, newest_depth(state, dist.size, self.grid_hw), self.grid_hw)
        orders = [ranked(dist, self.rng), self.rng.permutation(dist.size)] + (
            [ranked(prior, self.rng)] if prior is not None else []
        )
        areas = np.full((3, 2), np.nan)
        areas[: len(orders)] = curve_areas(net, state, orders, action, self.grid_hw)
        values = readout_values(net, state)
        kept = sufficiency_test(net, state, dist, action, self.grid_hw, self.rng, prior)
        on_reason = reason_measures(image, reason, self.grid_hw) if reason is not None else None
        checks = (math.nan if values is None else conicity(values), *kept, on_reason)
        self.frames.append((dist, normalised_entropy(rows), top_share(dist), top, rand, near, by_prior, areas, checks))

    def summary(self) -> InsightSummary | None:
        if not self.frames:
            return None
        maps, ent, share, top, rand, near, by_prior, areas, checks = zip(*self.frames, strict=True)
        near = [n for n in near if n is not None]
        by_prior = [b for b in by_prior if b is not None]
        a = np.stack(areas)  # (frames, order: map, random, mean map; deletion, insertion)
        mean = lambda v: float(np.nanmean(v)) if len(v) and not np.isnan(v).all() else math.nan  # noqa: E731
        curves = [mean(a[:, o, c]) for c in (0, 1) for o in (0, 2, 1)]  # CURVES' order
        cone, kept_top, kept_random, kept_prior, on_reason = zip(*checks, strict=True)
        kept_prior = [float(k) for k in kept_prior if k is not None]
        on_reason = [r for r in on_reason if r is not None]
        return InsightSummary(
            len(maps),
            float(np.mean(ent)),
            float(np.mean(share)),
            map_correlation(np.stack(maps)),
            float(np.mean(top)),
            float(np.mean(rand)),
            float(np.mean(near)) if near else math.nan,
            float(np.mean(by_prior)) if by_prior else math.nan,
            *curves,
            mean(np.array(cone)),
            float(np.mean(kept_top)),
            float(np.mean(kept_random)),
            mean(np.array(kept_prior)),
            mean(np.array([r[0] for r in on_reason])),
            mean(np.array([float(r[1]) for r in on_reason])),
        )
