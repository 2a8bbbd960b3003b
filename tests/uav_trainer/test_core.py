import numpy as np
import pytest
import torch

from uav_common.frame_stack import FrameStack
from uav_policy.networks import NetConfig
from uav_trainer import checkpoint
from uav_trainer.episodes import EpisodeStats
from uav_trainer.learner import Learner, double_dqn_target
from uav_trainer.replay import LanedReplay, ReplayMemory
from uav_trainer.training_config import LearnerConfig, linear_epsilon


def frame(v):
    return np.full((4, 4), float(v), dtype=np.float32)


def test_replay_stacks_match_the_policy_stack_across_episode_boundaries():
    mem = ReplayMemory(capacity=100, frame_shape=(4, 4), frames=5, seed=0)
    fs = FrameStack(5)
    states = {}
    mem.add_first(frame(1))
    states[0] = fs.reset(frame(1))
    v, slot = 2, 0
    for step in range(12):
        done = step == 6  # a collision: frame 8 starts a new episode
        mem.add_transition(action=step % 4, reward=float(step), done=done, next_depth=frame(v))
        slot += 1
        states[slot] = fs.reset(frame(v)) if done else fs.push(frame(v))
        v += 1
    for i, expected in states.items():
        np.testing.assert_array_equal(mem.stack(i), expected, err_msg=f"slot {i}")
    assert mem.stack(7)[:, 0, 0].tolist() == [8, 8, 8, 8, 8]  # first frame of episode 2, repeated
    assert mem.stack(9)[:, 0, 0].tolist() == [8, 8, 8, 9, 10]
    batch = mem.sample(64)
    for k, i in enumerate(batch["index"]):
        np.testing.assert_array_equal(batch["state"][k], states[i])
        np.testing.assert_array_equal(batch["next_state"][k], states[i + 1])
        assert batch["reward"][k] == float(i) and batch["done"][k] == (i == 6)
    assert 12 not in set(batch["index"]), "the newest frame has no transition yet"


def test_replay_wraparound_never_mixes_overwritten_history():
    mem = ReplayMemory(capacity=10, frame_shape=(4, 4), frames=5, seed=1)
    mem.add_first(frame(0))
    for v in range(1, 30):
        mem.add_transition(0, 0.0, False, frame(v))
    for _ in range(20):
        b = mem.sample(16)
        for s in b["state"]:
            seq = s[:, 0, 0]
            assert np.all(np.diff(seq) == 1), f"stack {seq} is not consecutive"


def journaled(mem: ReplayMemory, every: int, steps: int, prune: bool = True) -> list:
    """Fill `mem` to `steps` frames, taking a journal segment every `every` writes and at the end, as
    checkpoints do; segments the memory has overwritten since are dropped (`prune`), as
    checkpoint.prune_journal does."""
    segments, journaled = [], 0
    mem.add_first(frame(0))
    for v in range(1, steps):
        mem.add_transition(v % 4, float(v), v % 7 == 6, frame(v))
        if mem.writes % every == 0 or v == steps - 1:
            segments.append(mem.segment(journaled))
            journaled = mem.writes
            segments = [g for g in segments if g["span"][1] > mem.writes - mem.capacity or not prune]
    return segments


def same_batches(a: ReplayMemory, b: ReplayMemory) -> None:
    assert (a.cursor, a.count, a.writes, len(a)) == (b.cursor, b.count, b.writes, len(b))
    for _ in range(3):
        x, y = a.sample(16), b.sample(16)
        assert x.keys() == y.keys()
        for k in x:
            np.testing.assert_array_equal(x[k], y[k], err_msg=k)


@pytest.mark.parametrize("steps", [6, 30])  # partly filled; wrapped around
def test_the_replay_journal_rebuilds_the_memory_that_samples_the_same_batches(steps):
    mem = ReplayMemory(capacity=10, frame_shape=(4, 4), frames=5, seed=3)
    segments = journaled(mem, 4, steps)
    assert sum(len(g["action"]) for g in segments) <= steps + len(segments)  # each frame once (and one overlap)
    copy = ReplayMemory(capacity=10, frame_shape=(4, 4), frames=5, seed=3)
    copy.load_segments(segments, mem.writes, n_actions=4)
    same_batches(mem, copy)
    # As it was at an earlier write (the journal ran on past a checkpoint that did not become latest).
    upto = steps - 3
    earlier = ReplayMemory(capacity=10, frame_shape=(4, 4), frames=5, seed=3)
    journaled(earlier, 4, upto)
    copy = ReplayMemory(capacity=10, frame_shape=(4, 4), frames=5, seed=3)
    copy.load_segments(journaled(ReplayMemory(10, (4, 4), 5), 4, steps, prune=False), upto, n_actions=4)
    same_batches(earlier, copy)


