"""Pairing is exact: thousands of simulated steps, streams delivered out of order, faults injected."""

import numpy as np
from geometry_msgs.msg import TwistStamped

from uav_common import contract
from uav_common.actions import PAPER_ACTIONS
from uav_common.kinematics import BodyTwist
from uav_interfaces.msg import TeacherLabel
from uav_sim.reward import step_reward
from uav_sim.simulator import SimConfig, Simulator
from uav_sim.world import load_world
from uav_trainer.pairing import TransitionAssembler

STEP_NS = 500_000_000


class Sink:
    def __init__(self):
        self.events = []

    def add_first(self, frame):
        self.events.append(("first", frame))

    def add_step(self, action, beta, collided, frame, teacher=-1):
        self.events.append(("step", action, step_reward(beta, collided), collided, frame))

    def add_truncated(self, frame):
        self.events.append(("truncated", frame))


def simulate(n_steps, seed=0, max_episode_steps=0):
    """Ground truth and the messages sim_node and policy_node would publish for it."""
    sim = Simulator(load_world("basic"), SimConfig(seed=seed, start_yaw_jitter_deg=180, max_episode_steps=max_episode_steps))
    rng = np.random.default_rng(seed)
    r = sim.observe()
    msgs, truth = [], []
    for k in range(n_steps + 1):
        stamp = contract.stamp_from_seconds(r.sim_time_s)
        msgs.append(("frame", contract.depth_to_image(r.depth_m, stamp, "cam")))
        msgs.append(("outcome", contract.make_outcome(r.beta_m, r.collided, stamp, "cam", 0.1, 10.0, 0.3, r.truncated)))
        if k == n_steps:
            break
        a = int(rng.integers(4))
        act = PAPER_ACTIONS[a]
        ts = TwistStamped()
        ts.header.stamp = stamp
        ts.twist.linear.x = act.linear_x_mps
        ts.twist.angular.z = act.yaw_rate_radps(0.5)
        msgs.append(("action", ts))
        r = sim.step(BodyTwist(act.linear_x_mps, yaw_rate_radps=act.yaw_rate_radps(0.5)))
        truth.append((a, r.reward, r.collided, r.depth_m, r.truncated))
    sim.close()
    return msgs, truth


def shuffled_across_streams(msgs, rng, window=6):
    """Each stream keeps its order (DDS reliable), but streams interleave arbitrarily."""
    streams = {s: [m for st, m in msgs if st == s] for s in dict.fromkeys(st for st, _ in msgs)}
    out, pos = [], {s: 0 for s in streams}
    while any(pos[s] < len(streams[s]) for s in streams):
        # the lagging streams are at most `window` messages behind the leading one
        open_ = [s for s in streams if pos[s] < len(streams[s])]
        lead = max(pos[s] for s in open_)
        behind = [s for s in open_ if pos[s] < lead - window]
        s = behind[0] if behind else open_[rng.integers(len(open_))]
        out.append((s, streams[s][pos[s]]))
        pos[s] += 1
    return out


def test_thousands_of_steps_pair_exactly_in_any_interleaving():
    msgs, truth = simulate(3000)
    assert sum(t[2] for t in truth) > 50, "the trajectory should contain many collisions"
    sink = Sink()
    asm = TransitionAssembler(sink, PAPER_ACTIONS, STEP_NS, (64, 64))
    for stream, m in shuffled_across_streams(msgs, np.random.default_rng(1)):
        asm.add(stream, m)
    steps = [e for e in sink.events if e[0] == "step"]
    assert sink.events[0][0] == "first" and len(sink.events) == 1 + len(steps)
    # The newest transition too: it is stored before the policy answers the frame it leads to.
    assert len(steps) == len(truth) == 3000, "no transition lost"
    for k, (e, (a, rew, col, depth, _)) in enumerate(zip(steps, truth, strict=True)):
        assert (e[1], e[3]) == (a, col), f"step {k}: action/done mis-paired"
        assert abs(e[2] - rew) < 1e-4, f"step {k}: reward mis-paired"
        np.testing.assert_array_equal(e[4], depth, err_msg=f"step {k}: next frame mis-paired")
    assert all(v == 0 for v in asm.report().values())


def teacher_label(stamp, action: int, scores=None, mask=None) -> TeacherLabel:
    """sim_node's label for the frame at `stamp` (scores: the action's best by default, no reason by default)."""
    label = TeacherLabel(action=action, scores=list(scores) if scores is not None else [1e7 * (a == action) for a in range(4)])
    label.header.stamp = stamp
    label.reason = contract.mask_to_image(np.zeros((64, 64), bool) if mask is None else mask, stamp, "cam")
    return label


