import numpy as np
import pytest
import torch

from uav_policy.frame_stack import FrameStack
from uav_policy.networks import NetConfig
from uav_trainer import checkpoint
from uav_trainer.learner import Learner, LearnerConfig, double_dqn_target, linear_epsilon, random_shift
from uav_trainer.replay import PRIORITY_FLOOR, ReplayMemory


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


def test_n_step_returns_stop_at_crashes_time_limits_and_the_newest_frame():
    mem = ReplayMemory(capacity=100, frame_shape=(4, 4), frames=5, seed=0)
    mem.add_first(frame(0))
    for slot, r, done in [(0, 1, False), (1, 2, False), (2, 3, True), (3, 4, False), (4, 5, False)]:
        mem.add_transition(0, float(r), done, frame(slot + 1))
    mem.add_first(frame(6))  # slot 5 ended its episode at a time limit: it has no transition
    for slot in range(6, 10):
        mem.add_transition(0, float(slot), False, frame(slot + 1))
    # Slot -> (return, done, discount, bootstrap slot), gamma 0.5 and n 3, by hand.
    expected = {
        0: (1 + 0.5 * 2 + 0.25 * 3, True, 0.125, 3),  # stops at the crash in slot 2
        1: (2 + 0.5 * 3, True, 0.25, 3),
        2: (3, True, 0.5, 3),
        3: (4 + 0.5 * 5, False, 0.25, 5),  # the time limit: bootstraps from the episode's last frame
        4: (5, False, 0.5, 5),
        6: (6 + 0.5 * 7 + 0.25 * 8, False, 0.125, 9),
        7: (7 + 0.5 * 8 + 0.25 * 9, False, 0.125, 10),
        8: (8 + 0.5 * 9, False, 0.25, 10),  # slot 10 is the newest frame: no transition yet
        9: (9, False, 0.5, 10),
    }
    for i, want in expected.items():
        assert mem.n_step_return(i, 3, 0.5) == pytest.approx(want), f"slot {i}"
    batch = mem.sample(200, n_step=3, gamma=0.5)
    assert set(batch["index"]) == set(expected)
    for k, i in enumerate(batch["index"]):
        r, done, discount, boot = expected[i]
        assert (batch["reward"][k], batch["done"][k], batch["discount"][k]) == pytest.approx((r, float(done), discount))
        np.testing.assert_array_equal(batch["next_state"][k], mem.stack(boot))
    # n = 1 is one-step Q-learning: the stored reward, the next slot, gamma from the learner.
    one = mem.sample(50, n_step=1, gamma=0.5)
    assert "discount" not in one
    for k, i in enumerate(one["index"]):
        assert one["reward"][k] == mem.reward[i]
        np.testing.assert_array_equal(one["next_state"][k], mem.stack(i + 1))
    with pytest.raises(ValueError, match="n_step"):
        mem.sample(4, n_step=0)


def test_prioritized_sampling_follows_priorities_with_hand_computed_weights():
    mem = ReplayMemory(capacity=100, frame_shape=(4, 4), frames=5, seed=0)
    mem.add_first(frame(0))
    for v in range(1, 10):
        mem.add_transition(0, float(v), False, frame(v))
    # Slots 0..8 are sampleable (9 is the newest frame); all start at the top priority, 1.
    assert mem.priority[:9].tolist() == [1.0] * 9 and mem.priority[9] == 0.0
    mem.update_priorities(np.arange(9), mem.writes[:9], np.array([7.0] + [0.0] * 8))
    assert mem.priority[0] == 7.0 + PRIORITY_FLOOR and mem.priority[1] == PRIORITY_FLOOR
    assert mem.max_priority == 7.0 + PRIORITY_FLOOR
    batch = mem.sample(4000, priority_alpha=1.0, priority_beta=0.5)
    # P(0) = 7.001 / (7.001 + 8 * 0.001) = 0.99886: slot 0 nearly always.
    total = 7.0 + PRIORITY_FLOOR + 8 * PRIORITY_FLOOR
    p0, p1 = (7.0 + PRIORITY_FLOOR) / total, PRIORITY_FLOOR / total
    share = np.mean(batch["index"] == 0)
    assert abs(share - p0) < 0.005, share
    # w_i = (N P_i)^-beta / (N P_min)^-beta with N = 9, beta = 0.5, by hand.
    w = dict(zip(batch["index"].tolist(), batch["weight"].tolist(), strict=True))
    assert w[0] == pytest.approx((p1 / p0) ** 0.5, rel=1e-5) and w[1] == pytest.approx(1.0)
    # alpha 0.5 flattens the preference: P(0) = sqrt(7.001) / (sqrt(7.001) + 8 sqrt(0.001)).
    flat = mem.sample(4000, priority_alpha=0.5, priority_beta=1.0)
    want = (7.0 + PRIORITY_FLOOR) ** 0.5 / ((7.0 + PRIORITY_FLOOR) ** 0.5 + 8 * PRIORITY_FLOOR**0.5)
    assert abs(np.mean(flat["index"] == 0) - want) < 0.03
    # A new transition enters with the largest priority seen.
    mem.add_transition(0, 10.0, False, frame(10))
    assert mem.priority[9] == 7.0 + PRIORITY_FLOOR
    # Uniform sampling (alpha 0, the paper) carries no weights and ignores priorities.
    uniform = mem.sample(4000)
    assert "weight" not in uniform and "writes" not in uniform and np.mean(uniform["index"] == 0) < 0.2
    with pytest.raises(ValueError, match="priority_alpha"):
        mem.sample(4, priority_alpha=1.5)
    with pytest.raises(ValueError, match="finite"):
        mem.update_priorities(np.array([0]), mem.writes[:1], np.array([np.nan]))