def test_a_replay_journal_that_does_not_fit_holds_impossible_values_or_a_gap_is_refused_and_changes_nothing():
    mem = ReplayMemory(capacity=10, frame_shape=(4, 4), frames=5, seed=3)
    segments = journaled(mem, 4, 30)
    last = segments[-1]
    n = len(last["action"])

    def spoiled(**kw):
        return segments[:-1] + [{**last, **kw}]

    bad = [
        (ReplayMemory(capacity=12, frame_shape=(4, 4), frames=5), segments, "capacity"),
        (ReplayMemory(capacity=10, frame_shape=(4, 5), frames=5), segments, "capacity"),
        (None, spoiled(action=np.full(n, 4, dtype=np.int64)), "actions outside"),
        (None, spoiled(frame=np.full((n, 4, 4), np.nan, dtype=np.float16)), "NaN"),
        (None, spoiled(reward=np.ones(n - 1, dtype=np.float32)), "'reward'"),
        (None, spoiled(reward=np.full(n, np.inf, dtype=np.float32)), "non-finite"),
        (None, spoiled(span=np.array([5, 2], dtype=np.int64)), "span"),
        (None, segments[:1] + segments[2:], "misses writes"),
        (None, segments[-1:], "starts at write"),
    ]
    for target, segs, words in bad:
        if target is None:  # (an empty memory is falsy: it has no transitions)
            target = ReplayMemory(capacity=10, frame_shape=(4, 4), frames=5)
            target.load_segments(journaled(ReplayMemory(10, (4, 4), 5), 3, 8), 8, n_actions=4)
        before = {k: getattr(target, k).copy() for k in ReplayMemory.SLOT_ARRAYS}
        counters = (target.cursor, target.count, target.writes)
        with pytest.raises(ValueError, match=words):
            target.load_segments(segs, 30, n_actions=4)
        assert all(np.array_equal(before[k], getattr(target, k)) for k in before)
        assert (target.cursor, target.count, target.writes) == counters


def test_double_dqn_target_hand_computed():
    r = torch.tensor([1.0, -10.0])
    done = torch.tensor([0.0, 1.0])
    q_online = torch.tensor([[1.0, 5.0, 2.0], [0.0, 0.0, 9.0]])  # online picks a1, a2
    q_target = torch.tensor([[4.0, 3.0, 8.0], [7.0, 7.0, 7.0]])  # target evaluates them
    y = double_dqn_target(r, done, 0.9, q_online, q_target)
    # 1 + 0.9 * Q_target(s', a1) = 1 + 2.7; terminal: just the reward (not max_target = 8).
    torch.testing.assert_close(y, torch.tensor([3.7, -10.0]))


def test_epsilon_schedule():
    assert linear_epsilon(0, 1.0, 0.05, 1000) == 1.0
    assert linear_epsilon(500, 1.0, 0.05, 1000) == pytest.approx(0.525)
    assert linear_epsilon(5000, 1.0, 0.05, 1000) == 0.05


def small_batch(seed=0, b=8):
    rng = np.random.default_rng(seed)
    return {
        "state": rng.uniform(0, 10, (b, 5, 64, 64)).astype(np.float32),
        "action": rng.integers(0, 4, b),
        "reward": rng.normal(size=b).astype(np.float32),
        "done": (rng.random(b) < 0.2).astype(np.float32),
        "next_state": rng.uniform(0, 10, (b, 5, 64, 64)).astype(np.float32),
    }


