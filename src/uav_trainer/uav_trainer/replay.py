"""Replay memory that keeps each depth frame once; 5-frame stacks are rebuilt at sample time.

Slot i holds frame i, whether it starts an episode (or a new chain after a gap), and the
transition that left it: action, reward, done, and whether that transition exists. A stack
for slot i is frames i-N+1..i, where every frame before the latest episode start inside the
window is replaced by that start frame - exactly what the policy's FrameStack does at reset.
The next state of transition i is the stack at slot i+1; `done` masks it after a collision.

With `local_map`, slot i also keeps the local map of frame i (bits packed), appended to a stack as its last channel.

The memory is journaled, not saved whole: `segment(since)` holds the slots written since write `since`
(each checkpoint writes one, a few MiB), and `load_segments` rebuilds the memory from them as it was after
a given write, the slots where they were. So a resume after a stop or a crash learns on at once.

Several actors' steps interleave: `LanedReplay` keeps each actor's chain in a lane of its own (a
ReplayMemory with an equal share of the capacity), so a transition's frames stay neighbours.
"""

from __future__ import annotations

import math

import numpy as np


class ReplayMemory:
    def __init__(
        self,
        capacity: int,
        frame_shape: tuple[int, int],
        frames: int = 5,
        seed: int = 0,
        reason_nodes: int = 0,
        local_map: bool = False,
    ):
        if capacity < frames + 2:
            raise ValueError(f"capacity must be at least frames + 2 = {frames + 2}, got {capacity}")
        self.capacity, self.frames = capacity, frames
        self.frame = np.zeros((capacity, *frame_shape), dtype=np.float16)  # metres; inf survives float16
        self.start = np.zeros(capacity, dtype=bool)
        self.action = np.zeros(capacity, dtype=np.int64)
        self.reward = np.zeros(capacity, dtype=np.float32)
        self.done = np.zeros(capacity, dtype=bool)
        self.has_transition = np.zeros(capacity, dtype=bool)
        self.teacher = np.full(capacity, -1, dtype=np.int64)  # the teacher's action for the frame (-1: none)
        # With `reason_nodes`: the share of each attention cell the teacher's reason covers in the frame (0: none).
        self.reason = np.zeros((capacity, reason_nodes), dtype=np.float16)
        # With `local_map`: the frame's local map grid (frame_shape, 0/1), bits packed (512 bytes a 64x64 map).
        self.map_shape = tuple(frame_shape) if local_map else None
        self.map = np.zeros((capacity, (math.prod(frame_shape) + 7) // 8 if local_map else 0), dtype=np.uint8)
        self.writes = 0  # frames written since the memory began (slot = write % capacity)
        self.rng = np.random.default_rng(seed)

    @property
    def cursor(self) -> int:
        """The next slot to write."""
        return self.writes % self.capacity

    @property
    def count(self) -> int:
        """Frames stored (at most the capacity)."""
        return min(self.writes, self.capacity)

    # Arrays journaled per slot, with their dtypes; a segment adds `span` and `geometry`.
    SLOT_ARRAYS = {
        "frame": np.float16,
        "start": np.bool_,
        "action": np.int64,
        "reward": np.float32,
        "done": np.bool_,
        "has_transition": np.bool_,
        "teacher": np.int64,
        "reason": np.float16,
        "map": np.uint8,
    }

    def _geometry(self) -> tuple[int, int, int, int]:
        return (self.capacity, self.frames, *self.frame.shape[1:])

    def segment(self, since: int) -> dict[str, np.ndarray]:
        """Copies of the slots written from write `since` on (and of the one before: the frame after it
        completed its transition), as arrays for safetensors; `span` is [first write, end)."""
        first = max(since - 1, self.writes - self.count, 0)
        slots = np.arange(first, self.writes) % self.capacity
        out = {name: getattr(self, name)[slots] for name in self.SLOT_ARRAYS}
        out["span"] = np.array([first, self.writes], dtype=np.int64)
        out["geometry"] = np.array(self._geometry(), dtype=np.int64)
        return out

    def load_segments(self, segments: list[dict[str, np.ndarray]], upto: int, n_actions: int) -> None:
        """Rebuild the memory from journal segments as it was after write `upto` (later writes are left
        out; the newest frame's transition was not known then). Raises ValueError, leaving this memory
        unchanged, for a segment that does not fit this memory (another capacity, frame size or stack
        depth), holds values no run could have written (actions outside [0, n_actions), NaN or negative
        depths, ...), or a journal with a gap."""
        # A journal written before teacher labels or reasons has none (the caller's segments are left as they are).
        segments = [
            seg if "teacher" in seg or "action" not in seg else {**seg, "teacher": np.full(seg["action"].shape, -1, np.int64)}
            for seg in segments
        ]
        segments = [
            seg
            if "reason" in seg or "action" not in seg
            else {**seg, "reason": np.zeros((len(seg["action"]), self.reason.shape[1]), np.float16)}
            for seg in segments
        ]
        segments = [
            seg if "map" in seg or "action" not in seg else {**seg, "map": np.zeros((len(seg["action"]), 0), np.uint8)}
            for seg in segments
        ]
        spans = []
        for seg in segments:
            span, geometry = seg.get("span"), seg.get("geometry")
            if span is None or span.dtype != np.int64 or span.shape != (2,) or not 0 <= span[0] <= span[1]:
                raise ValueError("replay segment has no valid span")
            ok = geometry is not None and geometry.dtype == np.int64 and geometry.shape == (4,)
            theirs = tuple(int(g) for g in geometry) if ok else None
            if theirs != self._geometry():
                mine = self._geometry()
                raise ValueError(f"replay segment is for capacity, frames, height, width {theirs}, this memory {mine}")
            self._check(seg, int(span[1] - span[0]), n_actions)
            spans.append((int(span[0]), int(span[1])))
        order = sorted(range(len(segments)), key=lambda i: spans[i])
        end = spans[order[0]][0] if order else 0
        for i in order:
            if spans[i][0] > end:
                raise ValueError(f"the replay journal misses writes {end} to {spans[i][0]}")
            end = max(end, spans[i][1])
        end = min(end, upto)
        begin = spans[order[0]][0] if order else 0
        if begin > 0 and end - begin < self.capacity:
            raise ValueError(f"the replay journal starts at write {begin}, not at 0 or a full memory before {end}")
        fresh = {name: np.zeros_like(getattr(self, name)) for name in self.SLOT_ARRAYS}
        for i in order:
            a, b = spans[i][0], min(spans[i][1], end)
            if b <= a:
                continue
            slots = np.arange(a, b) % self.capacity
            for name in self.SLOT_ARRAYS:
                fresh[name][slots] = segments[i][name][: b - a]
        if end > 0:
            newest = (end - 1) % self.capacity
            fresh["has_transition"][newest] = False
            fresh["action"][newest], fresh["reward"][newest], fresh["done"][newest] = 0, 0.0, False
            fresh["teacher"][newest], fresh["reason"][newest] = -1, 0.0
        for name, a in fresh.items():
            setattr(self, name, a)
        self.writes = end

    def _check(self, arrays: dict[str, np.ndarray], n: int, n_actions: int) -> None:
        for name, dtype in self.SLOT_ARRAYS.items():
            a = arrays.get(name)
            want = (n, *getattr(self, name).shape[1:])
            if a is None or a.dtype != dtype or a.shape != want:
                raise ValueError(f"replay segment array {name!r} missing or not {np.dtype(dtype).name} of shape {want}")
        if np.isnan(arrays["frame"]).any() or (arrays["frame"] < 0).any():
            raise ValueError("replay segment has NaN or negative depths")
        if ((arrays["action"] < 0) | (arrays["action"] >= n_actions)).any():
            raise ValueError(f"replay segment has actions outside [0, {n_actions})")
        if ((arrays["teacher"] < -1) | (arrays["teacher"] >= n_actions)).any():
            raise ValueError(f"replay segment has teacher actions outside [-1, {n_actions})")
        if not np.isfinite(arrays["reason"]).all() or ((arrays["reason"] < 0) | (arrays["reason"] > 1)).any():
            raise ValueError("replay segment has reason shares outside [0, 1]")
        if not np.isfinite(arrays["reward"]).all():
            raise ValueError("replay segment has non-finite rewards")

    def __len__(self) -> int:
        """Number of sampleable transitions."""
        return int(self._valid().sum())

    def _write_frame(self, depth: np.ndarray, start: bool, grid: np.ndarray | None) -> None:
        i = self.cursor
        if self.map_shape is not None:
            if grid is None or np.shape(grid) != self.map_shape:
                raise ValueError(f"this memory keeps a local map of {self.map_shape} with every frame, got {np.shape(grid)}")
            self.map[i] = np.packbits(np.asarray(grid).ravel() > 0.5)
        with np.errstate(over="ignore"):  # +Inf stays +Inf in float16
            self.frame[i] = np.nan_to_num(depth, nan=np.inf).astype(np.float16)
        self.start[i] = start
        self.has_transition[i] = False
        self.teacher[i] = -1
        self.reason[i] = 0.0
        self.writes += 1

    def add_first(self, depth: np.ndarray, grid: np.ndarray | None = None) -> None:
        """A frame that starts an episode or a new chain (no transition leads into it); `grid`: its local map."""
        self._write_frame(depth, True, grid)

    def add_transition(
        self,
        action: int,
        reward: float,
        done: bool,
        next_depth: np.ndarray,
        teacher: int = -1,
        reason=None,
        grid: np.ndarray | None = None,
    ) -> None:
        """Complete the transition from the newest frame; `next_depth` is the frame it led to (`grid` its local map),
        `teacher` the teacher's action for the newest frame (-1: none), `reason` the share of each cell its reason
        covers (None: none).

        After a collision (done=True) the next frame is the first of a new episode.
        """
        if self.count == 0:
            raise RuntimeError("add_first must come before add_transition")
        i = (self.cursor - 1) % self.capacity
        self.action[i], self.reward[i], self.done[i], self.teacher[i] = action, reward, done, teacher
        if reason is not None:
            self.reason[i] = reason
        self.has_transition[i] = True
        self._write_frame(next_depth, done, grid)

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
        states = self.frame[idx].astype(np.float32)
        if self.map_shape is None:
            return states
        n = math.prod(self.map_shape)
        grids = np.unpackbits(self.map[slots], axis=1, count=n).reshape(len(slots), 1, *self.map_shape)
        return np.concatenate([states, grids.astype(np.float32)], axis=1)

    def sample(self, batch: int, valid: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """A batch of transitions drawn uniformly (the paper's one-step Q-learning); `valid`: the sampleable
        slots when the caller has them already."""
        valid = np.flatnonzero(self._valid()) if valid is None else valid
        if valid.size == 0:
            raise RuntimeError("the replay memory holds no complete transition yet")
        picks = self.rng.choice(valid, size=batch, replace=valid.size < batch)
        out = {"reason": self.reason[picks].astype(np.float32)} if self.reason.shape[1] else {}
        return out | {
            "state": self.stacks(picks),
            "action": self.action[picks],
            "teacher": self.teacher[picks],
            "index": picks,
            "reward": self.reward[picks],
            "done": self.done[picks].astype(np.float32),
            "next_state": self.stacks((picks + 1) % self.capacity),
        }


class LanedReplay:
    """One replay memory for several actors: lane i (a ReplayMemory of capacity // lanes frames) holds actor
    i's chain, and a batch is drawn uniformly over the transitions of all lanes. Not journaled: a run with
    several actors that resumes refills its memory."""

    def __init__(self, lanes: int, capacity: int, frame_shape: tuple[int, int], frames: int = 5, seed: int = 0, *slots):
        """`slots`: each lane's ReplayMemory reason_nodes and local_map."""
        if lanes < 2:
            raise ValueError(f"a laned memory needs at least 2 lanes, got {lanes} (one actor: ReplayMemory)")
        share = capacity // lanes
        self.lanes = [ReplayMemory(share, frame_shape, frames, seed + 1 + i, *slots) for i in range(lanes)]
        self.capacity = share * lanes
        self.rng = np.random.default_rng(seed)  # which lane each sample comes from

    @property
    def writes(self) -> int:
        return sum(lane.writes for lane in self.lanes)

    def __len__(self) -> int:
        return sum(len(lane) for lane in self.lanes)

    def sample(self, batch: int) -> dict[str, np.ndarray]:
        """A batch drawn uniformly over all lanes' transitions (each lane's share by its count)."""
        valid = [np.flatnonzero(lane._valid()) for lane in self.lanes]
        sizes = np.array([v.size for v in valid], dtype=np.float64)
        if sizes.sum() == 0:
            raise RuntimeError("the replay memory holds no complete transition yet")
        per_lane = self.rng.multinomial(batch, sizes / sizes.sum())
        parts = [lane.sample(int(k), v) for lane, v, k in zip(self.lanes, valid, per_lane, strict=True) if k]
        return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