def test_priorities_of_slots_rewritten_since_sampling_are_left_alone():
    mem = ReplayMemory(capacity=8, frame_shape=(4, 4), frames=5, seed=0)
    mem.add_first(frame(0))
    for v in range(1, 8):
        mem.add_transition(0, 0.0, False, frame(v))
    batch = mem.sample(64, priority_alpha=0.6, priority_beta=0.4)
    slots, writes = batch["index"], batch["writes"]
    stale = int(slots[0])
    mem.add_transition(0, 0.0, False, frame(8))  # writes slot 0 (the ring is full)...
    for _ in range((stale - 0) % 8):  # ...and on to the stale slot
        mem.add_transition(0, 0.0, False, frame(9))
    mem.add_transition(0, 0.0, False, frame(10))  # the stale slot now holds a new transition
    kept = mem.priority[stale]
    mem.update_priorities(slots, writes, np.full(len(slots), 5.0))
    assert mem.priority[stale] == kept, "a rewritten slot keeps the priority it was stored with"
    fresh = [int(i) for i, w in zip(slots, writes, strict=True) if mem.writes[i] == w]
    assert fresh and all(mem.priority[i] == 5.0 + PRIORITY_FLOOR for i in fresh)


def filled_memory(capacity: int, steps: int) -> ReplayMemory:
    mem = ReplayMemory(capacity=capacity, frame_shape=(4, 4), frames=5, seed=3)
    mem.add_first(frame(0))
    for v in range(1, steps):
        mem.add_transition(v % 4, float(v), v % 7 == 6, frame(v))
    mem.update_priorities(np.arange(3), mem.writes[:3], np.array([0.5, 2.0, 9.0]))
    return mem


@pytest.mark.parametrize("steps", [6, 30])  # partly filled; wrapped around
def test_replay_state_round_trip_samples_the_same_batches(steps):
    mem = filled_memory(10, steps)
    state = mem.state()
    assert state["frame"].shape == (min(steps, 10), 4, 4)  # only filled slots are written
    copy = ReplayMemory(capacity=10, frame_shape=(4, 4), frames=5, seed=3)
    copy.load_state(state, n_actions=4)
    assert (copy.cursor, copy.count, copy.transitions_added, copy.max_priority) == (
        mem.cursor,
        mem.count,
        mem.transitions_added,
        mem.max_priority,
    )
    for alpha in (0.0, 0.6):
        a, b = mem.sample(16, 3, 0.9, alpha, 0.5), copy.sample(16, 3, 0.9, alpha, 0.5)
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_replay_state_that_does_not_fit_or_holds_impossible_values_is_refused_and_changes_nothing():
    mem = filled_memory(10, 30)

    def spoiled(**kw):
        st = mem.state()
        st.update(kw)
        return st

    bad = [
        (ReplayMemory(capacity=12, frame_shape=(4, 4), frames=5), mem.state(), "capacity"),
        (ReplayMemory(capacity=10, frame_shape=(4, 5), frames=5), mem.state(), "capacity"),
        (None, spoiled(action=np.full(10, 4, dtype=np.int64)), "actions outside"),
        (None, spoiled(frame=np.full((10, 4, 4), np.nan, dtype=np.float16)), "NaN"),
        (None, spoiled(reward=np.ones(9, dtype=np.float32)), "'reward'"),
        (None, spoiled(priority=np.full(10, np.inf)), "non-finite"),
        (None, spoiled(header=np.array([10, 5, 4, 4, 10, 10, 29], dtype=np.int64)), "counters"),
        (None, {k: v for k, v in mem.state().items() if k != "header"}, "header"),
    ]
    for target, state, words in bad:
        if target is None:  # (an empty memory is falsy: it has no transitions)
            target = ReplayMemory(capacity=10, frame_shape=(4, 4), frames=5)
        before = target.state()
        with pytest.raises(ValueError, match=words):
            target.load_state(state, n_actions=4)
        after = target.state()
        assert all(np.array_equal(before[k], after[k]) for k in before)


