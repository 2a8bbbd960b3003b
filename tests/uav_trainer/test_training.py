import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from uav_policy import weights as wio
from uav_policy.networks import NetConfig
from uav_trainer import checkpoint
from uav_trainer.inprocess import run as run_inprocess
from uav_trainer.learner import LearnerConfig
from uav_trainer.replay import PRIORITY_FLOOR
from uav_trainer.training import TrainerConfig, Training, priority_beta


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
    # Every start records the machine: a seeded run is bit-exact only on the same kind of processor.
    starts = [json.loads(line) for line in (tmp_path / "machine.jsonl").read_text().splitlines()]
    assert [s["env_steps"] for s in starts] == [0, 120]
    assert starts[1]["cpu_kernels"] == torch.backends.cpu.get_cpu_capability() and starts[1]["torch"] == torch.__version__
    assert starts[1]["processor"] and starts[1]["torch_threads"] == torch.get_num_threads()


def test_the_lag_behind_the_replay_ratio_is_measured_and_warned_of(tmp_path):
    from uav_trainer.trainer_node import lag_warning

    t = Training(small_cfg(), tmp_path, log=lambda s: None)
    feed(t, 40)
    assert t.learning_lag() == (0, 0)  # before learning_starts nothing is due
    feed(t, 80, seed=1)  # 120 steps: (120 - 50) x 0.5 updates due, none done (acting ran on alone)
    assert t.learning_lag() == (35, 35)
    for _ in range(20):
        t.learn_once()
    assert t.learning_lag() == (15, 35)
    while t.learn_once():
        pass
    assert t.learning_lag() == (0, 35)
    t.close()
    assert lag_warning(0, 35, 0.5) is None and lag_warning(49, 60, 0.5) is None  # under 50 updates: quiet
    assert lag_warning(90, 1000, 0.25) is None  # under a tenth of what is due
    text = lag_warning(400, 1000, 0.25)
    assert text and "400 updates behind replay_ratio 0.25 (600 of 1000 done)" in text and "--max-rate-hz" in text


def test_a_stop_keeps_the_replay_memory_and_a_resume_learns_on_at_once(tmp_path):
    t = Training(small_cfg(), tmp_path, log=lambda s: None)
    feed(t, 120)
    while t.learn_once():
        pass
    path = t.save_checkpoint(final=True)
    assert (path / checkpoint.REPLAY_FILE).is_file()
    t.close()
    logs = []
    again = Training(small_cfg(), tmp_path, log=logs.append, resume=True)
    assert any(f"replay memory restored: {len(t.replay)} transitions" in line for line in logs), logs
    a, b = t.replay.sample(8), again.replay.sample(8)  # same memory, same sampling RNG
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    # Learning carries on at the uninterrupted run's cadence: 10 more steps allow 5 more updates.
    feed(t, 10, seed=1)
    feed(again, 10, seed=1)
    done = 0
    while again.learn_once():
        done += 1
    assert done == 5 and again.learner.updates == 40
    # A newer checkpoint removes the older one's replay file (400 MiB when full), keeping the checkpoint.
    newer = again.save_checkpoint()
    assert not (path / checkpoint.REPLAY_FILE).exists() and (path / "state.safetensors").is_file()
    assert not (newer / checkpoint.REPLAY_FILE).exists()
    again.close()


def test_the_replay_memory_is_not_written_after_the_budget_or_when_switched_off_and_a_bad_one_is_skipped(tmp_path):
    for name, cfg in (("budget", small_cfg(total_steps=100)), ("off", small_cfg(save_replay=False))):
        t = Training(cfg, tmp_path / name, log=lambda s: None)
        feed(t, 120)
        assert not (t.save_checkpoint(final=True) / checkpoint.REPLAY_FILE).exists(), name
        t.close()
    t = Training(small_cfg(), tmp_path / "bad", log=lambda s: None)
    feed(t, 120)
    (t.save_checkpoint(final=True) / checkpoint.REPLAY_FILE).write_bytes(b"\xff" * 64)  # corrupt on disk
    t.close()
    logs = []
    again = Training(small_cfg(), tmp_path / "bad", log=logs.append, resume=True)
    assert any("replay memory not restored" in line and "unreadable" in line for line in logs), logs
    assert len(again.replay) == 0 and again.env_steps == 120  # the checkpoint itself is still resumed
    again.close()