def test_teacher_labels_pair_exactly_and_each_release_knows_its_frames_label():
    """With a teacher (sim_node's teacher_label, stamped as its frame), every stored transition carries the teacher's
    action for the frame it left, in any interleaving, and the release of a frame can tell the trainer that label."""
    msgs, truth = simulate(600, seed=5)
    rng = np.random.default_rng(6)
    labels, with_teacher = [], []
    for stream, m in msgs:
        with_teacher.append((stream, m))
        if stream == "outcome":  # one label per frame, an action that is not the action flown
            a = int(rng.integers(4))
            labels.append(a)
            with_teacher.append(("teacher", teacher_label(m.header.stamp, a)))

    class LabelSink(Sink):
        def add_step(self, action, beta, collided, frame, teacher=-1):
            super().add_step(action, beta, collided, frame)
            self.events[-1] += (teacher,)

    sink, released = LabelSink(), []
    asm = TransitionAssembler(
        sink, PAPER_ACTIONS, STEP_NS, (64, 64), on_ready=lambda s: released.append(asm.teacher_of(s)), teacher=True
    )
    for stream, m in shuffled_across_streams(with_teacher, np.random.default_rng(7)):
        asm.add(stream, m)
    steps = [e for e in sink.events if e[0] == "step"]
    assert len(steps) == 600 and [e[5] for e in steps] == labels[:600], "each transition has its own frame's label"
    assert [e[1] for e in steps] == [t[0] for t in truth], "the action flown is still the policy's"
    assert released == labels, "every frame released with its own label"
    assert all(v == 0 for v in asm.report().values()), asm.report()
    # Without its teacher label a frame is not an observation yet: nothing stored, nothing released.
    sink, released = LabelSink(), []
    asm = TransitionAssembler(sink, PAPER_ACTIONS, STEP_NS, (64, 64), on_ready=released.append, teacher=True)
    for stream, m in msgs[:30]:
        asm.add(stream, m)
    assert sink.events == [] and released == []
    # A label naming no action of the table, or scoring another number of actions, labels nothing (counted).
    at = [k for k, (s, _) in enumerate(with_teacher) if s == "teacher"]
    bad = list(with_teacher)
    bad[at[5]] = ("teacher", teacher_label(bad[at[5]][1].header.stamp, 9))
    bad[at[12]] = ("teacher", teacher_label(bad[at[12]][1].header.stamp, 1, [1.0]))
    sink = LabelSink()
    asm = TransitionAssembler(sink, PAPER_ACTIONS, STEP_NS, (64, 64), teacher=True)
    for stream, m in bad[:200]:
        asm.add(stream, m)
    assert asm.report()["bad_teacher_labels"] == 2 and sum(e[5] == -1 for e in sink.events if e[0] == "step") == 2


def test_teacher_reasons_pair_with_their_frames_as_cell_shares():
    """With a reason grid, the teacher label's reason (the pixels the planner's decision is about, mono8) is mapped
    with its frame: each stored transition carries the shares of the grid's cells that the mask of the frame it left
    covers, in any interleaving; a malformed mask is counted and gives no share."""
    from uav_common.frame_stack import node_shares

    msgs, _ = simulate(120, seed=8)
    rng = np.random.default_rng(9)
    shares, full = [], []
    for stream, m in msgs:
        full.append((stream, m))
        if stream == "outcome":
            mask = np.zeros((64, 64), bool)
            r, c = rng.integers(0, 48, 2)
            mask[r : r + 16, c : c + int(rng.integers(1, 16))] = True
            shares.append(node_shares(mask, (8, 8)))
            label = teacher_label(m.header.stamp, 0, mask=mask)
            if len(shares) == 60:
                label.reason.encoding = "rgb8"  # malformed
                shares[-1] = np.zeros(64, np.float32)
            full.append(("teacher", label))

    class ReasonSink(Sink):
        def add_step(self, action, beta, collided, frame, teacher=-1, reason=None):
            super().add_step(action, beta, collided, frame)
            self.events[-1] += (reason,)

    for order in range(3):  # the malformed mask counted once, however the streams interleave
        sink = ReasonSink()
        asm = TransitionAssembler(sink, PAPER_ACTIONS, STEP_NS, (64, 64), teacher=True, reason_grid=(8, 8))
        for stream, m in shuffled_across_streams(full, np.random.default_rng(10 + order)):
            asm.add(stream, m)
        steps = [e for e in sink.events if e[0] == "step"]
        assert len(steps) == 120 and all(np.array_equal(e[-1], want) for e, want in zip(steps, shares, strict=False))
        assert asm.report()["bad_reasons"] == 1 and asm.report()["frames_without_teacher_label"] == 0


