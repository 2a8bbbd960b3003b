"""Turning the three message streams into transitions, by exact stamp, never guessing.

A record is (depth frame k, step outcome k, action answering frame k), joined on the stamp
of frame k. Record k and observation k+1 (frame and outcome k+1) make the transition
(s_k, a_k, r_k, s_{k+1}, done_k) when their stamps are exactly one step apart; r_k and done_k
come from outcome k+1 (the outcome of the step that produced frame k+1). The transition is
stored as soon as observation k+1 is in, before the policy answers frame k+1: a trainer that
learns in lockstep (trainer_node) learns from it before the policy acts on
frame k+1, as the in-process loop does. Anything else - a gap, an action that matches no known
action, a malformed frame, stamps going back (a restarted simulator) - starts a new chain and is
counted. An outcome that says a new episode began without a collision (the simulator's time limit, or a reset)
stores no transition: the frame it comes with starts the next episode's chain.

`on_ready(stamp)` (optional) hears of each observation once nothing more will be stored before
the policy's answer to it: after its transition is stored, or at once when it cannot be chained.
An observation whose predecessor's answer has not arrived yet waits for it.

With `teacher`, an observation is also sim_node's `teacher_label` for the frame (the planner's action, its scores and
its reason, stamped as the frame): each stored transition carries the teacher's action for the frame it left (-1 for a
label that names no action of the table or scores another number of actions, counted), and `teacher_of(stamp)` gives
it for a frame about to be released. With `reason_grid` too, the label's reason (the pixels the planner's decision is about)
is mapped onto the network's input as the frames are: each transition carries the share of each cell of that grid it
covers in the frame it left (as the in-process loop computes it).

With `map_grid` (a network with the local map), an observation is also sim_node's `odom` of the frame's stamp: each
frame goes into a local map in stamp order (a new episode forgets) and is stored with its egocentric grid, as
uav_sim.stacked_sim.StackedSim maps the frames in process; the reason's share covers the map's cells too.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from uav_common import contract
from uav_common.actions import match_action
from uav_common.frame_stack import NetworkInput
from uav_common.local_map import LocalMap, PinholeCamera, camera_position

from .teacher import NO_LABEL, label_action, reason_shares


@dataclasses.dataclass
class _Prev:
    stamp: int
    action: int | None
    answered: bool = True  # False: the frame is stored, the policy's answer to it is not joined yet
    teacher: int = -1  # the teacher's action for the frame (-1: none)
    reason: np.ndarray | None = None  # with a reason grid: the share of each cell the teacher's reason covers


class TransitionAssembler:
    """Feed messages with `add(stream, msg)`; completed steps go to `sink.add_first/add_step/add_truncated`."""

    STREAMS = ("frame", "outcome", "action")

    def __init__(
        self,
        sink,
        actions,
        step_ns: int,
        net_hw: tuple[int, int],
        max_pending: int = 500,
        on_ready=None,
        teacher: bool = False,
        reason_grid: tuple[int, int] | None = None,
        map_grid: tuple[int, float] | None = None,
    ):
        self.sink, self.actions, self.step_ns, self.net_hw = sink, actions, step_ns, net_hw
        self.on_ready, self.reason_grid, self.map_grid = on_ready, reason_grid, map_grid
        self.map = LocalMap() if map_grid is not None else None
        self.camera: PinholeCamera | None = None  # the frames' intrinsics (the local map's)
        # What a step's simulator says.
        self.observation = ("frame", "outcome") + (("teacher",) if teacher else ())
        self.observation += ("odom",) if map_grid is not None else ()
        self.joiner = contract.StampJoiner(self.STREAMS + self.observation[2:], max_pending=max_pending)
        self.prev: _Prev | None = None
        self.early: tuple[int, bool] | None = None  # (stamp, frame usable) stored before its record completed
        self.released = -1  # the newest stamp handed to on_ready
        self.counts = {"chain_breaks": 0, "unmatched_actions": 0, "bad_frames": 0, "bad_teacher_labels": 0}
        self.counts |= {"bad_reasons": 0} if reason_grid else {}
        self.counts |= {"unmapped_frames": 0} if map_grid else {}
        self.to_input = NetworkInput(*net_hw)

    def set_camera(self, intrinsics, hfov_deg: float) -> None:
        """Frames go onto the network's input through the camera's intrinsics, as policy_node maps them (the
        trained field of view is the camera's own): a sensor preset's frames are padded to a square view."""
        self.to_input.set_camera(intrinsics, hfov_deg)
        if intrinsics is not None:
            fx, fy, cx, cy, width, height = intrinsics
            self.camera = PinholeCamera(width, height, fx, fy, cx, cy)

    def add(self, stream: str, msg) -> None:
        restarts = self.joiner.restarts
        joined = self.joiner.add(stream, contract.stamp_ns(msg.header.stamp), msg)
        if self.joiner.restarts != restarts:  # the simulator restarted: a new chain, released afresh
            self.prev, self.early, self.released = None, None, -1
            self.counts["chain_breaks"] += 1
        if joined is not None:
            self._record(joined)
        self._store_next()
        self._release()

    def _frame(self, slot: dict):
        """(the frame at the network's size, with the local map its local map's grid else None), or None (counted)
        when malformed. Called once per frame, in stamp order: the map takes it."""
        try:
            depth = contract.image_to_depth(slot["frame"])
            frame = self.to_input(depth)
        except ValueError:
            self.counts["bad_frames"] += 1
            return None
        if self.map is None:
            return frame, None
        if contract.outcome_new_episode(slot["outcome"]):
            self.map.reset()
        pose, camera = contract.odometry_pose(slot["odom"]), self.camera
        if pose is None or camera is None or (camera.height, camera.width) != depth.shape:
            self.counts["unmapped_frames"] += 1  # malformed odometry, or no depth/camera_info of the frame's size
            self.map.reset()
            return None
        x, y, z, yaw = pose
        self.map.insert(depth, camera, *camera_position(x, y, yaw), z, yaw)
        return frame, self.map.egocentric(*self.map_grid)

    def _action(self, rec: dict) -> int | None:
        tw = rec["action"].twist
        action = match_action(self.actions, tw.linear.x, tw.angular.z, self.step_ns / 1e9)
        if action is None:
            self.counts["unmatched_actions"] += 1
        return action

    def _teacher(self, slot: dict) -> int:
        """The teacher's action in an observation; -1 when none is given, or a malformed label (counted when stored)."""
        return label_action(slot["teacher"], len(self.actions)) if "teacher" in slot else NO_LABEL

    def _reason(self, slot: dict) -> np.ndarray | None:
        """The share of each reason_grid node that the teacher's reason covers on the network's input (None without a
        reason grid; no share for a mask that is malformed or not the frame's size, counted)."""
        if self.reason_grid is None:
            return None
        try:
            mask = contract.image_to_mask(slot["teacher"].reason)
            if mask.shape != (slot["frame"].height, slot["frame"].width):
                raise ValueError("not the frame's size")
        except ValueError:
            self.counts["bad_reasons"] += 1
            return np.zeros(self.reason_grid[0] * self.reason_grid[1] * (1 + (self.map is not None)), np.float32)
        return reason_shares(self.to_input.mask(mask), self.reason_grid, self.map, self.map_grid, mask)

    def teacher_of(self, stamp: int) -> int:
        """The teacher's action for the observation at `stamp` (-1: none): for its release."""
        slot = self.joiner.pending.get(stamp)
        if slot is not None and "teacher" in slot:
            return self._teacher(slot)
        return self.prev.teacher if self.prev is not None and self.prev.stamp == stamp else -1

    def _store(self, mapped, out) -> None:
        """The step from record self.prev to (frame, out), one step later (`mapped`: _frame's)."""
        frame, grid = mapped[0], ({"grid": mapped[1]} if self.map is not None else {})
        if contract.outcome_truncated(out):  # a new episode without a collision: nothing to learn
            self.sink.add_truncated(frame, **grid)
        else:
            collided = contract.outcome_collided(out)
            beta = contract.outcome_beta(out)
            if "teacher" in self.observation and self.prev.teacher < 0:
                self.counts["bad_teacher_labels"] += 1
            reason = {"reason": self.prev.reason} if self.reason_grid else {}
            self.sink.add_step(self.prev.action, beta, collided, frame, teacher=self.prev.teacher, **grid, **reason)

    def _record(self, rec: dict) -> None:
        stamp = contract.stamp_ns(rec["frame"].header.stamp)
        if self.early is not None and self.early[0] == stamp:  # the frame went in before its answer came
            usable, self.early = self.early[1], None
            kept = self.prev.reason if self.prev is not None and self.prev.stamp == stamp else None  # mapped once
            reason = kept if kept is not None or self.reason_grid is None else self._reason(rec)
            self.prev = _Prev(stamp, self._action(rec), teacher=self._teacher(rec), reason=reason) if usable else None
            return
        frame = self._frame(rec)
        if frame is None:
            self.prev = None
            return
        action = self._action(rec)
        prev, out = self.prev, rec["outcome"]
        if prev is not None and prev.action is not None and prev.answered and stamp - prev.stamp == self.step_ns:
            self._store(frame, out)
        else:
            if prev is not None and not contract.outcome_truncated(out):  # ~/reset republishes at the same stamp
                self.counts["chain_breaks"] += 1
            self.sink.add_first(frame[0], **({"grid": frame[1]} if self.map is not None else {}))
        self.prev = _Prev(stamp, action, teacher=self._teacher(rec), reason=self._reason(rec))

    def _store_next(self) -> None:
        """Store the observation one step after a complete record without waiting for its own answer."""
        prev = self.prev
        if prev is None or prev.action is None or not prev.answered:
            return
        stamp = prev.stamp + self.step_ns
        slot = self.joiner.pending.get(stamp)
        if slot is None or not all(k in slot for k in self.observation):
            return
        frame = self._frame(slot)
        self.early = (stamp, frame is not None)
        if frame is None:
            self.prev = None
            return
        self._store(frame, slot["outcome"])
        self.prev = _Prev(stamp, None, answered=False, teacher=self._teacher(slot), reason=self._reason(slot))

    def _release(self) -> None:
        if self.on_ready is None:
            return
        pending = self.joiner.pending

        def observed(stamp: int) -> bool:  # frame and outcome (and teacher) in, the policy's answer not yet (else joined)
            slot = pending.get(stamp)
            return slot is not None and all(k in slot for k in self.observation)

        ready = {s for s in pending if s > self.released and observed(s)}
        if self.prev is not None and self.prev.stamp > self.released:  # joined at once (its answer came first)
            ready.add(self.prev.stamp)
        for s in sorted(ready):
            if observed(s - self.step_ns):
                break  # its transition needs the answer to the observation before it; later ones wait too
            self.released = s
            self.on_ready(s)

    def report(self) -> dict:
        j = self.joiner
        return {
            "frames_without_action": j.dropped["action"],
            "frames_without_outcome": j.dropped["outcome"],
            **({"frames_without_teacher_label": j.dropped["teacher"]} if "teacher" in j.dropped else {}),
            **({"frames_without_odometry": j.dropped["odom"]} if "odom" in j.dropped else {}),
            "outcomes_or_actions_without_frame": j.dropped["frame"],
            "duplicates": j.duplicates,
            "said_again": j.late,
            "stamp_restarts": j.restarts,
            **self.counts,
        }


@dataclasses.dataclass(frozen=True)
class ActorSink:
    """One actor's side of a Training: the steps a TransitionAssembler completes, tagged with the actor."""

    training: object  # a uav_trainer.training.Training
    actor: int

    def add_first(self, frame: np.ndarray, grid: np.ndarray | None = None) -> None:
        self.training.add_first(frame, self.actor, grid)

    def add_step(
        self, action: int, beta_m: float, collided: bool, next_frame: np.ndarray, teacher: int = -1, reason=None, grid=None
    ) -> float:
        return self.training.add_step(action, beta_m, collided, next_frame, self.actor, teacher, reason, grid)

    def add_truncated(self, first_frame: np.ndarray, grid: np.ndarray | None = None) -> None:
        self.training.add_truncated(first_frame, self.actor, grid)