def test_importance_weights_scale_each_samples_loss_and_td_errors_come_back():
    batch = small_batch(2)
    learner = Learner(NetConfig(model="cnn"), LearnerConfig(seed=5))
    with torch.no_grad():
        s, a, r, done, s2 = learner._tensors(batch)
        y = double_dqn_target(r, done, 0.99, learner.online(s2)[0], learner.target(s2)[0])
        q = learner.online(s)[0].gather(1, a.unsqueeze(1)).squeeze(1)
    w = np.array([1.0, 0.0, 0.5, 0.25, 1.0, 0.0, 0.75, 0.1], np.float32)
    per_sample = torch.nn.functional.huber_loss(q, y, reduction="none")
    out = learner.update({**batch, "weight": w})
    assert out["loss"] == pytest.approx(float((torch.from_numpy(w) * per_sample).mean()), rel=1e-5)
    np.testing.assert_allclose(out["td_abs"], (q - y).abs().numpy(), rtol=1e-5)
    # All-ones weights are the unweighted loss.
    a1 = Learner(NetConfig(model="cnn"), LearnerConfig(seed=5)).update({**batch, "weight": np.ones(8, np.float32)})
    a2 = Learner(NetConfig(model="cnn"), LearnerConfig(seed=5)).update(batch)
    assert a1["loss"] == pytest.approx(a2["loss"], rel=1e-6)


def test_a_batch_discount_replaces_gamma_in_the_target():
    batch = small_batch(1)
    plain = Learner(NetConfig(model="cnn"), LearnerConfig(seed=4, gamma=0.5))
    per_sample = Learner(NetConfig(model="cnn"), LearnerConfig(seed=4, gamma=0.99))
    assert plain.update(batch)["loss"] == per_sample.update({**batch, "discount": np.full(8, 0.5, np.float32)})["loss"]
    # Per-sample discounts: each row's target uses its own.
    r, done = torch.tensor([1.0, 1.0]), torch.tensor([0.0, 0.0])
    q = torch.tensor([[2.0, 0.0], [2.0, 0.0]])
    y = double_dqn_target(r, done, torch.tensor([0.5, 0.25]), q, q)
    torch.testing.assert_close(y, torch.tensor([2.0, 1.5]))


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


def test_a_checkpoints_networks_export_as_policy_weights_and_bad_ones_are_refused(tmp_path):
    from uav_policy import weights as wio

    cfg = NetConfig(model="sam")
    lr = Learner(cfg, LearnerConfig(seed=6, target_update_interval=100))
    for k in range(3):
        lr.update(small_batch(k))
    path = checkpoint.save(tmp_path / "ck", lr, {"env_steps": 77}, {})
    state = torch.ones(1, 5, 64, 64)
    for net, source in (("online", lr.online), ("target", lr.target)):
        out = tmp_path / f"{net}.safetensors"
        assert checkpoint.export_weights(path, out, net, camera_hfov_deg=120.0) == cfg
        assert wio.read_file_camera(out) == 120.0 and wio.read_file_window(out) is None
        back = wio.load_file(out, cfg)
        with torch.no_grad():
            torch.testing.assert_close(back(state), source(state), rtol=0, atol=0)
    # Online and target differ after updates (the target is synced only every 100), so the choice matters.
    with torch.no_grad():
        assert not torch.equal(lr.online(state)[0], lr.target(state)[0])
    with pytest.raises(ValueError, match="no 'ema' network"):  # the run kept no average
        checkpoint.export_weights(path, tmp_path / "ema.safetensors", "ema")
    with pytest.raises(ValueError, match="net must be one of"):
        checkpoint.export_weights(path, tmp_path / "x.safetensors", "best")
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        checkpoint.export_weights(tmp_path, tmp_path / "x.safetensors")
    (path / "state.safetensors").write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json}")
    with pytest.raises(ValueError, match="corrupt|readable"):
        checkpoint.export_weights(path, tmp_path / "x.safetensors")
    assert not (tmp_path / "x.safetensors").exists()


