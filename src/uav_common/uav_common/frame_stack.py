"""The state: the last N depth frames, restarted at every episode start, and the mapping of any depth
camera's frame onto the network's input."""

from __future__ import annotations

import dataclasses
import math
from collections import deque

import numpy as np


@dataclasses.dataclass(frozen=True)
class CameraView:
    """Where the network's input cells lie in a camera's pixels: `edges_x` (width + 1) and `edges_y`
    (height + 1) are the camera pixel coordinates of the cells' borders. Cells outside the camera's
    image read "no return" (+Inf): the network sees the field of view it was trained with, padded."""

    edges_x: np.ndarray
    edges_y: np.ndarray
    coverage: float  # the share of the network's cells the camera sees
    one_to_one: bool = False  # cell i is pixel i on both axes (the simulator's own camera): nothing to map

    @staticmethod
    def from_intrinsics(
        fx: float, fy: float, cx: float, cy: float, width: int, height: int, trained_hfov_deg: float, out_h: int, out_w: int
    ) -> CameraView:
        """The network's square-pixel pinhole window of `trained_hfov_deg` (as sim_node renders it), seen
        through a camera with focal lengths fx, fy and principal point cx, cy (px); ValueError if unusable."""
        if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0 or width <= 0 or height <= 0:
            raise ValueError(f"camera intrinsics unusable: fx={fx} fy={fy} cx={cx} cy={cy} size {width}x{height}")
        f_net = (out_w / 2.0) / math.tan(math.radians(trained_hfov_deg) / 2.0)
        # A pixel's centre is at its index + 0.5 (CameraInfo's cx is in the same convention as sim_node's w/2).
        ex = cx + fx * (np.arange(out_w + 1) - out_w / 2.0) / f_net
        ey = cy + fy * (np.arange(out_h + 1) - out_h / 2.0) / f_net
        seen_x = np.clip(np.minimum(ex[1:], width) - np.maximum(ex[:-1], 0), 0, None) / np.diff(ex)
        seen_y = np.clip(np.minimum(ey[1:], height) - np.maximum(ey[:-1], 0), 0, None) / np.diff(ey)
        one_to_one = (width, height) == (out_w, out_h) and all(
            np.allclose(e, np.arange(len(e)), rtol=0.0, atol=1e-6) for e in (ex, ey)
        )
        return CameraView(ex, ey, float(seen_x.mean() * seen_y.mean()), one_to_one)

    @staticmethod
    def stretch(height: int, width: int, out_h: int, out_w: int) -> CameraView:
        """The whole frame stretched onto the input (no intrinsics known)."""
        return CameraView(np.arange(out_w + 1) * width / out_w, np.arange(out_h + 1) * height / out_h, 1.0)


def _fit_axis(a: np.ndarray, axis: int, edges: np.ndarray) -> np.ndarray:
    n, size = a.shape[axis], len(edges) - 1
    first = np.floor(edges[:-1] + 1e-6)  # a border on a pixel's edge, up to rounding, starts there
    inside = (edges[1:] > 0) & (first < n)
    if not inside.any():
        shape = list(a.shape)
        shape[axis] = size
        return np.full(shape, np.inf, dtype=np.float32)
    idx = np.flatnonzero(inside)
    starts = np.clip(first[idx], 0, n - 1).astype(np.intp)
    end = int(np.clip(np.ceil(edges[idx[-1] + 1]), starts[-1] + 1, n))
    part = np.take(a, np.arange(end), axis=axis)
    # Cells [start_i, start_i+1): the nearest depth of each wins; a cell narrower than a pixel repeats it.
    with np.errstate(invalid="ignore"):
        pooled = np.fmin.reduceat(part, starts, axis=axis)
    if len(idx) == size:
        return pooled
    shape = list(a.shape)
    shape[axis] = size
    out = np.full(shape, np.inf, dtype=np.float32)
    sl = [slice(None)] * a.ndim
    sl[axis] = idx
    out[tuple(sl)] = pooled
    return out


def fit_to_network(depth_m: np.ndarray, height: int, width: int, view: CameraView | None = None) -> np.ndarray:
    """A frame at the network's input size, never inventing depths between edges: a side that shrinks keeps
    the nearest depth of each cell (a thin pole survives a real camera's 848 px going to 64), a side that
    grows repeats the nearest pixel. NaN (no reading) loses to any reading in its cell. With a `view`
    (CameraInfo and the trained field of view) the frame is cropped or padded with +Inf (no return) to the
    field of view the weights were trained with; without one the whole frame fills the input."""
    if depth_m.shape == (height, width) and (view is None or view.one_to_one):
        return depth_m  # the per-step case in the simulator: no copy, no pooling
    if view is None:
        view = CameraView.stretch(depth_m.shape[0], depth_m.shape[1], height, width)
    out = np.asarray(depth_m, dtype=np.float32)
    out = _fit_axis(out, 0, view.edges_y)
    out = _fit_axis(out, 1, view.edges_x)
    return np.ascontiguousarray(out)