def test_faults_are_counted_and_never_paired_wrongly():
    msgs, truth = simulate(200, seed=2)
    # Drop the action that answered frame 50, make frame 120's action unknown, corrupt frame 160.
    actions = [i for i, (s, _) in enumerate(msgs) if s == "action"]
    frames = [i for i, (s, _) in enumerate(msgs) if s == "frame"]
    del_idx = actions[50]
    msgs[actions[120]][1].twist.linear.x = 1.7
    msgs[frames[160]][1].encoding = "rgb8"
    msgs = [m for i, m in enumerate(msgs) if i != del_idx]
    sink = Sink()
    asm = TransitionAssembler(sink, PAPER_ACTIONS, STEP_NS, (64, 64))
    for stream, m in msgs:
        asm.add(stream, m)
    rep = asm.report()
    assert rep["frames_without_action"] == 1 and rep["unmatched_actions"] == 1 and rep["bad_frames"] == 1
    steps = [e for e in sink.events if e[0] == "step"]
    # Lost: 50 (record 50 incomplete; 49 leads to frame 50 and is kept), 120 (unknown action),
    # 159 and 160 (bad frame). No others.
    assert len(steps) == 200 - 4
    expected = [t for k, t in enumerate(truth) if k not in (50, 120, 159, 160)]
    for e, (a, rew, col, depth, _) in zip(steps, expected, strict=True):
        assert (e[1], e[3]) == (a, col) and abs(e[2] - rew) < 1e-4
        np.testing.assert_array_equal(e[4], depth)


def test_a_time_limit_stores_no_transition_and_starts_a_new_chain():
    msgs, truth = simulate(400, seed=3, max_episode_steps=7)
    cuts = [k for k, t in enumerate(truth) if t[4]]
    assert len(cuts) > 10 and sum(t[2] for t in truth) > 0, "both ends of episodes should occur"
    sink = Sink()
    asm = TransitionAssembler(sink, PAPER_ACTIONS, STEP_NS, (64, 64))
    for stream, m in shuffled_across_streams(msgs, np.random.default_rng(4)):
        asm.add(stream, m)
    assert [e[0] for e in sink.events].count("truncated") == len(cuts)
    events = sink.events[1:]  # after the first frame: one event per step
    assert len(events) == len(truth)
    for k, (e, (a, rew, col, depth, cut)) in enumerate(zip(events, truth, strict=True)):
        assert e[0] == ("truncated" if cut else "step"), f"step {k}"
        np.testing.assert_array_equal(e[-1], depth)  # after a cut: the new episode's first frame
        if not cut:
            assert (e[1], e[3]) == (a, col) and abs(e[2] - rew) < 1e-4
    assert all(v == 0 for v in asm.report().values())


def test_lockstep_release_follows_storage_and_waits_for_the_previous_answer():
    """on_ready(stamp) comes once per observation, after the transition leading to it is stored, and an
    observation whose predecessor's answer is late waits for it (lockstep learning depends on both)."""
    msgs, truth = simulate(300, seed=5, max_episode_steps=9)
    sink, released = Sink(), []
    asm = TransitionAssembler(sink, PAPER_ACTIONS, STEP_NS, (64, 64), on_ready=lambda s: released.append((s, len(sink.events))))
    # Each step's answer arrives after the next frame and outcome (a slow action writer): the worst order.
    order, held = [], None
    for stream, m in msgs:
        if stream == "action":
            held = (stream, m)
            continue
        order.append((stream, m))
        if stream == "outcome" and held is not None:
            order.append(held)
            held = None
    for stream, m in order:
        asm.add(stream, m)
    frames = [contract.stamp_ns(m.header.stamp) for s, m in msgs if s == "frame"]
    assert [s for s, _ in released] == frames, "every observation released once, in order"
    # Before observation k+1 is released its transition is in: events = first frame + k + 1 steps.
    assert [n for _, n in released[1:]] == list(range(2, len(frames) + 1))
    assert released[0] == (frames[0], 0), "the first frame is released before anything can be stored"
    assert len(sink.events) == 1 + len(truth) and all(v == 0 for v in asm.report().values())