def test_confidence_interval_matches_a_hand_computed_t_interval():
    from uav_trainer.evaluate import mean_ci95

    mean, hw = mean_ci95([0.0, 1.0, 2.0])  # s = 1, n = 3: 4.303 * 1 / sqrt(3)
    assert mean == 1.0 and hw == pytest.approx(4.303 / 3**0.5)
    assert np.isnan(mean_ci95([5.0])[1])


def test_weight_average_follows_online_without_changing_learning(tmp_path):
    cfg = NetConfig(model="sam")
    plain = Learner(cfg, LearnerConfig(seed=4, target_update_interval=2))
    avg = Learner(cfg, LearnerConfig(seed=4, target_update_interval=2, ema_decay=0.9))
    assert plain.ema is None
    expected = [p.detach().clone() for p in avg.online.parameters()]
    for k in range(4):
        assert plain.update(small_batch(k))["loss"] == avg.update(small_batch(k))["loss"]
        expected = [0.9 * e + 0.1 * p.detach() for e, p in zip(expected, avg.online.parameters(), strict=True)]
    for a, b in zip(plain.online.parameters(), avg.online.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)  # the average never feeds back into learning
    for e, p in zip(expected, avg.ema.parameters(), strict=True):
        torch.testing.assert_close(p, e)
    assert any(not torch.equal(p, o) for p, o in zip(avg.ema.parameters(), avg.online.parameters(), strict=True))
    # The average is checkpointed and restored with the rest.
    path = checkpoint.save(tmp_path, avg, {}, {})
    back = Learner(cfg, LearnerConfig(seed=5, ema_decay=0.9))
    checkpoint.load(path, back)
    for a, b in zip(avg.ema.parameters(), back.ema.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_learning_rate_annealing_schedule_reaches_the_optimizer():
    lr = Learner(NetConfig(model="cnn"), LearnerConfig(learning_rate=1e-3, lr_anneal_updates=4, lr_end_fraction=0.1))
    assert [lr.learning_rate(u) for u in (0, 2, 4, 100)] == pytest.approx([1e-3, 5.5e-4, 1e-4, 1e-4])
    for k in range(3):
        lr.update(small_batch(k))
    assert lr.optimizer.param_groups[0]["lr"] == pytest.approx(lr.learning_rate(2))
    assert Learner(NetConfig(model="cnn"), LearnerConfig()).learning_rate(10**6) == LearnerConfig.learning_rate


@pytest.mark.parametrize(
    "bad",
    [
        {"ema_decay": 1.0},
        {"ema_decay": -0.1},
        {"lr_anneal_updates": -1},
        {"lr_end_fraction": 0.0},
        {"augment_shift_px": -1},
        {"augment_shift_px": 9},
    ],
)
def test_bad_learner_settings_are_refused(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        Learner(NetConfig(model="cnn"), LearnerConfig(**bad))


def test_random_shift_is_a_pad_and_crop_with_repeated_edges():
    x = torch.arange(64 * 3 * 9 * 11, dtype=torch.float32).reshape(64, 3, 9, 11)
    out = random_shift(x, 2, torch.Generator().manual_seed(7))
    assert out.shape == x.shape and random_shift(x, 0) is x
    padded = torch.nn.functional.pad(x, (2, 2, 2, 2), mode="replicate")
    offsets = set()
    for i in range(64):  # each sample is one of the 25 crops of its padded image, all frames alike
        crops = [(dy, dx) for dy in range(5) for dx in range(5) if torch.equal(out[i], padded[i, :, dy : dy + 9, dx : dx + 11])]
        assert len(crops) == 1, i
        offsets.add(crops[0])
    assert len(offsets) > 10  # samples draw their own shifts


def test_shift_augmentation_changes_the_update_and_stays_reproducible_and_resumable(tmp_path):
    cfg = NetConfig(model="sam")
    plain = Learner(cfg, LearnerConfig(seed=2))
    shifted = [Learner(cfg, LearnerConfig(seed=2, augment_shift_px=4)) for _ in range(2)]
    losses = [[lr.update(small_batch(k))["loss"] for k in range(3)] for lr in [plain, *shifted]]
    assert losses[1] == losses[2]  # seeded: the same shifts
    assert losses[0] != losses[1]  # the augmentation reaches the update
    # A checkpoint carries the random state the shifts are drawn from: a resumed learner goes on as
    # the uninterrupted one.
    path = checkpoint.save(tmp_path, shifted[0], {}, {})
    after = shifted[0].update(small_batch(3))["loss"]
    resumed = Learner(cfg, LearnerConfig(seed=9, augment_shift_px=4))
    checkpoint.load(path, resumed)
    assert resumed.update(small_batch(3))["loss"] == after
