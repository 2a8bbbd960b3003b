"""Turning attention weights into pictures: a per-pixel map and an RGB overlay."""

from __future__ import annotations

import cv2
import numpy as np


def attention_received(weights: np.ndarray) -> np.ndarray:
    """How much attention each node receives: (heads, n, n) -> (n,), averaged over heads and queries."""
    if weights.ndim != 3 or weights.shape[1] != weights.shape[2]:
        raise ValueError(f"attention weights must be (heads, nodes, nodes), got {weights.shape}")
    return weights.mean(axis=(0, 1))


def attention_map(weights: np.ndarray, grid_hw: tuple[int, int], image_hw: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 in [0, 1]: the attention each image region receives, max-normalised.

    Node i covers grid cell (i // grid_w, i % grid_w); each cell is upsampled to the image
    region it sees (nearest neighbour: no attention is smeared onto cells that got none).
    """
    received = attention_received(weights).reshape(grid_hw).astype(np.float32)
    lo, hi = float(received.min()), float(received.max())
    norm = (received - lo) / (hi - lo) if hi > lo else np.zeros_like(received)
    h, w = image_hw
    return cv2.resize(norm, (w, h), interpolation=cv2.INTER_NEAREST)


def colourise_depth(depth_m: np.ndarray, max_range_m: float) -> np.ndarray:
    """(H, W, 3) uint8 grey image: near = bright, far or out of range = dark."""
    d = np.nan_to_num(depth_m.astype(np.float32), nan=max_range_m, posinf=max_range_m, neginf=0.0)
    grey = (255.0 * (1.0 - np.clip(d / max_range_m, 0.0, 1.0))).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def overlay(depth_m: np.ndarray, att_map: np.ndarray, max_range_m: float, strength: float = 0.7) -> np.ndarray:
    """rgb8 picture: the depth in grey with the attention in green on top (as in the paper)."""
    base = colourise_depth(depth_m, max_range_m).astype(np.float32)
    a = np.clip(att_map, 0.0, 1.0)[:, :, None] * strength
    green = np.zeros_like(base)
    green[:, :, 1] = 255.0
    return (base * (1.0 - a) + green * a).astype(np.uint8)
