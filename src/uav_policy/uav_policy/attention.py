"""Turning an explanation (SAM's attention, the CNN's saliency) into pictures on an absolute scale: a per-pixel
map of each region's mass relative to its uniform share, and an rgb overlay with its legend; for a network with the
local map, the top-down picture of what it weighs there (`map_overlay`)."""

from __future__ import annotations

import cv2
import numpy as np

from .masking import received

SCALE_MAX = 4.0  # the overlay's full colour: four times a uniform share
OVERLAY_MIN_PX = 256  # the overlay's shorter side is upscaled to at least this


def attention_map(weights: np.ndarray, grid_hw: tuple[int, int], image_hw: tuple[int, int], view=None) -> np.ndarray:
    """(H, W) float32: the mass each image region receives relative to a uniform share (1 = as if uniform, 0 =
    none, 4 = four times its share), the same scale on every frame. `weights` (..., nodes): SAM's attention
    (heads, queries, nodes) or a saliency map (nodes,).

    Node i covers grid cell (i // grid_w, i % grid_w) of the network's input; each cell is drawn on the image
    region it sees (nearest neighbour: no mass is smeared onto cells that got none). With `view` (the
    uav_common.frame_stack.CameraView a camera's frames were mapped through: the input cells' borders in the
    image's pixels) the cells land where they see the camera's image, a camera of another field of view or
    aspect included; camera pixels outside the trained view get 0. Without it the grid is stretched over the image.
    A network with the local map attends over the image's cells and the map's: the image's are drawn, as their share.
    """
    gh, gw = grid_hw
    dist = received(weights)
    if dist.size == 2 * gh * gw:  # a network with the local map: the image's cells are the first half
        dist = received(dist[: gh * gw])
    if dist.size != gh * gw:
        raise ValueError(f"{dist.size} nodes do not fill a {gh}x{gw} grid")
    rel = (dist * dist.size).reshape(grid_hw).astype(np.float32)
    h, w = image_hw
    if view is None or view.one_to_one:
        return cv2.resize(rel, (w, h), interpolation=cv2.INTER_NEAREST)
    out_w, out_h = len(view.edges_x) - 1, len(view.edges_y) - 1
    # The input cell each image pixel centre falls in (-1 or out_*: outside the trained view), then its grid cell.
    cx = np.searchsorted(view.edges_x, np.arange(w) + 0.5) - 1  # pixel centres: index + 0.5 (CameraView's convention)
    cy = np.searchsorted(view.edges_y, np.arange(h) + 0.5) - 1
    inside_x, inside_y = (cx >= 0) & (cx < out_w), (cy >= 0) & (cy < out_h)
    gx = np.clip(cx, 0, out_w - 1) * gw // out_w
    gy = np.clip(cy, 0, out_h - 1) * gh // out_h
    amap = rel[gy[:, None], gx[None, :]]
    return np.where(inside_y[:, None] & inside_x[None, :], amap, 0.0).astype(np.float32)


def colourise_depth(depth_m: np.ndarray, max_range_m: float) -> np.ndarray:
    """(H, W, 3) uint8 grey image: near = bright, far or out of range = dark."""
    d = np.nan_to_num(depth_m.astype(np.float32), nan=max_range_m, posinf=max_range_m, neginf=0.0)
    grey = (255.0 * (1.0 - np.clip(d / max_range_m, 0.0, 1.0))).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def strength(att_map: np.ndarray) -> np.ndarray:
    """The overlay's colour strength in [0, 1] on the absolute scale: 0 at or below a uniform share, 1 at SCALE_MAX
    times it (a log scale, so twice a uniform share is half-way)."""
    return np.clip(np.log(np.maximum(att_map, 1e-6)) / np.log(SCALE_MAX), 0.0, 1.0)


def overlay(depth_m: np.ndarray, att_map: np.ndarray, max_range_m: float, label: str = "", kind: str = "attention") -> np.ndarray:
    """rgb8 picture: the depth in grey with `kind` (attention or saliency) in green on top, upscaled so its shorter
    side is at least OVERLAY_MIN_PX, a legend bar of the absolute scale (x uniform share) and `label` (e.g. the
    chosen action and its Q lead over the next best) in a strip below."""
    base = colourise_depth(depth_m, max_range_m).astype(np.float32)
    a = strength(att_map)[:, :, None] * 0.8
    green = np.zeros_like(base)
    green[:, :, 1] = 255.0
    img = (base * (1.0 - a) + green * a).astype(np.uint8)
    h, w = img.shape[:2]
    k = max(1, -(-OVERLAY_MIN_PX // min(h, w)))
    img = cv2.resize(img, (w * k, h * k), interpolation=cv2.INTER_NEAREST)
    return np.concatenate([img, legend(img.shape[1], label, kind)], axis=0)


def legend(width: int, label: str, kind: str) -> np.ndarray:
    """A 40 px strip: `label` on top; below it a bar from a uniform share (no colour) to SCALE_MAX times it."""
    strip = np.full((40, width, 3), 32, np.uint8)
    font, white = cv2.FONT_HERSHEY_SIMPLEX, (255, 255, 255)
    cv2.putText(strip, label, (4, 14), font, 0.4, white, 1, cv2.LINE_AA)
    text = f"{kind} 1x..{SCALE_MAX:g}x uniform"
    x0, x1 = 4, max(width - 6 * len(text) - 8, 24)
    ramp = strength(SCALE_MAX ** np.linspace(0.0, 1.0, x1 - x0))[None, :, None] * 0.8
    green = np.zeros((1, x1 - x0, 3), np.float32)
    green[..., 1] = 255.0
    strip[24:34, x0:x1] = np.repeat((green * ramp).astype(np.uint8), 10, axis=0)
    cv2.putText(strip, text, (x1 + 4, 33), font, 0.35, white, 1, cv2.LINE_AA)
    return strip


def map_overlay(grid: np.ndarray, weights: np.ndarray, grid_hw: tuple[int, int], label: str = "") -> np.ndarray:
    """rgb8 top-down picture for a network with the local map: its egocentric grid (obstacle cells white, the vehicle
    a red mark at the bottom centre, looking up) with the attention on the map's cells (the second half of the nodes)
    in green on the overlay's absolute scale; the legend says the share of the attention the map gets."""
    gh, gw = grid_hw
    dist = received(weights)
    if dist.size != 2 * gh * gw:
        raise ValueError(f"{dist.size} nodes are not the {gh}x{gw} image cells and as many map cells")
    on_map = float(dist[gh * gw :].sum())
    rel = received(dist[gh * gw :]) * gh * gw
    h, w = grid.shape
    amap = cv2.resize(rel.reshape(gh, gw).astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
    base = np.where(np.asarray(grid)[:, :, None] > 0.5, 255.0, 40.0) * np.ones(3, np.float32)
    a = strength(amap)[:, :, None] * 0.8
    green = np.zeros_like(base)
    green[:, :, 1] = 255.0
    img = (base * (1.0 - a) + green * a).astype(np.uint8)
    k = max(1, -(-OVERLAY_MIN_PX // min(h, w)))
    img = cv2.resize(img, (w * k, h * k), interpolation=cv2.INTER_NEAREST)
    cx, cy = (w // 2) * k, (h - h // 4) * k  # the camera: a quarter of the grid lies behind it
    cv2.drawMarker(img, (cx, cy), (255, 0, 0), cv2.MARKER_TRIANGLE_UP, 3 * k, 2)
    text = f"{label}; " if label else ""
    return np.concatenate([img, legend(img.shape[1], f"{text}map {100 * on_map:.0f} % of the attention", "attention")])
