"""Replay memory that keeps each depth frame once; 5-frame stacks are rebuilt at sample time.

Slot i holds frame i, whether it starts an episode (or a new chain after a gap), and the
transition that left it: action, reward, done, and whether that transition exists. A stack
for slot i is frames i-N+1..i, where every frame before the latest episode start inside the
window is replaced by that start frame - exactly what the policy's FrameStack does at reset.
The next state of transition i is the stack at slot i+1; `done` masks it after a collision.

`state()` and `load_state()` carry the memory across a stop and resume (trainer checkpoints keep it
in replay.safetensors); only the filled slots are written.
"""

from __future__ import annotations

import numpy as np


class ReplayMemory:
    def __init__(self, capacity: int, frame_shape: tuple[int, int], frames: int = 5, seed: int = 0):
        if capacity < frames + 2:
            raise ValueError(f"capacity must be at least frames + 2 = {frames + 2}, got {capacity}")
        self.capacity, self.frames = capacity, frames
        self.frame = np.zeros((capacity, *frame_shape), dtype=np.float16)  # metres; inf survives float16
        self.start = np.zeros(capacity, dtype=bool)
        self.action = np.zeros(capacity, dtype=np.int64)
        self.reward = np.zeros(capacity, dtype=np.float32)
        self.done = np.zeros(capacity, dtype=bool)
        self.has_transition = np.zeros(capacity, dtype=bool)
        self.cursor = 0  # next slot to write
        self.count = 0  # frames stored (<= capacity)
        self.transitions_added = 0
        self.rng = np.random.default_rng(seed)

    # Arrays saved per slot, with their dtypes; `state()` adds `header`. (Memories saved with the
    # prioritized replay that was retired also hold `priority`, `writes` and `max_priority`: ignored.)
    SLOT_ARRAYS = {
        "frame": np.float16,
        "start": np.bool_,
        "action": np.int64,
        "reward": np.float32,
        "done": np.bool_,
        "has_transition": np.bool_,
    }

    def state(self) -> dict[str, np.ndarray]:
        """Copies of the filled slots and the counters, as arrays (for safetensors)."""
        n = self.count
        out = {name: getattr(self, name)[:n].copy() for name in self.SLOT_ARRAYS}
        out["header"] = np.array(
            [self.capacity, self.frames, *self.frame.shape[1:], self.cursor, self.count, self.transitions_added], dtype=np.int64
        )
        return out

    def load_state(self, state: dict[str, np.ndarray], n_actions: int) -> None:
        """Restore what `state()` returned. Raises ValueError, leaving this memory unchanged, when the
        arrays do not fit this memory (another capacity, frame size or stack depth) or hold values
        no run could have written (actions outside [0, n_actions), NaN or negative depths, ...)."""
        header = state.get("header")
        if header is None or header.dtype != np.int64 or header.shape != (7,):
            raise ValueError("replay state has no valid header")
        capacity, frames, h, w, cursor, count, added = (int(v) for v in header)
        mine = (self.capacity, self.frames, *self.frame.shape[1:])
        if (capacity, frames, h, w) != mine:
            theirs = (capacity, frames, h, w)
            raise ValueError(f"replay state is for capacity, frames, height, width {theirs}, this memory {mine}")
        if not 0 <= count <= capacity or not 0 <= cursor < capacity or (count < capacity and cursor != count) or added < 0:
            raise ValueError(f"replay state has inconsistent counters: cursor {cursor}, count {count}, added {added}")
        arrays = {}
        for name, dtype in self.SLOT_ARRAYS.items():
            a = state.get(name)
            want = (count, *self.frame.shape[1:]) if name == "frame" else (count,)
            if a is None or a.dtype != dtype or a.shape != want:
                raise ValueError(f"replay state array {name!r} missing or not {np.dtype(dtype).name} of shape {want}")
            arrays[name] = a
        if np.isnan(arrays["frame"]).any() or (arrays["frame"] < 0).any():
            raise ValueError("replay state has NaN or negative depths")
        if ((arrays["action"] < 0) | (arrays["action"] >= n_actions)).any():
            raise ValueError(f"replay state has actions outside [0, {n_actions})")
        if not np.isfinite(arrays["reward"]).all():
            raise ValueError("replay state has non-finite rewards")
        for name, a in arrays.items():
            target = getattr(self, name)
            target[:count] = a
            target[count:] = 0
        self.cursor, self.count, self.transitions_added = cursor, count, added

    def __len__(self) -> int:
        """Number of sampleable transitions."""
        return int(self._valid().sum())

    def _write_frame(self, depth: np.ndarray, start: bool) -> None:
        i = self.cursor
        with np.errstate(over="ignore"):  # +Inf stays +Inf in float16
            self.frame[i] = np.nan_to_num(depth, nan=np.inf).astype(np.float16)
        self.start[i] = start
        self.has_transition[i] = False
        self.cursor = (i + 1) % self.capacity
        self.count = min(self.count + 1, self.capacity)

    def add_first(self, depth: np.ndarray) -> None:
        """A frame that starts an episode or a new chain (no transition leads into it)."""
        self._write_frame(depth, start=True)

    def add_transition(self, action: int, reward: float, done: bool, next_depth: np.ndarray) -> None:
        """Complete the transition from the newest frame; `next_depth` is the frame it led to.

        After a collision (done=True) the next frame is the first of a new episode.
        """
        if self.count == 0:
            raise RuntimeError("add_first must come before add_transition")
        i = (self.cursor - 1) % self.capacity
        self.action[i], self.reward[i], self.done[i] = action, reward, done
        self.has_transition[i] = True
        self._write_frame(next_depth, start=done)
        self.transitions_added += 1

    def _valid(self) -> np.ndarray:
        """Slots whose transition can be sampled: complete, next frame stored, full history kept."""
        valid = self.has_transition.copy()
        newest = (self.cursor - 1) % self.capacity
        valid[newest] = False  # its next frame is not stored yet
        if self.count == self.capacity:
            # The oldest frames' histories were overwritten: only keep them if an episode start
            # inside their window makes the overwritten part irrelevant.
            for k in range(self.frames - 1):
                j = (self.cursor + k) % self.capacity
                window = [(j - m) % self.capacity for m in range(k + 1)]
                if not any(self.start[w] for w in window):
                    valid[j] = False
        else:
            valid[self.count :] = False
        return valid

    def stack(self, i: int) -> np.ndarray:
        """(frames, H, W) float32 state ending at slot i."""
        return self.stacks(np.array([i]))[0]

    def stacks(self, slots: np.ndarray) -> np.ndarray:
        """(len(slots), frames, H, W) float32 states ending at each slot, gathered in one indexing."""
        slots = np.asarray(slots, dtype=np.int64)
        idx = (slots[:, None] - np.arange(self.frames - 1, -1, -1)) % self.capacity  # oldest first
        # Within each window, at the latest episode start (the oldest position does not count: nothing
        # is older) every older frame is replaced by that start frame.
        starts = self.start[idx]
        starts[:, 0] = False
        latest = self.frames - 1 - np.argmax(starts[:, ::-1], axis=1)
        older = starts.any(axis=1)[:, None] & (np.arange(self.frames)[None, :] < latest[:, None])
        idx = np.where(older, idx[np.arange(len(slots)), latest][:, None], idx)
        return self.frame[idx].astype(np.float32)

    def sample(self, batch: int) -> dict[str, np.ndarray]:
        """A batch of transitions drawn uniformly (the paper's one-step Q-learning)."""
        valid = np.flatnonzero(self._valid())
        if valid.size == 0:
            raise RuntimeError("the replay memory holds no complete transition yet")
        picks = self.rng.choice(valid, size=batch, replace=valid.size < batch)
        return {
            "state": self.stacks(picks),
            "action": self.action[picks],
            "index": picks,
            "reward": self.reward[picks],
            "done": self.done[picks].astype(np.float32),
            "next_state": self.stacks((picks + 1) % self.capacity),
        }