def test_steps_arriving_after_the_budget_are_not_recorded(tmp_path):
    """Over ROS, sim_node may deliver a step or two before trainer_node shuts down at its budget; the run
    still ends at exactly total_steps env steps, transitions and logged episode ends."""
    exact = Training(small_cfg(), tmp_path / "exact", log=lambda s: None)
    feed(exact, 100)
    t = Training(small_cfg(total_steps=100), tmp_path / "late", log=lambda s: None)
    feed(t, 103)  # the same first 100 steps; episodes end every 25 steps
    t.add_truncated(np.zeros((64, 64), np.float32))
    assert t.budget_done and t.env_steps == 100 and t.stats.episodes == 4
    assert len(t.replay) == len(exact.replay) and t.reward_sum == exact.reward_sum
    for run in (t, exact):
        run.close()
    assert (tmp_path / "late" / "episodes.csv").read_text() == (tmp_path / "exact" / "episodes.csv").read_text()


def test_the_weight_average_is_written_beside_the_policy_weights(tmp_path):
    t = Training(small_cfg(learner=LearnerConfig(batch_size=8, ema_decay=0.99)), tmp_path, log=lambda s: None)
    feed(t, 80)
    while t.learn_once():
        pass
    t.save_checkpoint()
    t.close()
    net = wio.load_file(tmp_path / "policy_cnn_ema.safetensors", t.net_cfg)
    for a, b in zip(net.parameters(), t.learner.ema.parameters(), strict=True):
        torch.testing.assert_close(a, b)
    assert any(not torch.equal(a, b) for a, b in zip(net.parameters(), t.learner.online.parameters(), strict=True))


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


def test_n_step_returns_reach_the_learner_and_out_of_range_values_are_refused(tmp_path):
    t = Training(small_cfg(n_step=3), tmp_path, log=lambda s: None)
    asked, sample = [], t.replay.sample
    t.replay.sample = lambda *a: asked.append(a) or sample(*a)
    learnt = []
    update = t.learner.update
    t.learner.update = lambda batch: learnt.append(batch) or update(batch)
    feed(t, 80)
    assert t.learn_once()
    assert len(asked) == 1 and asked[0][:4] == (8, 3, 0.99, 0.0)  # 3-step, uniform sampling
    assert "discount" in learnt[0] and set(learnt[0]["discount"]) <= {np.float32(0.99**k) for k in (1, 2, 3)}
    t.close()
    for bad in (0, 21):
        with pytest.raises(ValueError, match="n_step"):
            Training(small_cfg(n_step=bad), tmp_path / f"bad{bad}", log=lambda s: None)
        assert not (tmp_path / f"bad{bad}").exists()


def test_prioritized_replay_reaches_the_memory_and_the_learners_errors_come_back(tmp_path):
    t = Training(small_cfg(priority_alpha=0.6, priority_beta=0.4, priority_beta_steps=200), tmp_path, log=lambda s: None)
    asked, sample = [], t.replay.sample
    t.replay.sample = lambda *a: asked.append(a) or sample(*a)
    learnt, update = [], t.learner.update
    t.learner.update = lambda batch: learnt.append((batch, update(batch))) or learnt[-1][1]
    feed(t, 80)
    assert t.learn_once()
    # beta at 80 env steps: 0.4 + 0.6 * 80 / 200
    assert asked == [(8, 1, 0.99, 0.6, pytest.approx(0.64))]
    batch, out = learnt[0]
    assert "weight" in batch and batch["weight"].max() <= 1.0
    # Each sampled slot's priority is now its |TD error| + the floor (the last draw of a repeated slot).
    last = {int(i): e for i, e in zip(batch["index"], out["td_abs"], strict=True)}
    for i, e in last.items():
        assert t.replay.priority[i] == pytest.approx(e + PRIORITY_FLOOR)
    t.close()
    for bad in (dict(priority_alpha=-0.1), dict(priority_alpha=1.5), dict(priority_beta=2.0), dict(priority_beta_steps=-1)):
        where = tmp_path / f"bad{len(asked)}{sorted(bad.items())}"
        with pytest.raises(ValueError, match="priority"):
            Training(small_cfg(**bad), where, log=lambda s: None)
        assert not where.exists()


def test_the_importance_weight_exponent_rises_to_one():
    cfg = TrainerConfig(priority_alpha=0.6, priority_beta=0.4, priority_beta_steps=1000)
    assert [priority_beta(cfg, n) for n in (0, 500, 1000, 5000)] == pytest.approx([0.4, 0.7, 1.0, 1.0])
    assert priority_beta(dataclasses.replace(cfg, priority_beta_steps=0), 0) == 1.0


