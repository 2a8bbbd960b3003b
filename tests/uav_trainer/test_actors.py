"""trainer_node's jobs without ROS: each actor's release chain and liveness, the camera and reward window recorded
in the weights files, and what it reports."""

import types

from uav_sim.reward import window_fov_rad
from uav_trainer.actors import ActorState
from uav_trainer.camera_record import CameraRecord
from uav_trainer.trainer_status import progress_line


class Log:
    def __init__(self):
        self.said = []

    def warning(self, message, **_):
        self.said.append(message)

    info = warning


def test_a_release_goes_once_its_weights_only_when_changed_and_again_with_them_when_unanswered():
    a = ActorState(0, "/actor0", "/actor0/step_outcome")
    assert a.weights_due(5) and not a.weights_due(5) and a.weights_due(6)
    a.go_stamp = 1_500_000_000
    a.sent("fut", now=100.0)
    assert (a.in_flight, a.in_flight_stamp, a.go_stamp, a.unanswered_since) == ("fut", 1_500_000_000, None, 100.0)
    assert a.overdue(109.0, timeout_s=10.0) is None
    said = a.overdue(110.5, timeout_s=10.0)
    assert "did not answer the release of the frame at 1.5 s" in said and a.in_flight is None
    assert a.go_stamp == 1_500_000_000 and a.weights_due(6)  # the same frame again, with the weights
    a.go_stamp = 2_000_000_000
    a.sent("fut2", now=111.0)
    assert a.unanswered_since == 100.0  # still unanswered since the first
    a.go_stamp = 2_500_000_000  # a newer frame came meanwhile: the retry releases up to it
    a.overdue(122.0, timeout_s=10.0)
    assert a.go_stamp == 2_500_000_000
    # The answer to a release is lost and the next release waits behind it: the lockstep simulator waits for the
    # policy, falls silent and is counted as lost; its release still goes again, else the three wait on each other.
    a.silent = "sim"
    a.sent("fut3", now=130.0)
    assert a.overdue(139.0, timeout_s=10.0) is None
    assert "did not answer the release" in a.overdue(140.5, timeout_s=10.0) and a.in_flight is None


def test_an_actor_is_reported_missing_lost_or_unanswering_once_and_taken_up_again():
    a, b = ActorState(0, "/actor0", "/actor0/step_outcome"), ActorState(1, "/actor1", "/actor1/step_outcome")
    assert a.check_alive(29.0, started=0.0, timeout_s=30.0, actors=[a, b]) is None
    count, said = a.check_alive(30.0, started=0.0, timeout_s=30.0, actors=[a, b])
    assert count == "actors_missing" and "/actor0/step_outcome" in said and "goes on with 1 other" in said
    assert a.check_alive(90.0, started=0.0, timeout_s=30.0, actors=[a, b]) is None  # once
    assert "heard from" in a.heard(91.0) and a.silent is None and a.heard(92.0) is None
    count, said = a.check_alive(122.0, started=0.0, timeout_s=30.0, actors=[a, b])
    assert count == "actors_lost" and "said nothing for 30 s" in said
    a.heard(130.0)
    a.go_stamp = 1
    a.sent("f", now=130.0)
    a.heard(165.0)
    count, said = a.check_alive(165.0, started=0.0, timeout_s=30.0, actors=[a, b])
    assert count == "actors_lost" and "answered no release" in said
    assert "answers again" in a.answered() and a.silent is None and a.unanswered_since is None
    b.silent = "sim"
    a.last_heard = 0.0
    assert "no actor is heard from: training waits" in a.check_alive(200.0, 0.0, 30.0, [a, b])[1]


def test_the_camera_and_a_reward_window_that_is_not_the_papers_are_recorded_from_whichever_actor_says_them():
    training = types.SimpleNamespace(camera_hfov_deg=None, reward_window_fraction=None)
    cameras, log = [], Log()
    rec = CameraRecord(training, log, lambda intrinsics, hfov: cameras.append(hfov))
    rec.on_info(None, 64, None)
    rec.on_info(200.0, 64, None)  # outside the weights files' range
    assert training.camera_hfov_deg is None and sum("malformed" in m for m in log.said) == 2
    rec.on_info(87.0, 64, "k")
    rec.on_info(87.0, 64, "k")  # every step sends it: only a change is news
    assert training.camera_hfov_deg == 87.0 and cameras == [87.0]
    rec.on_outcome_fov(window_fov_rad(64, 87.0, 0.2))  # the paper's window: the middle 20 % of each side
    assert training.reward_window_fraction is None
    rec.on_outcome_fov(window_fov_rad(64, 87.0, 0.5))
    assert training.reward_window_fraction == 0.5 and any("recorded in the weights files" in m for m in log.said)


def test_the_progress_line_sums_what_did_not_pair_and_names_each_actors_steps():
    training = types.SimpleNamespace(cfg=types.SimpleNamespace(total_steps=200), actor_steps=[30, 70])
    actors = [types.SimpleNamespace(ns="/a0", index=0), types.SimpleNamespace(ns="/a1", index=1)]
    row = dict(env_steps=100, updates=25, episodes=3, mean_episode_length=33.3, mean_episode_reward=1.5, epsilon=0.5)
    row.update(loss=0.1, env_steps_per_s=20.0, updates_per_s=5.0)
    status = dict(frames_without_action=1, frames_without_outcome=2, outcomes_or_actions_without_frame=3)
    status.update(chain_breaks=4, stamp_restarts=0)
    line = progress_line(row, status, training, actors)
    assert "steps 100 (50.0%)" in line and "unpaired 6 breaks 4" in line and "actors /a0 30 /a1 70" in line
    assert "(ratio 0.25)" in line