def node_slices(grid_hw: tuple[int, int], image_hw: tuple[int, int]) -> list[tuple[slice, slice]]:
    """The image region each node sees (row-major), the grid laid evenly over the image."""
    gh, gw = grid_hw
    h, w = image_hw
    return [(slice(r * h // gh, (r + 1) * h // gh), slice(c * w // gw, (c + 1) * w // gw)) for r in range(gh) for c in range(gw)]


def node_shares(mask: np.ndarray, grid_hw: tuple[int, int]) -> np.ndarray:
    """(nodes,) float32: the share of each node's image region (node_slices) that the bool image `mask` covers."""
    m = np.asarray(mask, dtype=bool)
    return np.array([m[rs, cs].mean() for rs, cs in node_slices(grid_hw, m.shape)], dtype=np.float32)


class NetworkInput:
    """Frames of one camera onto the network's input: with `set_camera` (CameraInfo's intrinsics and the
    field of view the weights were trained with) cropped or padded to that view, else stretched whole.
    Frames binned below the CameraInfo's size are mapped with its intrinsics scaled to theirs."""

    def __init__(self, height: int, width: int):
        self.hw = (height, width)
        self.camera = None  # ((fx, fy, cx, cy, width, height), trained hfov in deg)
        self.view: CameraView | None = None  # the latest frame's
        self._key = None

    def set_camera(self, intrinsics: tuple[float, float, float, float, int, int] | None, trained_hfov_deg: float) -> None:
        self.camera = (tuple(intrinsics), float(trained_hfov_deg)) if intrinsics is not None else None

    def __call__(self, depth_m: np.ndarray) -> np.ndarray:
        if self.camera is None:
            return fit_to_network(depth_m, *self.hw)
        key = (self.camera, depth_m.shape, self.hw)
        if key != self._key:
            (fx, fy, cx, cy, w, h), hfov = self.camera
            sx, sy = depth_m.shape[1] / w, depth_m.shape[0] / h
            self.view = CameraView.from_intrinsics(
                fx * sx, fy * sy, cx * sx, cy * sy, depth_m.shape[1], depth_m.shape[0], hfov, *self.hw
            )
            self._key = key
        return fit_to_network(depth_m, *self.hw, self.view)

    def mask(self, mask: np.ndarray) -> np.ndarray:
        """A camera-sized bool mask on the network's input, mapped as the frames are: an input pixel is in it when one
        of the camera pixels it min-pools is (drawn as a near depth among no returns)."""
        return np.isfinite(self(np.where(mask, np.float32(1.0), np.float32(np.inf))))


class FrameStack:
    def __init__(self, frames: int = 5):
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        self.frames = frames
        self._buf: deque[np.ndarray] = deque(maxlen=frames)

    def reset(self, first: np.ndarray) -> np.ndarray:
        """Start an episode: the stack is the first frame repeated (as DQN does at reset)."""
        self._buf.clear()
        for _ in range(self.frames):
            self._buf.append(first)
        return self.state()

    def push(self, frame: np.ndarray) -> np.ndarray:
        if not self._buf:
            return self.reset(frame)
        if frame.shape != self._buf[-1].shape:
            raise ValueError(f"frame shape {frame.shape} differs from the stack's {self._buf[-1].shape}")
        self._buf.append(frame)
        return self.state()

    def state(self) -> np.ndarray:
        """(frames, H, W) float32, oldest first."""
        return np.stack(self._buf, axis=0).astype(np.float32, copy=False)

    def restore(self, state: np.ndarray) -> None:
        """Carry on from a state (frames, H, W), oldest first, e.g. one a SampledStack built."""
        if len(state) != self.frames:
            raise ValueError(f"a state of {len(state)} frames for a stack of {self.frames}")
        self._buf.clear()
        self._buf.extend(state)

    @property
    def empty(self) -> bool:
        return not self._buf


class SampledStack:
    """The state from a stream of any rate: the newest frame and those nearest to 1, 2, ... step periods
    before it, so that the stack spans what the weights were trained on (one frame per step) whatever the
    camera's rate. Before the stream reaches back far enough, the oldest frame stands in (as at an
    episode's start). Stamps going back restart it (`add` returns False)."""

    def __init__(self, frames: int, period_s: float):
        if frames < 1 or not period_s > 0:
            raise ValueError(f"need frames >= 1 and period_s > 0, got {frames}, {period_s}")
        self.frames, self.period_s = frames, period_s
        self._times: deque[float] = deque()
        self._frames: deque[np.ndarray] = deque()

    def add(self, t_s: float, frame: np.ndarray) -> bool:
        """Keep a frame taken at t_s; False (and a fresh start) when t_s is before the newest frame's."""
        restarted = bool(self._times) and t_s < self._times[-1]
        if restarted:
            self.clear()
        self._times.append(t_s)
        self._frames.append(frame)
        horizon = t_s - self.period_s * self.frames  # one period of slack beyond the oldest sample
        while len(self._times) > 1 and self._times[1] <= horizon:
            self._times.popleft()
            self._frames.popleft()
        return not restarted

    def clear(self) -> None:
        self._times.clear()
        self._frames.clear()

    @property
    def empty(self) -> bool:
        return not self._times

    @property
    def newest_s(self) -> float | None:
        return self._times[-1] if self._times else None

    def state(self) -> np.ndarray:
        """(frames, H, W) float32, oldest first."""
        times = np.fromiter(self._times, dtype=np.float64, count=len(self._times))
        wanted = times[-1] - self.period_s * np.arange(self.frames - 1, -1, -1)
        picks = np.abs(times[None, :] - wanted[:, None]).argmin(axis=1)
        return np.stack([self._frames[i] for i in picks], axis=0).astype(np.float32, copy=False)
