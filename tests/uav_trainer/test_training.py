import math

import numpy as np
import torch

from uav_trainer import checkpoint
from uav_trainer.inprocess import run as run_inprocess
from uav_trainer.learner import LearnerConfig
from uav_trainer.training import TrainerConfig, Training


def feed(t: Training, n: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    t.add_first(rng.uniform(0, 10, (64, 64)).astype(np.float32))
    for k in range(n):
        t.add_step(int(rng.integers(4)), float(rng.uniform(0, 6)), k % 25 == 24, rng.uniform(0, 10, (64, 64)).astype(np.float32))


def small_cfg(**kw):
    base = dict(
        model="cnn",
        learning_starts=50,
        replay_ratio=0.5,
        checkpoint_interval_updates=10,
        push_interval_updates=5,
        replay_capacity=500,
        learner=LearnerConfig(batch_size=8),
    )
    base.update(kw)
    return TrainerConfig(**base)


def test_training_writes_outputs_and_resumes(tmp_path):
    t = Training(small_cfg(), tmp_path, log=lambda s: None)
    feed(t, 120)
    while t.learn_once():
        pass
    assert t.learner.updates == int((120 - 50) * 0.5)
    assert t.take_push() is not None and t.take_push() is None
    t.metrics_row()
    t.save_checkpoint()
    t.close()
    for name in ("metrics.csv", "episodes.csv", "curves.png", "policy_cnn.safetensors"):
        assert (tmp_path / name).is_file(), name
    assert len((tmp_path / "episodes.csv").read_text().splitlines()) == 1 + 4  # 4 episodes ended (every 25 steps)
    again = Training(small_cfg(), tmp_path, log=lambda s: None, resume=True)
    assert (again.env_steps, again.learner.updates, again.stats.episodes) == (120, 35, 4)
    assert again.epsilon() == t.epsilon()
    for a, b in zip(t.learner.online.parameters(), again.learner.online.parameters(), strict=True):
        torch.testing.assert_close(a, b)
    # The fresh replay must refill before learning continues.
    feed(again, 40, seed=1)
    assert not again.can_learn()
    again.close()


def test_non_finite_loss_stops_learning_and_keeps_the_last_good_checkpoint(tmp_path):
    t = Training(small_cfg(), tmp_path, log=lambda s: None)
    feed(t, 120)
    t.learn_once()
    good = t.save_checkpoint()
    t.replay.reward[:] = np.nan  # poison the memory
    assert not t.learn_once()
    assert t.failed and "loss is nan" in t.failed
    assert str(good) in t.failed and not t.can_learn()
    assert t.save_checkpoint() is None and checkpoint.latest(tmp_path / "checkpoints") == good
    t.close()


def test_inprocess_training_is_reproducible(tmp_path):
    cfg = TrainerConfig(model="sam", seed=5, total_steps=300, learning_starts=100, replay_ratio=0.25)
    weights = []
    for k in range(2):
        t = run_inprocess(cfg, str(tmp_path / f"r{k}"), log=lambda s: None)
        weights.append([p.detach().clone() for p in t.learner.online.parameters()])
        assert t.learner.updates == 50 and not math.isnan(t.last_loss)
    for a, b in zip(*weights, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_layout_per_episode_flies_a_new_layout_after_every_crash(tmp_path, monkeypatch):
    import uav_trainer.inprocess as ip

    made = []
    real = ip.procedural_world
    monkeypatch.setattr(ip, "procedural_world", lambda seed: made.append(seed) or real(seed))
    cfg = TrainerConfig(model="cnn", seed=0, total_steps=120, learning_starts=10**6, epsilon_start=1.0)
    t = ip.run(cfg, str(tmp_path), log=lambda s: None, layout_per_episode=True)
    assert t.stats.episodes >= 3 and len(made) == t.stats.episodes + 1  # the first layout plus one per crash
    assert min(made) >= 1000 and len(set(made)) == len(made)  # never the held-out random:0..999
