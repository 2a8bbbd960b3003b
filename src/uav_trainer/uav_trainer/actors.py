"""What trainer_node keeps per actor (a sim_node/policy_node pair), without ROS: the release chain (the newest frame
to release, the push in flight, the weights its policy has) and whether the actor is alive. An actor whose simulator
says nothing, or whose policy answers no release, for actor_timeout_s is reported once (missing at start-up, lost
later) and taken up again when it is heard from or answers; a release not answered within release_timeout_s is sent
again, with the weights. Times are time.monotonic() seconds."""

from __future__ import annotations

from collections.abc import Sequence

# The policy refused the learner's weights: it would act on others for the rest of the run, so no step would be in
# lockstep (each one held for its wait_for_trainer_timeout_s). trainer_node stops; its final checkpoint lets the same
# command resume once the nodes agree.
REJECTED_WEIGHTS = (
    "{policy} rejected the weights of a release: {why}. Stopping: in lockstep the policy must act on this node's "
    "weights. Give policy_node and trainer_node the same model, frame_stack, input size (policy_node input_width and "
    "input_height, this node input_size_px) and action_* parameters (train does), then run again to resume from the "
    "final checkpoint"
)


# Frames heard without a single teacher_label before a run with a teacher stops: a lockstep step is released only
# with its teacher's label, so without them nothing is learnt.
TEACHERLESS_FRAMES = 10


class ActorState:
    pairing = None  # its TransitionAssembler (trainer_node's Actor makes it)

    def __init__(self, index: int, namespace: str, outcome_topic: str):
        self.index, self.ns, self.outcome_topic = index, namespace, outcome_topic
        self.label = namespace or "the actor"
        self.policy = f"{namespace}'s policy_node" if namespace else "policy_node"  # in log lines
        self.go_stamp = None  # the newest frame to release, once the previous push is answered
        self.in_flight = None  # the push sent and not answered (a future)
        self.in_flight_stamp, self.in_flight_since = None, 0.0
        self.pushed_version = None  # the version of the released weights this actor's policy has (Training.released_weights)
        self.last_heard: float | None = None  # its sim's latest message
        self.unanswered_since: float | None = None  # its policy was sent a release not answered since
        self.silent: str | None = None  # reported missing or lost: "sim" (said nothing) or "policy" (answered nothing)
        self.frames_heard = self.teachers_heard = 0  # frames and teacher labels heard
        self.fly_for: tuple[int, int | None] | None = None  # (stamp, the teacher's action flown or None) of the release

    def on_teacher(self, msg) -> None:
        self.teachers_heard += 1
        self.pairing.add("teacher", msg)

    def no_teacher(self, teacher: str) -> str | None:
        """With a teacher, the error that stops the run when its simulator sends frames but no teacher_label (a camera
        has no world to plan in); else None."""
        if teacher == "none" or self.frames_heard < TEACHERLESS_FRAMES or self.teachers_heard:
            return None
        return (
            f"parameter 'teacher'={teacher!r}: {self.frames_heard} depth frames came from {self.label} but no "
            "teacher_label. A teacher is sim_node's planner (sim_node teacher:=stack, all or map; train sets it); a "
            "camera has no world to plan in, so a run from a camera trains with teacher:=none"
        )

    def heard(self, now: float) -> str | None:
        """Its simulator said something; a line to log when it was silent."""
        self.last_heard = now
        if self.silent != "sim":
            return None
        self.silent = None
        if self.unanswered_since is not None:  # its policy gets another actor_timeout_s to answer
            self.unanswered_since = now
        return f"{self.label}: its sim_node is heard from, learning from it"

    def weights_due(self, version: int) -> bool:
        """Whether the next release carries the weights (they changed since its policy got them)."""
        due, self.pushed_version = version != self.pushed_version, version
        return due

    def sent(self, fut, now: float) -> None:
        """The release of go_stamp went out as `fut`."""
        self.in_flight, self.in_flight_stamp, self.in_flight_since, self.go_stamp = fut, self.go_stamp, now, None
        if self.unanswered_since is None:
            self.unanswered_since = now

    def answered(self) -> str | None:
        """The push in flight was answered; a line to log when its policy was counted as lost."""
        self.in_flight, self.unanswered_since = None, None
        if self.silent != "policy":
            return None
        self.silent = None
        return f"{self.label}: its policy_node answers again, learning from it"

    def overdue(self, now: float, timeout_s: float) -> str | None:
        """A release not answered within timeout_s is to be sent again, with the weights: the line to log, after which
        the caller drops the push in flight; else None. Also when its simulator has fallen silent: in lockstep the
        simulator waits for the policy, which waits for this release (its answer lost, the next release held behind
        it), so the silence may be this release's own doing. A policy that is gone offers no service, and nothing is
        sent to it (trainer_node._send_go)."""
        if self.in_flight is None or now - self.in_flight_since < timeout_s:
            return None
        self.in_flight = None
        if self.go_stamp is None or self.go_stamp < self.in_flight_stamp:
            self.go_stamp = self.in_flight_stamp
        self.pushed_version = None
        return (
            f"{self.policy} did not answer the release of the frame at {self.in_flight_stamp / 1e9:.1f} s "
            f"sim time within {timeout_s:g} s: sending it again"
        )

    def check_alive(self, now: float, started: float, timeout_s: float, actors: Sequence[ActorState]) -> tuple[str, str] | None:
        """(the count to add to: actors_missing or actors_lost, the error to log) when it falls silent now, else None."""
        if self.silent:
            return None
        sim_quiet = now - (self.last_heard if self.last_heard is not None else started) >= timeout_s
        unanswered = self.unanswered_since is not None and now - self.unanswered_since >= timeout_s
        if not sim_quiet and not unanswered:
            return None
        self.silent = "sim" if sim_quiet else "policy"
        count = "actors_lost"
        if self.silent == "policy":
            what = f"{self.label}: its policy_node has answered no release for {timeout_s:g} s, counted as lost"
        elif self.last_heard is None:
            count = "actors_missing"
            what = (
                f"{self.label}: nothing from its sim_node on {self.outcome_topic} within {timeout_s:g} s of start-up (is "
                "it running, on this ROS_DOMAIN_ID, and discoverable from here? docs/TRAINING.md, 'Many actors')"
            )
        else:
            what = f"{self.label}: its sim_node has said nothing for {timeout_s:g} s, counted as lost"
        others = sum(a.silent is None for a in actors)
        goes_on = f"training goes on with {others} other actor(s)" if others else "no actor is heard from: training waits"
        return count, f"{what}; {goes_on}, and takes it up when it comes"
