"""Turning the three message streams into transitions, by exact stamp, never guessing.

A record is (depth frame k, step outcome k, action answering frame k), joined on the stamp
of frame k. Record k and record k+1 make the transition (s_k, a_k, r_k, s_{k+1}, done_k)
when their stamps are exactly one step apart; r_k and done_k come from outcome k+1 (the
outcome of the step that produced frame k+1). Anything else - a gap, an action that matches
no known action, a malformed frame - starts a new chain and is counted. A transition is stored
once the policy has answered the frame it leads to (record k+1 needs action k+1), so the
newest transition of a run is always still pending when the run stops. A NaN outcome (the
episode hit the simulator's time limit, or was reset) stores no transition: the frame it comes
with starts the next episode's chain.
"""

from __future__ import annotations

import dataclasses

from uav_policy.actions import match_action
from uav_policy.frame_stack import fit_to_network
from uav_sim import contract


@dataclasses.dataclass
class _Prev:
    stamp: int
    action: int | None


class TransitionAssembler:
    """Feed messages with `add(stream, msg)`; completed steps go to `sink.add_first/add_step/add_truncated`."""

    STREAMS = ("frame", "outcome", "action")

    def __init__(self, sink, actions, step_ns: int, net_hw: tuple[int, int], max_pending: int = 500):
        self.sink, self.actions, self.step_ns, self.net_hw = sink, actions, step_ns, net_hw
        self.joiner = contract.StampJoiner(self.STREAMS, max_pending=max_pending)
        self.prev: _Prev | None = None
        self.counts = {"chain_breaks": 0, "unmatched_actions": 0, "bad_frames": 0}

    def add(self, stream: str, msg) -> None:
        joined = self.joiner.add(stream, contract.stamp_ns(msg.header.stamp), msg)
        if joined is not None:
            self._record(joined)

    def _record(self, rec: dict) -> None:
        stamp = contract.stamp_ns(rec["frame"].header.stamp)
        try:
            frame = fit_to_network(contract.image_to_depth(rec["frame"]), *self.net_hw)
        except ValueError:
            self.counts["bad_frames"] += 1
            self.prev = None
            return
        tw = rec["action"].twist
        action = match_action(self.actions, tw.linear.x, tw.angular.z, self.step_ns / 1e9)
        if action is None:
            self.counts["unmatched_actions"] += 1
        prev, out = self.prev, rec["outcome"]
        truncated = contract.outcome_truncated(out)  # a new episode without a collision: nothing to learn
        if prev is not None and prev.action is not None and stamp - prev.stamp == self.step_ns:
            if truncated:
                self.sink.add_truncated(frame)
            else:
                collided = contract.outcome_collided(out)
                beta = 0.0 if collided else min(max(float(out.range), 0.0), float(out.max_range))
                self.sink.add_step(prev.action, beta, collided, frame)
        else:
            if prev is not None and not truncated:  # ~/reset republishes at the same stamp: not a break
                self.counts["chain_breaks"] += 1
            self.sink.add_first(frame)
        self.prev = _Prev(stamp, action)

    def report(self) -> dict:
        j = self.joiner
        return {
            "frames_without_action": j.dropped["action"],
            "frames_without_outcome": j.dropped["outcome"],
            "outcomes_or_actions_without_frame": j.dropped["frame"],
            "duplicates": j.duplicates,
            "out_of_order": j.late,
            **self.counts,
        }
