"""Cells of a state taken away, and what the decision does then (no ROS): the explanations' shared ground.

A node of the attention (a cell of the trunk's grid) sees a region of every depth frame; with the local map, the second
half of the nodes see regions of the map channel. Removing a node reads its image regions as "no return" (+inf) and its
map cells as free. uav_policy.insight and uav_policy.map_checks measure explanations with these.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from uav_common.frame_stack import node_shares, node_slices

TOP_FRACTION = 0.1  # sharpness and the deletion test: the top tenth of the nodes
RANDOM_DRAWS = 4  # the deletion test's random masks per frame


def rows_of(weights: np.ndarray) -> np.ndarray:
    """(..., nodes) -> (rows, nodes), each row a distribution."""
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim < 1 or w.shape[-1] < 2:
        raise ValueError(f"an explanation needs at least 2 nodes on its last axis, got shape {w.shape}")
    return w.reshape(-1, w.shape[-1])


def received(weights: np.ndarray) -> np.ndarray:
    """The mass each node receives, (nodes,), summing to 1: the rows of (..., nodes) averaged."""
    r = rows_of(weights).mean(axis=0)
    total = r.sum()
    return r / total if total > 0 else np.full_like(r, 1.0 / r.size)


def top_count(nodes: int) -> int:
    return max(1, math.ceil(TOP_FRACTION * nodes))


def mass_ratio(dist: np.ndarray, mask: np.ndarray, grid_hw: tuple[int, int]) -> float | None:
    """The explanation's mass on the pixels of `mask` (an image-sized bool array) over their share of the image
    (1 = no preference, 2 = twice their share); None when the mask is empty."""
    d = received(dist)
    m = np.asarray(mask, dtype=bool)
    share = float(m.mean())
    if share == 0.0:
        return None
    return float((d * node_shares(m, grid_hw)).sum() / share)


@functools.lru_cache(maxsize=16)
def node_of_pixel(grid_hw: tuple[int, int], image_hw: tuple[int, int]) -> np.ndarray:
    """(H, W) the node each pixel belongs to (node_slices' regions); cached and read-only: measuring maps cells to
    pixels on every call."""
    out = np.zeros(image_hw, dtype=np.int64)
    for n, (rs, cs) in enumerate(node_slices(grid_hw, image_hw)):
        out[rs, cs] = n
    out.flags.writeable = False
    return out


def state_nodes(state: np.ndarray, grid_hw: tuple[int, int], nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """((channels, H, W) the node each value of `state` belongs to, (channels, 1, 1) what a removed value reads as).
    With `nodes` twice the grid's (a network with the local map): the depth frames' pixels are the first half's
    nodes and read as "no return" (+inf) when removed, the map channel's cells the second half's and read as free."""
    cells = grid_hw[0] * grid_hw[1]
    pixel_node = node_of_pixel(tuple(grid_hw), tuple(state.shape[-2:]))
    channels = state.shape[0]
    fill = np.full((channels, 1, 1), np.inf, dtype=np.float32)
    per_channel = np.broadcast_to(pixel_node, (channels, *pixel_node.shape))
    if nodes == 2 * cells:
        per_channel = np.concatenate([per_channel[:-1], pixel_node[None] + cells])
        fill[-1] = 0.0
    return per_channel, fill


def newest_depth(state: np.ndarray, nodes: int, grid_hw: tuple[int, int]) -> np.ndarray:
    """The newest depth frame of a state (the last channel but one with the local map)."""
    return state[-2] if nodes == 2 * grid_hw[0] * grid_hw[1] else state[-1]


def masked_states(
    state: np.ndarray, nodes: list[np.ndarray], grid_hw: tuple[int, int], count: int | None = None
) -> np.ndarray:  # (len(nodes), channels, H, W)
    """Copies of `state` (channels, H, W), each with the image regions of one set of nodes set to "no return"
    (+inf) in every frame (and a map node's cells to free: state_nodes); `count`: the nodes (default: the grid's)."""
    count = grid_hw[0] * grid_hw[1] if count is None else count
    pixel_node, fill = state_nodes(state, grid_hw, count)
    gone = np.zeros((len(nodes), count), dtype=bool)
    for i, chosen in enumerate(nodes):
        gone[i, np.asarray(chosen, dtype=np.int64)] = True
    return np.where(gone[:, pixel_node], fill[None], np.asarray(state, dtype=np.float32)[None])


def ranked(dist: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The nodes by mass, most first; nodes of equal mass in random order, not by index."""
    d = received(dist)
    shuffled = rng.permutation(d.size)
    return shuffled[np.argsort(-d[shuffled], kind="stable")]


def top_nodes(dist: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The top 10 % of the nodes by mass (`ranked`)."""
    return ranked(dist, rng)[: top_count(received(dist).size)]


def compared_sets(dist: np.ndarray, rng: np.random.Generator, prior: np.ndarray | None = None) -> list[np.ndarray]:
    """The node sets a deletion or sufficiency test compares: the map's top 10 %, RANDOM_DRAWS sets of as many random
    nodes, and with a `prior` its top 10 %."""
    d = received(dist)
    sets = [top_nodes(d, rng)] + [rng.choice(d.size, size=top_count(d.size), replace=False) for _ in range(RANDOM_DRAWS)]
    return sets + ([top_nodes(prior, rng)] if prior is not None else [])


@torch.no_grad()
def decisions_with(net: torch.nn.Module, state: np.ndarray, gone: list[np.ndarray], grid_hw, count=None) -> np.ndarray:
    """(len(gone),) the greedy action on `state` with the image regions of each set of nodes read as no return."""
    q, _ = net(torch.from_numpy(masked_states(state, gone, grid_hw, count)).to(next(net.parameters()).device))
    return q.argmax(dim=1).cpu().numpy()