def test_inprocess_training_is_reproducible(tmp_path):
    cfg = TrainerConfig(model="sam", seed=5, total_steps=300, learning_starts=100, replay_ratio=0.25)
    weights = []
    for k in range(2):
        t = run_inprocess(cfg, str(tmp_path / f"r{k}"), log=lambda s: None)
        weights.append([p.detach().clone() for p in t.learner.online.parameters()])
        assert t.learner.updates == 50 and not math.isnan(t.last_loss)
        # Every weights file says which camera it was trained with (policy_node and evaluate read it).
        assert wio.read_file_camera(t.policy_weights_path) == 120.0
    for a, b in zip(*weights, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_pushed_acting_flies_the_copy_taken_at_each_push_interval_not_the_newest_network(tmp_path):
    from uav_policy.agent import Agent
    from uav_trainer.inprocess import PushedActing

    t = Training(small_cfg(), tmp_path, log=lambda s: None)
    feed(t, 200)
    agent = Agent(t.learner.online, t.net_cfg)
    pushed = PushedActing(agent, t.learner, every=4)
    initial = [p.detach().clone() for p in t.learner.online.parameters()]

    def same(net, params):
        return all(torch.equal(a, b) for a, b in zip(net.parameters(), params, strict=True))

    taken = initial
    for u in range(1, 11):
        assert t.learn_once()
        pushed.after_learning()
        if u % 4 == 0:
            taken = [p.detach().clone() for p in t.learner.online.parameters()]
        assert agent.net is not t.learner.online and same(agent.net, taken), u
        assert (u % 4 == 0) == same(t.learner.online, taken), u  # between pushes the learner has moved on
    assert not same(agent.net, initial)
    with pytest.raises(ValueError, match="push interval"):
        PushedActing(agent, t.learner, every=0)


def test_inprocess_acting_on_pushes_is_reproducible_and_changes_the_flight_once_learning_begins(tmp_path, monkeypatch, capsys):
    from uav_trainer import inprocess

    cfg = TrainerConfig(
        model="cnn", seed=2, total_steps=300, learning_starts=100, replay_ratio=0.5, epsilon_start=0.0, epsilon_end=0.0
    )
    logged = []
    short = dict(max_episode_steps=15)  # the greedy initial network would fly long episodes
    runs = [run_inprocess(cfg, str(tmp_path / "newest"), log=lambda s: None, **short)]
    for k in range(2):
        runs.append(run_inprocess(cfg, str(tmp_path / f"pushed{k}"), log=logged.append, act_on_pushes=20, **short))
    assert "acting on a copy of the network pushed every 20 updates, as policy_node beside trainer_node" in logged
    episodes = [(r.dir / "episodes.csv").read_text().splitlines() for r in runs]
    assert episodes[1] == episodes[2]  # reproducible
    before = [[e for e in ep[1:] if int(e.split(",")[1]) <= 100] for ep in episodes]
    assert before[0] == before[1] and len(before[0]) >= 3  # the same initial network flies until learning begins
    assert episodes[0] != episodes[1]  # then the greedy flights part
    for a, b in zip(runs[1].learner.online.parameters(), runs[2].learner.online.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    monkeypatch.setattr("sys.argv", ["inprocess", "--steps", "10", "--act-on-pushes", "-1"])
    with pytest.raises(SystemExit):
        inprocess.main()
    assert "--act-on-pushes must be >= 0 updates, got -1" in capsys.readouterr().err


@pytest.mark.parametrize("redraw", [False, True])
def test_layout_per_episode_flies_a_new_layout_after_every_crash(tmp_path, monkeypatch, redraw):
    import uav_sim.world as world_module
    import uav_trainer.inprocess as ip
    from uav_sim.simulator import Simulator

    made, start_yaws = [], []
    real = world_module.procedural_world
    monkeypatch.setattr(world_module, "procedural_world", lambda seed, **kw: made.append(seed) or real(seed, **kw))
    observe, enter = Simulator.observe, Simulator._enter  # the first episode's frame; every later layout
    monkeypatch.setattr(Simulator, "observe", lambda sim: start_yaws.append(sim.pose.yaw_rad) or observe(sim))
    monkeypatch.setattr(Simulator, "_enter", lambda sim, *a: enter(sim, *a) or start_yaws.append(sim.pose.yaw_rad))
    cfg = TrainerConfig(model="cnn", seed=0, total_steps=120, learning_starts=10**6, epsilon_start=1.0)
    t = ip.run(cfg, str(tmp_path), log=lambda s: None, layout_per_episode=True, hfov_deg=90.0, redraw_heading=redraw)
    assert wio.read_file_camera(t.policy_weights_path) == 90.0
    assert t.stats.episodes >= 3 and len(made) == t.stats.episodes + 1  # the first layout plus one per crash
    assert min(made) >= 1000 and len(set(made)) == len(made)  # never the held-out random:0..999
    assert len(start_yaws) == len(made)
    # Without redraw every layout starts at the seed's first heading draw; with it each episode draws anew.
    assert len(set(start_yaws)) == (len(made) if redraw else 1), start_yaws


def test_inprocess_time_limit_cuts_long_episodes(tmp_path):
    import csv

    cfg = TrainerConfig(model="cnn", seed=0, total_steps=80, learning_starts=10**6, epsilon_start=1.0)
    t = run_inprocess(cfg, str(tmp_path), log=lambda s: None, layout_per_episode=True, hfov_deg=90.0, max_episode_steps=4)
    rows = list(csv.DictReader(open(tmp_path / "episodes.csv")))
    cut = [int(r["length"]) for r in rows if r["end"] == "time_limit"]
    crashed = [int(r["length"]) for r in rows if r["end"] == "crash"]
    assert cut and set(cut) == {4} and all(n <= 4 for n in crashed)
    assert t.env_steps == 80 and t.collisions == len(crashed)


def test_inprocess_random_starts_begin_episodes_away_from_the_start_pose(tmp_path):
    import csv

    cfg = TrainerConfig(model="cnn", seed=1, total_steps=60, learning_starts=10**6, epsilon_start=1.0)
    logged = []
    run_inprocess(cfg, str(tmp_path), log=logged.append, layout_per_episode=True, max_episode_steps=3, random_start_fraction=1.0)
    episodes = len(list(csv.DictReader(open(tmp_path / "episodes.csv"))))
    # Every episode, the first included, began at a random place: the count covers the unfinished last one too.
    assert f"random starts: {episodes + 1} of {episodes + 1} episodes" in logged, logged[-3:]


def test_weight_snapshots_equal_the_shorter_run(tmp_path):
    cfg = TrainerConfig(model="sam", seed=5, total_steps=300, learning_starts=100, replay_ratio=0.25)
    short = run_inprocess(dataclasses.replace(cfg, total_steps=200), str(tmp_path / "short"), log=lambda s: None)
    logged = []
    long = run_inprocess(cfg, str(tmp_path / "long"), log=logged.append, save_weights_at=(200, 150))
    assert sorted(p.name for p in (tmp_path / "long").glob("policy_sam_step*.safetensors")) == [
        "policy_sam_step150.safetensors",
        "policy_sam_step200.safetensors",
    ]
    assert sum("weights snapshot" in line for line in logged) == 2
    # The first 200 steps of a 300-step run are the 200-step run, bit for bit.
    assert (tmp_path / "long" / "policy_sam_step200.safetensors").read_bytes() == short.policy_weights_path.read_bytes()
    assert long.policy_weights_path.read_bytes() != short.policy_weights_path.read_bytes()
    with pytest.raises(ValueError, match="save_weights_at"):
        run_inprocess(cfg, str(tmp_path / "bad"), log=lambda s: None, save_weights_at=(301,))
    assert not (tmp_path / "bad").exists()


def test_planned_snapshots_skip_steps_a_resumed_run_has_passed_and_are_written_once(tmp_path):
    t = Training(small_cfg(model="sam"), str(tmp_path), log=lambda s: None)
    try:
        t.env_steps = 150  # as after a resume from step 150
        t.plan_snapshots([200, 100, 300])
        t.env_steps = 250  # over ROS the learner may see a step late: the snapshot keeps its step's name
        assert t.save_due_snapshots() == [tmp_path / "policy_sam_step200.safetensors"]
        assert t.save_due_snapshots() == []
        assert sorted(p.name for p in tmp_path.glob("policy_sam_step*")) == ["policy_sam_step200.safetensors"]
        t.env_steps = 300
        assert t.save_due_snapshots() == [tmp_path / "policy_sam_step300.safetensors"]
        assert wio.read_file_config(tmp_path / "policy_sam_step300.safetensors").model == "sam"
    finally:
        t.close()


def test_sam_layer_sizes_reach_the_network_the_weights_file_and_the_evaluation(tmp_path):
    from uav_trainer.evaluate import evaluate_inprocess

    cfg = TrainerConfig(model="sam", seed=2, total_steps=60, learning_starts=30, d_model=24, heads=2, relational_blocks=2)
    t = run_inprocess(cfg, str(tmp_path), log=lambda s: None, hfov_deg=90.0)
    assert t.learner.updates > 0 and len(t.learner.online.relational_blocks) == 2
    made = wio.read_file_config(t.policy_weights_path)
    assert (made.d_model, made.heads, made.relational_blocks, made.mlp_hidden) == (24, 2, 2, NetConfig.mlp_hidden)
    r = evaluate_inprocess("sam", str(t.policy_weights_path), "basic", 20, seed=1)  # sizes from the file
    assert r.steps == 20


def test_input_size_reaches_the_network_the_camera_and_the_evaluation(tmp_path):
    from uav_trainer.evaluate import evaluate_inprocess

    cfg = TrainerConfig(model="sam", seed=2, total_steps=60, learning_starts=30, input_size_px=48)
    t = run_inprocess(cfg, str(tmp_path), log=lambda s: None, hfov_deg=90.0)
    assert t.learner.updates > 0  # the replay memory took the camera's 48 x 48 frames
    made = wio.read_file_config(t.policy_weights_path)
    assert (made.height, made.width) == (48, 48) and t.learner.online.grid_hw == (6, 6)
    assert wio.config_for("sam", t.policy_weights_path) == made
    # The evaluation renders at the file's input size: a 64 x 64 camera would not fit the network.
    r = evaluate_inprocess("sam", str(t.policy_weights_path), "basic", 20, seed=1)
    assert r.steps == 20


def test_the_frame_stack_reaches_the_network_the_replay_memory_and_the_evaluation(tmp_path):
    from uav_trainer.evaluate import architecture_args, evaluate_inprocess

    cfg = TrainerConfig(model="sam", seed=2, total_steps=60, learning_starts=30, frames=3)
    t = run_inprocess(cfg, str(tmp_path), log=lambda s: None, hfov_deg=90.0)
    assert t.learner.updates > 0 and t.replay.frames == 3 and t.learner.online.trunk.net[0].in_channels == 3
    assert wio.read_file_config(t.policy_weights_path).frames == 3
    assert architecture_args("sam", str(t.policy_weights_path)) == ["frame_stack:=3"]  # policy_node's parameter
    assert evaluate_inprocess("sam", str(t.policy_weights_path), "basic", 20, seed=1).steps == 20  # stacks 3 frames
    with pytest.raises(ValueError, match=r"frames in \[1, 16\]"):
        NetConfig(frames=17).validate()  # nor may a weights file's header ask for more


def test_a_two_layer_trunk_gives_sam_16_by_16_nodes_and_the_file_carries_it(tmp_path, monkeypatch, capsys):
    from uav_trainer import inprocess
    from uav_trainer.evaluate import architecture_args, evaluate_inprocess

    cfg = TrainerConfig(model="sam", seed=2, total_steps=60, learning_starts=30, conv_channels=(16, 32))
    t = run_inprocess(cfg, str(tmp_path), log=lambda s: None, hfov_deg=90.0)
    assert t.learner.updates > 0 and t.learner.online.grid_hw == (16, 16)
    assert t.learner.online.coords.shape == (256, 2)
    made = wio.read_file_config(t.policy_weights_path)
    assert made.conv_channels == (16, 32) and wio.config_for("sam", t.policy_weights_path) == made
    assert architecture_args("sam", str(t.policy_weights_path)) == []  # policy_node takes layer sizes from the file
    assert evaluate_inprocess("sam", str(t.policy_weights_path), "basic", 20, seed=1).steps == 20
    with pytest.raises(ValueError, match="7 conv layers leave nothing of a 64x64 input .* use at most 6"):
        NetConfig(conv_channels=(8,) * 7).validate()  # nor may a weights file's header ask for more
    for bad, said in (["16", "0"], "conv_channels must be integer"), (["8"] * 7, "7 conv layers leave nothing"):
        monkeypatch.setattr("sys.argv", ["inprocess", "--steps", "10", "--conv-channels", *bad])
        with pytest.raises(SystemExit) as e:
            inprocess.main()
        assert e.value.code == 2 and f"--conv-channels: {said}" in capsys.readouterr().err


def test_training_refuses_a_camera_whose_reward_window_sees_the_floor(tmp_path, monkeypatch, capsys):
    from uav_sim.simulator import RewardWindowError
    from uav_trainer import inprocess

    run_dir = tmp_path / "wide"
    monkeypatch.setattr("sys.argv", ["inprocess", "--steps", "10", "--hfov-deg", "150", "--run-dir", str(run_dir)])
    with pytest.raises(SystemExit) as e:
        inprocess.main()
    said = capsys.readouterr().err
    assert e.value.code == 2 and "hfov_deg=150 with 64x64 images shows the floor 1.43 m" in said
    assert "smaller reward_window_fraction (now 0.2)" in said
    cfg = TrainerConfig(model="cnn", seed=0, total_steps=10)
    with pytest.raises(RewardWindowError, match="floor 1.43 m ahead"):
        run_inprocess(cfg, str(run_dir), log=lambda s: None, hfov_deg=150.0, layout_per_episode=True)
    assert not run_dir.exists()  # refused before anything was written
    # A window of 5 x 5 px keeps about the 120 degree camera's angle: the floor is 4.3 m ahead, training runs.
    lines = []
    t = run_inprocess(cfg, str(run_dir), log=lines.append, hfov_deg=150.0, layout_per_episode=True, reward_window_fraction=0.078)
    assert t.env_steps == 10 and any("reward the paper's, window 0.078;" in s for s in lines)
    # The weights record the window (evaluate measures the reward with it); the paper's is not recorded.
    assert wio.read_file_window(t.policy_weights_path) == 0.078 and wio.read_file_camera(t.policy_weights_path) == 150.0
    t = run_inprocess(cfg, str(tmp_path / "paper"), log=lambda s: None, hfov_deg=120.0, layout_per_episode=True)
    assert wio.read_file_window(t.policy_weights_path) is None
    monkeypatch.setattr("sys.argv", ["inprocess", "--steps", "10", "--reward-window-fraction", "0"])
    with pytest.raises(SystemExit) as e:
        inprocess.main()
    assert e.value.code == 2 and "--reward-window-fraction must lie in (0, 1], got 0.0" in capsys.readouterr().err


def test_validation_keeps_the_best_network_without_changing_training(tmp_path):
    import csv

    from uav_policy import weights as wio
    from uav_policy.networks import NetConfig
    from uav_trainer.inprocess import Validation

    cfg = TrainerConfig(model="sam", seed=5, total_steps=300, learning_starts=100, replay_ratio=0.25, epsilon_decay_steps=100)
    plain = run_inprocess(cfg, str(tmp_path / "plain"), log=lambda s: None)
    val = lambda t: Validation(t, every=100, worlds=("random:200", "random:201"), steps=40, log=lambda s: None)  # noqa: E731
    selected = run_inprocess(cfg, str(tmp_path / "val"), log=lambda s: None, validation=val)
    for a, b in zip(plain.learner.online.parameters(), selected.learner.online.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)  # validation flights leave training untouched
    rows = list(csv.DictReader(open(tmp_path / "val" / "validation.csv")))
    assert [int(r["env_steps"]) for r in rows] == [100, 200, 300] and all(int(r["steps"]) == 80 for r in rows)
    best = [(int(r["crashes"]), -float(r["mean_reward"])) for r in rows]
    flags = [int(r["best"]) for r in rows]
    assert flags[0] == 1 and all(f == int(best[i] < min(best[:i])) for i, f in enumerate(flags) if i > 0)
    wio.load_file(tmp_path / "val" / "policy_sam_best.safetensors", NetConfig(model="sam"))
    resumed = val(selected)  # a resumed run competes with the best it already saved
    assert resumed.best is not None and (resumed.best[0], -resumed.best[1]) == min(
        b for b, f in zip(best, flags, strict=True) if f
    )
    resumed.close()


def test_clearance_penalty_is_added_to_the_papers_reward_only_when_asked(tmp_path):
    from uav_sim.reward import step_reward

    frame = np.full((64, 64), 8.0, dtype=np.float32)
    frame[32, 0] = 0.5  # something beside the path, outside beta's window
    paper = Training(small_cfg(), tmp_path / "a", log=lambda s: None)
    shaped = Training(small_cfg(clearance_m=1.0, clearance_weight=4.0), tmp_path / "b", log=lambda s: None)
    for t in (paper, shaped):
        t.add_first(frame)
    assert paper.add_step(0, 8.0, False, frame) == step_reward(8.0, False)
    assert shaped.add_step(0, 8.0, False, frame) == step_reward(8.0, False) - 2.0
    assert shaped.add_step(0, 8.0, True, frame) == -10.0  # a collision's frame is the next episode's: no penalty
    paper.close()
    shaped.close()


def test_turn_penalty_applies_to_turning_actions_only_when_asked(tmp_path):
    from uav_sim.reward import step_reward

    frame = np.full((64, 64), 8.0, dtype=np.float32)
    paper = Training(small_cfg(), tmp_path / "a", log=lambda s: None)
    shaped = Training(small_cfg(turn_penalty=0.75), tmp_path / "b", log=lambda s: None)
    for t in (paper, shaped):
        t.add_first(frame)
    base = step_reward(8.0, False)
    assert [paper.add_step(a, 8.0, False, frame) for a in range(4)] == [base] * 4
    assert [shaped.add_step(a, 8.0, False, frame) for a in range(4)] == [base, base - 0.75, base - 0.75, base]
    assert shaped.add_step(1, 8.0, True, frame) == -10.0  # a crash costs the same either way
    paper.close()
    shaped.close()


def test_a_time_limit_ends_the_episode_and_stores_no_transition(tmp_path):
    frames = [np.full((64, 64), k + 1.0, dtype=np.float32) for k in range(6)]
    t = Training(small_cfg(), tmp_path, log=lambda s: None)
    t.add_first(frames[0])
    for k in (1, 2):
        t.add_step(0, 8.0, False, frames[k])
    t.add_truncated(frames[3])  # the step from frames[2] was cut: frames[3] starts the next episode
    for k in (4, 5):
        t.add_step(3, 8.0, False, frames[k])
    assert (t.env_steps, t.stats.episodes, t.collisions) == (5, 1, 0)
    batch = t.replay.sample(200)
    pairs = {(float(s[-1, 0, 0]), float(n[-1, 0, 0])) for s, n in zip(batch["state"], batch["next_state"], strict=True)}
    assert pairs == {(1.0, 2.0), (2.0, 3.0), (4.0, 5.0), (5.0, 6.0)}  # nothing from frame 3 into frame 4's episode
    assert not batch["done"].any()
    t.close()
    rows = (tmp_path / "episodes.csv").read_text().splitlines()
    assert rows[0] == "episode,env_step,length,reward,end" and len(rows) == 2
    assert rows[1].startswith("1,3,3,") and rows[1].endswith(",time_limit")  # two learnt steps and the cut one


def test_a_deterministic_policy_at_a_fixed_start_repeats_its_crash_site():
    """Why evaluate reports crash sites: flying straight ahead in a small room from the same start
    pose crashes at one site every lap; random start headings spread the crashes out."""
    from uav_trainer.evaluate import evaluate_inprocess

    class Straight(torch.nn.Module):  # constant Q: the agent always picks action 3 (2 m/s ahead)
        def forward(self, x):
            return torch.tensor([[0.0, 0.0, 0.0, 1.0]]).expand(x.shape[0], 4), None

    fixed = evaluate_inprocess("cnn", "", "tests/worlds/small.yaml", 300, net=Straight())
    varied = evaluate_inprocess("cnn", "", "tests/worlds/small.yaml", 300, net=Straight(), start_yaw_jitter_deg=180.0)
    assert fixed.crashes >= 3 and fixed.crash_sites == 1
    assert varied.crash_sites > 1


def test_the_crash_log_says_where_when_and_from_which_start(tmp_path):
    from uav_trainer.evaluate import CRASH_FIELDS, evaluate_inprocess
    from uav_trainer.evaluate import main as evaluate_main

    class Straight(torch.nn.Module):  # constant Q: the agent always picks action 3 (2 m/s ahead)
        def forward(self, x):
            return torch.tensor([[0.0, 0.0, 0.0, 1.0]]).expand(x.shape[0], 4), None

    fly = lambda log, **kw: evaluate_inprocess("cnn", "", "tests/worlds/small.yaml", 300, net=Straight(), crash_log=log, **kw)  # noqa: E731
    fixed, varied = [], []
    r = fly(fixed)
    assert len(fixed) == r.crashes >= 3 and all(tuple(row) == CRASH_FIELDS for row in fixed)
    # From the fixed start every lap is the same: same length, same place, same start heading.
    assert fixed[0]["episode_step"] == fixed[0]["step"] and {row["episode_step"] for row in fixed} == {fixed[0]["episode_step"]}
    assert [row["step"] for row in fixed] == [fixed[0]["step"] * (i + 1) for i in range(len(fixed))]
    assert len({(row["x_m"], row["y_m"]) for row in fixed}) == 1 and {row["start_yaw_deg"] for row in fixed} == {0.0}
    assert {row["action"] for row in fixed} == {"a3_forward_2mps"}
    r = fly(varied, start_yaw_jitter_deg=180.0)
    assert len(varied) == r.crashes and len({row["start_yaw_deg"] for row in varied}) > 1
    assert sum(row["episode_step"] for row in varied) <= 300
    with pytest.raises(SystemExit) as e:
        evaluate_main(["--crash-log", "--out", str(tmp_path)])
    assert e.value.code == 2  # the ROS measurement has no crash log


def test_the_reward_is_described_with_its_extensions():
    from uav_trainer.training import reward_description

    assert reward_description(TrainerConfig()) == "the paper's"
    both = TrainerConfig(turn_penalty=1.0, clearance_m=1.5, clearance_weight=4.0)
    assert reward_description(both) == "the paper's - 1 per turning step - clearance penalty (up to 4 within 1.5 m)"


def test_inprocess_world_every_flies_the_world_between_layouts(tmp_path, monkeypatch):
    import uav_trainer.inprocess as ip
    from uav_sim.simulator import Simulator

    entered = []
    enter = Simulator._enter
    monkeypatch.setattr(Simulator, "_enter", lambda sim, *a: enter(sim, *a) or entered.append(sim.world.name))
    cfg = TrainerConfig(model="cnn", seed=0, total_steps=60, learning_starts=10**6, epsilon_start=1.0)
    ip.run(cfg, str(tmp_path), world="complex", log=lambda s: None, layout_per_episode=True, max_episode_steps=3, world_every=2)
    # The first episode is a layout; from then on every second episode flies --world.
    assert len(entered) >= 10 and entered[0::2] == ["complex"] * len(entered[0::2])
    assert all(n.startswith("random:") for n in entered[1::2])
    with pytest.raises(ValueError, match="layout_per_episode"):
        ip.run(cfg, str(tmp_path / "no"), log=lambda s: None, world_every=2)
    # --layout-partitions: the layouts are random_partitions:SEED, the mixed world stays as it is.
    entered.clear()
    ip.run(
        cfg,
        str(tmp_path / "p"),
        world="complex",
        log=lambda s: None,
        layout_per_episode=True,
        max_episode_steps=3,
        world_every=2,
        partitions=True,
    )
    assert entered[0::2] == ["complex"] * len(entered[0::2]) and all(n.startswith("random_partitions:") for n in entered[1::2])
    with pytest.raises(ValueError, match="layout_per_episode"):
        ip.run(cfg, str(tmp_path / "no2"), log=lambda s: None, partitions=True)


def test_shift_augmentation_reaches_the_learner_from_the_command_line(tmp_path, monkeypatch, capsys):
    from uav_trainer import inprocess

    run = ["inprocess", "--model", "cnn", "--steps", "40", "--learning-starts", "20", "--run-dir", str(tmp_path / "r")]
    made = []
    monkeypatch.setattr(inprocess, "Training", lambda *a, **k: made.append(Training(*a, **k)) or made[-1])
    monkeypatch.setattr("sys.argv", [*run, "--augment-shift", "3"])
    inprocess.main()
    assert made[0].cfg.learner.augment_shift_px == 3 and made[0].learner.updates > 0
    assert "uniform replay, 1-step returns, states shifted by up to 3 px" in capsys.readouterr().out
    assert (tmp_path / "r" / "policy_cnn.safetensors").is_file()
    monkeypatch.setattr("sys.argv", [*run, "--augment-shift", "9"])
    with pytest.raises(SystemExit) as e:
        inprocess.main()
    assert e.value.code == 2 and "--augment-shift must lie in [0, 8] px, got 9" in capsys.readouterr().err


def test_export_checkpoint_script_writes_the_runs_own_weights_from_its_last_checkpoint(tmp_path, capsys):
    from conftest import script_module

    script = script_module("export_checkpoint")
    t = Training(small_cfg(), tmp_path, log=lambda s: None)
    feed(t, 120)
    while t.learn_once():
        pass
    last = t.save_checkpoint()
    t.close()
    assert script.main([str(last)]) == 0
    out = tmp_path / "policy_cnn_step120.safetensors"
    assert out.read_bytes() == (tmp_path / "policy_cnn.safetensors").read_bytes()  # camera and window copied too
    assert script.main([str(last), "--net", "target", "--out-dir", str(tmp_path / "x")]) == 0
    target = wio.load_file(tmp_path / "x" / "policy_cnn_step120_target.safetensors", NetConfig(model="cnn"))
    for a, b in zip(target.parameters(), t.learner.target.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    capsys.readouterr()
    assert script.main([str(tmp_path)]) == 2  # the run folder, not a checkpoint
    assert "export_checkpoint:" in capsys.readouterr().err
