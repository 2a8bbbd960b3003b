"""The state: the last N depth frames, restarted at every episode start."""

from __future__ import annotations

from collections import deque

import numpy as np


def fit_to_network(depth_m: np.ndarray, height: int, width: int) -> np.ndarray:
    """A frame at the network's input size, never inventing depths between edges: a side that shrinks keeps
    the nearest depth of each cell (a thin pole survives a real camera's 848 px going to 64), a side that
    grows repeats the nearest pixel. NaN (no reading) loses to any reading in its cell."""
    if depth_m.shape == (height, width):
        return depth_m
    out = np.asarray(depth_m, dtype=np.float32)
    for axis, size in ((0, height), (1, width)):
        n = out.shape[axis]
        if size < n:  # nearest depth per cell: cells [floor(i n / size), floor((i + 1) n / size))
            starts = (np.arange(size) * n) // size
            with np.errstate(invalid="ignore"):
                out = np.fmin.reduceat(out, starts, axis=axis)
        elif size > n:
            out = np.take(out, (np.arange(size) * n) // size, axis=axis)
    return np.ascontiguousarray(out)


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

    @property
    def empty(self) -> bool:
        return not self._buf