def test_learner_is_seeded_and_reproducible():
    runs = []
    for _ in range(2):
        lr = Learner(NetConfig(model="sam"), LearnerConfig(seed=3, target_update_interval=2))
        losses = [lr.update(small_batch(k))["loss"] for k in range(4)]
        runs.append((losses, [p.detach().clone() for p in lr.online.parameters()]))
    assert runs[0][0] == runs[1][0]
    for a, b in zip(runs[0][1], runs[1][1], strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_learner_fits_a_fixed_target():
    lr = Learner(NetConfig(model="cnn"), LearnerConfig(seed=0, learning_rate=1e-3))
    batch = small_batch(0)
    batch["done"][:] = 1.0  # targets are just the rewards
    first = lr.update(batch)["loss"]
    for _ in range(60):
        last = lr.update(batch)["loss"]
    assert last < 0.1 * first


def test_checkpoint_round_trip_and_resume(tmp_path):
    cfg = NetConfig(model="sam")
    a = Learner(cfg, LearnerConfig(seed=1, target_update_interval=3))
    for k in range(5):
        a.update(small_batch(k))
    rng = np.random.default_rng(9)
    rng.random(7)
    path = checkpoint.save(tmp_path, a, {"env_steps": 123, "episodes": 4}, {"replay": checkpoint.rng_state(rng)})
    assert checkpoint.latest(tmp_path) == path
    b = Learner(cfg, LearnerConfig(seed=2, target_update_interval=3))
    meta = checkpoint.load(path, b)
    assert meta["counters"] == {"env_steps": 123, "episodes": 4} and b.updates == 5
    rng2 = np.random.default_rng(0)
    checkpoint.set_rng_state(rng2, meta["rng"]["replay"])
    assert rng2.random() == rng.random()
    # Resumed training continues exactly as the original would have.
    for k in range(5, 8):
        la, lb = a.update(small_batch(k))["loss"], b.update(small_batch(k))["loss"]
        assert la == pytest.approx(lb, rel=1e-6)
    for pa, pb in zip(a.online.parameters(), b.online.parameters(), strict=True):
        torch.testing.assert_close(pa, pb)


def test_only_complete_checkpoints_are_resumed(tmp_path):
    lr = Learner(NetConfig(model="cnn"), LearnerConfig())
    good = checkpoint.save(tmp_path, lr, {}, {})
    (tmp_path / ".ckpt-broken.tmp").mkdir()  # a crash mid-write leaves only a temp dir
    assert checkpoint.latest(tmp_path) == good


def test_a_laned_memory_keeps_each_actors_chain_and_samples_every_lane_by_its_share():
    """Two actors' steps interleave: each lane's stacks and next states are its own actor's frames, as if it
    had a memory of its own, and batches come from the lanes in proportion to what they hold."""
    mem = LanedReplay(2, 200, (2, 2), frames=3, seed=1)
    assert [lane.capacity for lane in mem.lanes] == [100, 100] and mem.capacity == 200
    alone = [ReplayMemory(100, (2, 2), frames=3) for _ in range(2)]
    frame = lambda actor, k: np.full((2, 2), 100.0 * actor + k, dtype=np.float32)  # noqa: E731
    for m, actor in ((mem.lanes[0], 0), (mem.lanes[1], 1), (alone[0], 0), (alone[1], 1)):
        m.add_first(frame(actor, 0))
    for k in range(1, 31):
        for actor in (0, 1):  # interleaved, as two actors' steps arrive
            if actor == 1 and k > 10:
                continue  # actor 1 makes a third of actor 0's steps
            for m in (mem.lanes[actor], alone[actor]):
                m.add_transition(k % 4, float(k), False, frame(actor, k))
    assert len(mem) == len(alone[0]) + len(alone[1]) == 30 + 10
    for actor in (0, 1):
        for slot in range(len(alone[actor])):
            assert np.array_equal(mem.lanes[actor].stack(slot), alone[actor].stack(slot))
    batch = mem.sample(4000)
    assert batch["state"].shape == (4000, 3, 2, 2)
    from_1 = (batch["state"][:, -1, 0, 0] >= 100).mean()
    assert 0.2 < from_1 < 0.3, from_1  # 10 of 40 transitions are actor 1's
    # Every sampled transition's next state is the same actor's next frame.
    assert np.array_equal(batch["next_state"][:, -1, 0, 0] - batch["state"][:, -1, 0, 0], np.ones(4000))
    with pytest.raises(ValueError, match="at least 2 lanes"):
        LanedReplay(1, 200, (2, 2))


def test_each_actors_episode_is_its_own():
    stats = EpisodeStats()
    assert stats.step(1.0, False, 1, actor=0) is None
    assert stats.step(5.0, False, 2, actor=1) is None
    assert stats.step(2.0, True, 3, actor=0) == (2, 3.0)  # actor 1's step is not in actor 0's episode
    assert stats.step(5.0, True, 4, actor=1) == (2, 10.0)
    assert stats.episodes == 2 and stats.mean_length() == 2.0