def test_a_restarted_simulator_starts_a_new_chain_and_is_released_again():
    """The simulator restarts mid-run (its stamps begin again): nothing is paired across the restart,
    every step after it is stored, and lockstep release goes on (before, the trainer waited for good)."""
    before, truth_before = simulate(40, seed=7)
    after, truth_after = simulate(60, seed=8)
    sink, released = Sink(), []
    asm = TransitionAssembler(sink, PAPER_ACTIONS, STEP_NS, (64, 64), on_ready=released.append)
    rng = np.random.default_rng(9)
    for stream, m in shuffled_across_streams(before, rng) + shuffled_across_streams(after, rng):
        asm.add(stream, m)
    kinds = [e[0] for e in sink.events]
    assert kinds.count("first") == 2 and kinds[41] == "first", "the restart begins a new chain"
    steps = [e for e in sink.events if e[0] == "step"]
    assert len(steps) == len(truth_before) + len(truth_after)
    for e, (a, rew, col, depth, _) in zip(steps, truth_before + truth_after, strict=True):
        assert (e[1], e[3]) == (a, col) and abs(e[2] - rew) < 1e-4
        np.testing.assert_array_equal(e[4], depth)
    stamps = lambda msgs: [contract.stamp_ns(m.header.stamp) for s, m in msgs if s == "frame"]  # noqa: E731
    assert released == stamps(before) + stamps(after)
    assert asm.report()["stamp_restarts"] == 1


def test_with_the_local_map_each_frame_is_stored_with_the_map_its_odometry_places():
    """With a map grid, sim_node's odom completes an observation: the frames go into the local map in stamp order
    whatever the interleaving, and each is stored with the grid StackedSim gives the same run in process (a new episode
    forgets); malformed odometry is counted and starts a new chain."""
    from uav_sim.messages import odometry_msg
    from uav_sim.stacked_sim import StackedSim

    sim = Simulator(load_world("complex"), SimConfig(seed=4, image_width=64, image_height=64, hfov_deg=90.0))
    env = StackedSim(sim, 5, input_hw=(64, 64), map_grid=(64, 0.1))
    rng = np.random.default_rng(4)
    msgs, grids, r = [], [], env.last
    for k in range(150):
        stamp = contract.stamp_from_seconds(r.sim_time_s)
        odom = odometry_msg(r.pose, BodyTwist(0.0), stamp, "odom", "base_link")
        if k == 100:
            odom.pose.pose.position.x = float("nan")
        msgs += [("frame", contract.depth_to_image(r.depth_m, stamp, "cam")), ("odom", odom)]
        msgs.append(("outcome", contract.make_outcome(r.beta_m, r.collided, stamp, "cam", 0.1, 10.0, 0.3, r.truncated)))
        grids.append(env.last_grid.copy())
        a = int(rng.integers(4))
        ts = TwistStamped()
        ts.header.stamp = stamp
        ts.twist.linear.x, ts.twist.angular.z = PAPER_ACTIONS[a].linear_x_mps, PAPER_ACTIONS[a].yaw_rate_radps(0.5)
        msgs.append(("action", ts))
        r = env.step(a)
    k_matrix = sim.camera.intrinsics.k_matrix()
    sim.close()

    class MapSink(Sink):
        def add_first(self, frame, grid=None):
            self.events.append(("first", frame, grid))

        def add_step(self, action, beta, collided, frame, teacher=-1, grid=None):
            self.events.append(("step", frame, grid))

        def add_truncated(self, frame, grid=None):
            self.events.append(("truncated", frame, grid))

    for order in range(2):
        sink = MapSink()
        asm = TransitionAssembler(sink, PAPER_ACTIONS, STEP_NS, (64, 64), map_grid=(64, 0.1))
        asm.set_camera((k_matrix[0], k_matrix[4], k_matrix[2], k_matrix[5], 64, 64), 90.0)
        for stream, m in shuffled_across_streams(msgs, np.random.default_rng(20 + order)):
            asm.add(stream, m)
        stored = [e[2] for e in sink.events]
        assert len(stored) == 149 and asm.report()["unmapped_frames"] == 1, asm.report()
        assert sum(g.sum() > 0 for g in stored) > 100, "the map shows obstacles"
        # Up to the bad odometry every frame's grid is the in-process one; after it the map starts afresh.
        assert all(np.array_equal(g, want) for g, want in zip(stored[:100], grids[:100], strict=True))
