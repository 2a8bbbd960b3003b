import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
import safetensors.numpy
import torch

from conftest import SMALL_WORLD, run_to_exit
from uav_policy import weights as wio
from uav_policy.networks import NetConfig
from uav_sim.simulator import SimConfig
from uav_sim.world import WorldChoice
from uav_trainer import checkpoint
from uav_trainer.inprocess import run
from uav_trainer.teacher import TeacherConfig
from uav_trainer.training import RunDirError, Training
from uav_trainer.training_config import LearnerConfig, TrainerConfig


def run_inprocess(cfg, run_dir, log=print, world="basic", mix_world_every=0, hfov_deg=120.0, window=0.2, **sim):
    """The in-process trainer in `world` behind a camera of `hfov_deg` with random start headings."""
    sim_cfg = SimConfig(
        seed=cfg.seed,
        hfov_deg=hfov_deg,
        reward_window_fraction=window,
        start_yaw_jitter_deg=180.0,
        image_width=cfg.input_size_px,
        image_height=cfg.input_size_px,
        **sim,
    )
    worlds = WorldChoice(world=world, mix_world="complex", mix_world_every=mix_world_every)
    return run(cfg, str(run_dir), sim_cfg, worlds, log=log)


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
    # Every checkpoint journals the replay memory: it is back, and learning goes on at once.
    assert len(again.replay) == len(t.replay) and not again.can_learn()  # 35 updates for 120 steps: all made
    feed(again, 2, seed=1)
    assert again.can_learn()
    again.close()
    # Every start records the machine: a seeded run is bit-exact only on the same kind of processor.
    starts = [json.loads(line) for line in (tmp_path / "machine.jsonl").read_text().splitlines()]
    assert [s["env_steps"] for s in starts] == [0, 120]
    assert starts[1]["cpu_kernels"] == torch.backends.cpu.get_cpu_capability() and starts[1]["torch"] == torch.__version__
    assert starts[1]["processor"] and starts[1]["torch_threads"] == torch.get_num_threads()


def journal(t: Training) -> list:
    return sorted((t.checkpoint_dir / checkpoint.JOURNAL_DIR).glob("seg-*.safetensors"))


def test_a_stop_keeps_the_replay_memory_and_a_resume_learns_on_at_once(tmp_path):
    t = Training(small_cfg(), tmp_path, log=lambda s: None)
    for k in range(6):  # a checkpoint every 10 updates, each with the frames since the one before
        feed(t, 20, seed=10 + k)
        while t.learn_once():
            pass
    path = t.save_checkpoint(final=True)
    assert len(journal(t)) >= 3 and not (path / checkpoint.SEGMENT_FILE).exists()
    spans = [tuple(int(v) for v in safetensors.numpy.load_file(str(f))["span"]) for f in journal(t)]
    assert spans[0][0] == 0 and spans[-1][1] == t.replay.writes == 6 * 21
    assert all(b[0] == a[1] - 1 for a, b in zip(spans, spans[1:], strict=False)), spans  # each frame once, and the one before
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
    again.close()


def test_a_killed_run_resumes_from_the_journal_and_learns_on_at_once(tmp_path):
    """SIGKILL: no final checkpoint. The last periodic one (every 10 updates here, at least every 120 s in
    a run) and its journal bring back the memory it had seen; only the steps after it are lost."""
    t = Training(small_cfg(), tmp_path, log=lambda s: None)
    feed(t, 120)
    while t.learn_once():
        pass
    kept = checkpoint.latest(t.checkpoint_dir)
    assert t.learner.updates == 35 and kept.name.startswith("ckpt-000000030")
    at_checkpoint = checkpoint.read_meta(kept)[0]["counters"]["replay_writes"]
    feed(t, 7, seed=2)  # lost with the process
    logs = []
    again = Training(small_cfg(), tmp_path, log=logs.append, resume=True)
    assert again.replay.writes == at_checkpoint and again.env_steps == at_checkpoint - 1
    assert any(f"replay memory restored: {len(again.replay)} transitions" in line for line in logs), logs
    assert again.learner.updates == 30 and again.can_learn()  # no refill: learning goes on at once
    feed(again, 10, seed=1)
    done = 0
    while again.learn_once():
        done += 1
    assert done == 5 + 5, "the replay ratio from the checkpoint on: 30 + 0.5 x (110 - 50 + 10) - 30"
    again.close()


def test_a_fresh_run_beside_an_earlier_runs_checkpoints_keeps_its_own(tmp_path):
    """An earlier run's checkpoints in the folder (a start without resume) may be named higher: the newest
    checkpoint is kept all the same, `latest` names it and its replay segment joins the journal."""
    for n in (7, 8, 9):
        (tmp_path / "checkpoints" / f"ckpt-00000999{n}-000099999").mkdir(parents=True)
    t = Training(small_cfg(), tmp_path, log=lambda s: None)
    feed(t, 60)
    t.learn_once()
    path = t.save_checkpoint()
    assert checkpoint.latest(t.checkpoint_dir) == path and (path / "state.safetensors").is_file()
    assert [f.name for f in journal(t)] == ["seg-000000000000-000000000061.safetensors"]
    assert len(list(t.checkpoint_dir.glob("ckpt-*"))) == checkpoint.KEEP
    t.close()


def test_the_replay_journal_goes_after_the_budget_or_when_switched_off_and_a_bad_one_is_dropped(tmp_path):
    for name, cfg in (("budget", small_cfg(total_steps=100)), ("off", small_cfg(save_replay=False))):
        t = Training(cfg, tmp_path / name, log=lambda s: None)
        feed(t, 120)
        while t.learn_once():
            pass
        t.save_checkpoint(final=True)
        assert not journal(t), name
        t.close()
    t = Training(small_cfg(), tmp_path / "bad", log=lambda s: None)
    feed(t, 120)
    while t.learn_once():
        pass
    t.save_checkpoint(final=True)
    journal(t)[0].write_bytes(b"\xff" * 64)  # corrupt on disk
    t.close()
    logs = []
    again = Training(small_cfg(), tmp_path / "bad", log=logs.append, resume=True)
    assert any("replay memory not restored" in line and "unreadable" in line for line in logs), logs
    assert len(again.replay) == 0 and again.env_steps == 120  # the checkpoint itself is still resumed
    assert not journal(again), "a broken journal is dropped: the refilled memory journals afresh"
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
    for r in (t, exact):
        r.close()
    assert (tmp_path / "late" / "episodes.csv").read_text() == (tmp_path / "exact" / "episodes.csv").read_text()


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
        t = run_inprocess(cfg, tmp_path / f"r{k}", log=lambda s: None)
        weights.append([p.detach().clone() for p in t.learner.online.parameters()])
        assert t.learner.updates == 50 and not math.isnan(t.last_loss)
        # Every weights file says which camera it was trained with (policy_node and evaluate read it).
        assert wio.read_file_camera(t.policy_weights_path) == 120.0
    for a, b in zip(*weights, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_a_new_layout_every_episode_never_the_held_out_ones_all_at_the_runs_first_heading(tmp_path, monkeypatch):
    import uav_sim.world as world_module
    from uav_sim.simulator import Simulator

    made, start_yaws = [], []
    real = world_module.procedural_world
    monkeypatch.setattr(world_module, "procedural_world", lambda seed, **kw: made.append(seed) or real(seed, **kw))
    observe, enter = Simulator.observe, Simulator._enter  # the first episode's frame; every later layout
    monkeypatch.setattr(Simulator, "observe", lambda sim: start_yaws.append(sim.pose.yaw_rad) or observe(sim))
    monkeypatch.setattr(Simulator, "_enter", lambda sim, *a, **k: enter(sim, *a, **k) or start_yaws.append(sim.pose.yaw_rad))
    cfg = TrainerConfig(model="cnn", seed=0, total_steps=120, learning_starts=10**6, epsilon_end=1.0)  # random flight
    t = run_inprocess(cfg, tmp_path, log=lambda s: None, world="random_each_episode", hfov_deg=90.0)
    assert wio.read_file_camera(t.policy_weights_path) == 90.0
    assert t.stats.episodes >= 3 and len(made) == t.stats.episodes + 1  # the first layout plus one per crash
    assert min(made) >= 1000 and len(set(made)) == len(made)  # never the held-out random:0..999
    assert len(start_yaws) == len(made) and len(set(start_yaws)) == 1, start_yaws


def test_inprocess_time_limit_cuts_long_episodes(tmp_path):
    import csv

    cfg = TrainerConfig(model="cnn", seed=0, total_steps=80, learning_starts=10**6, epsilon_end=1.0)
    t = run_inprocess(cfg, tmp_path, log=lambda s: None, world="random_each_episode", hfov_deg=90.0, max_episode_steps=4)
    rows = list(csv.DictReader(open(tmp_path / "episodes.csv")))
    cut = [int(r["length"]) for r in rows if r["end"] == "time_limit"]
    crashed = [int(r["length"]) for r in rows if r["end"] == "crash"]
    assert cut and set(cut) == {4} and all(n <= 4 for n in crashed)
    assert t.env_steps == 80 and t.collisions == len(crashed)


def test_weight_snapshots_equal_the_shorter_run(tmp_path):
    # Given schedules (the defaults follow the budget, so a shorter budget would explore for fewer steps).
    cfg = TrainerConfig(model="sam", seed=5, total_steps=300, learning_starts=100, epsilon_decay_steps=100, snapshots=2)
    short = run_inprocess(dataclasses.replace(cfg, total_steps=290, snapshots=0), tmp_path / "short", log=lambda s: None)
    logged = []
    long = run_inprocess(cfg, tmp_path / "long", log=logged.append)
    assert sorted(p.name for p in (tmp_path / "long").glob("policy_sam_step*.safetensors")) == [
        "policy_sam_step280.safetensors",
        "policy_sam_step290.safetensors",
    ]
    assert sum("weights snapshot" in line for line in logged) == 2
    # The first 290 steps of a 300-step run are the 290-step run, bit for bit.
    assert (tmp_path / "long" / "policy_sam_step290.safetensors").read_bytes() == short.policy_weights_path.read_bytes()
    assert long.policy_weights_path.read_bytes() != short.policy_weights_path.read_bytes()


def test_snapshots_are_a_thirtieth_of_the_budget_apart_and_need_a_budget(tmp_path):
    from uav_trainer.training_config import snapshot_steps

    assert snapshot_steps(9, 30000) == list(range(21000, 30000, 1000))  # the shipped recipe's
    assert snapshot_steps(0, 0) == []
    with pytest.raises(ValueError, match="'snapshots'=9 needs a step budget"):
        TrainerConfig(snapshots=9).validate()
    t = Training(small_cfg(model="sam", total_steps=300, snapshots=2), tmp_path, log=lambda s: None)
    try:
        feed(t, 285)  # learning_starts 50, so updates happened
        assert t.learn_due() == [tmp_path / "policy_sam_step280.safetensors"]
        assert t.learn_due() == []  # written once
        assert wio.read_file_config(tmp_path / "policy_sam_step280.safetensors").model == "sam"
    finally:
        t.close()


def test_sam_layer_sizes_reach_the_network_the_weights_file_and_the_evaluation(tmp_path):
    from uav_eval.flights import FlightSpec, evaluate_inprocess

    cfg = TrainerConfig(model="sam", seed=2, total_steps=60, learning_starts=30, d_model=24, heads=2, relational_blocks=2)
    t = run_inprocess(cfg, tmp_path, log=lambda s: None, hfov_deg=90.0)
    assert t.learner.updates > 0 and len(t.learner.online.relational_blocks) == 2
    made = wio.read_file_config(t.policy_weights_path)
    assert (made.d_model, made.heads, made.relational_blocks, made.mlp_hidden) == (24, 2, 2, NetConfig.mlp_hidden)
    r = evaluate_inprocess(FlightSpec("sam", str(t.policy_weights_path), "basic", 20, seed=1))  # sizes from the file
    assert r.steps == 20


def test_input_size_reaches_the_network_the_camera_and_the_evaluation(tmp_path):
    from uav_eval.flights import FlightSpec, evaluate_inprocess

    cfg = TrainerConfig(model="sam", seed=2, total_steps=60, learning_starts=30, input_size_px=48)
    t = run_inprocess(cfg, tmp_path, log=lambda s: None, hfov_deg=90.0)
    assert t.learner.updates > 0  # the replay memory took the camera's 48 x 48 frames
    made = wio.read_file_config(t.policy_weights_path)
    assert (made.height, made.width) == (48, 48) and t.learner.online.grid_hw == (6, 6)
    assert wio.config_for("sam", t.policy_weights_path) == made
    # The evaluation renders at the file's input size: a 64 x 64 camera would not fit the network.
    r = evaluate_inprocess(FlightSpec("sam", str(t.policy_weights_path), "basic", 20, seed=1))
    assert r.steps == 20


def test_the_frame_stack_reaches_the_network_the_replay_memory_and_the_evaluation(tmp_path):
    from uav_eval.flights import FlightSpec, architecture_args, evaluate_inprocess

    cfg = TrainerConfig(model="sam", seed=2, total_steps=60, learning_starts=30, frames=3)
    t = run_inprocess(cfg, tmp_path, log=lambda s: None, hfov_deg=90.0)
    assert t.learner.updates > 0 and t.replay.frames == 3 and t.learner.online.trunk.net[0].in_channels == 3
    assert wio.read_file_config(t.policy_weights_path).frames == 3
    assert architecture_args("sam", str(t.policy_weights_path)) == ["frame_stack:=3"]  # policy_node's parameter
    assert evaluate_inprocess(FlightSpec("sam", str(t.policy_weights_path), "basic", 20, seed=1)).steps == 20  # stacks 3 frames
    with pytest.raises(ValueError, match=r"frames in \[1, 16\]"):
        NetConfig(frames=17).validate()  # nor may a weights file's header ask for more


def test_a_two_layer_trunk_gives_sam_16_by_16_nodes_and_the_file_carries_it(tmp_path, monkeypatch, capsys):
    from uav_eval.flights import FlightSpec, architecture_args, evaluate_inprocess
    from uav_trainer import inprocess

    cfg = TrainerConfig(model="sam", seed=2, total_steps=60, learning_starts=30, conv_channels=(16, 32))
    t = run_inprocess(cfg, tmp_path, log=lambda s: None, hfov_deg=90.0)
    assert t.learner.updates > 0 and t.learner.online.grid_hw == (16, 16)
    assert t.learner.online.coords.shape == (256, 2)
    made = wio.read_file_config(t.policy_weights_path)
    assert made.conv_channels == (16, 32) and wio.config_for("sam", t.policy_weights_path) == made
    assert architecture_args("sam", str(t.policy_weights_path)) == []  # policy_node takes layer sizes from the file
    assert evaluate_inprocess(FlightSpec("sam", str(t.policy_weights_path), "basic", 20, seed=1)).steps == 20
    with pytest.raises(ValueError, match="7 conv layers leave nothing of a 64x64 input .* use at most 6"):
        NetConfig(conv_channels=(8,) * 7).validate()  # nor may a weights file's header ask for more
    for bad, said in (["16", "0"], "conv_channels must be integer"), (["8"] * 7, "7 conv layers leave nothing"):
        with pytest.raises(SystemExit) as e:
            inprocess.main(["--steps", "10", "--conv-channels", *bad, "--run-dir", str(tmp_path / "bad")])
        assert e.value.code == 2 and f"'conv_channels'=[{', '.join(bad)}]: {said}" in capsys.readouterr().err


def test_training_refuses_a_camera_whose_reward_window_sees_the_floor(tmp_path, capsys):
    from uav_sim.simulator import RewardWindowError
    from uav_trainer import inprocess

    run_dir = tmp_path / "wide"
    with pytest.raises(SystemExit) as e:
        inprocess.main(
            ["--steps", "30", "--recipe", "wide150", "--sim-arg", "reward_window_fraction:=0.2", "--run-dir", str(run_dir)]
        )
    said = capsys.readouterr().err
    assert e.value.code == 2 and "hfov_deg=150 with 64x64 images shows the floor 1.43 m" in said
    assert "smaller reward_window_fraction (now 0.2)" in said
    cfg = TrainerConfig(model="cnn", seed=0, total_steps=10)
    with pytest.raises(RewardWindowError, match="floor 1.43 m ahead"):
        run_inprocess(cfg, run_dir, log=lambda s: None, hfov_deg=150.0, world="random_each_episode")
    assert not run_dir.exists()  # refused before anything was written
    # A window of 5 x 5 px keeps about the 120 degree camera's angle: the floor is 4.3 m ahead, training runs.
    lines = []
    t = run_inprocess(cfg, run_dir, log=lines.append, hfov_deg=150.0, window=0.078, world="random_each_episode")
    assert t.env_steps == 10 and any("reward the paper's, window 0.078" in s for s in lines)
    # The weights record the window (evaluate measures the reward with it); the paper's is not recorded.
    assert wio.read_file_window(t.policy_weights_path) == 0.078 and wio.read_file_camera(t.policy_weights_path) == 150.0
    t = run_inprocess(cfg, tmp_path / "paper", log=lambda s: None, hfov_deg=120.0, world="random_each_episode")
    assert wio.read_file_window(t.policy_weights_path) is None
    with pytest.raises(SystemExit) as e:
        inprocess.main(["--steps", "30", "--sim-arg", "reward_window_fraction:=0.0"])
    assert e.value.code == 2 and "'reward_window_fraction'=0.0 is outside [0.01, 1.0]" in capsys.readouterr().err


def test_turn_penalty_applies_to_turning_actions_only_when_asked(tmp_path):
    from uav_sim.reward import step_reward

    frame = np.full((64, 64), 8.0, dtype=np.float32)
    paper = Training(small_cfg(), tmp_path / "a", log=lambda s: None)
    shaped = Training(small_cfg(turn_penalty=0.75), tmp_path / "b", log=lambda s: None)
    for t in (paper, shaped):
        t.add_first(frame)
    base = step_reward(8.0, False)
    assert base == pytest.approx(3.0 + 8.0 / 5)  # the paper's safe-step reward at 8 m, by hand
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
    from uav_eval.flights import FlightSpec, evaluate_inprocess

    class Straight(torch.nn.Module):  # constant Q: the agent always picks action 3 (2 m/s ahead)
        def forward(self, x):
            return torch.tensor([[0.0, 0.0, 0.0, 1.0]]).expand(x.shape[0], 4), None

    fixed = evaluate_inprocess(FlightSpec("cnn", "", SMALL_WORLD, 300), Straight())
    varied = evaluate_inprocess(FlightSpec("cnn", "", SMALL_WORLD, 300, start_yaw_jitter_deg=180.0), Straight())
    assert fixed.crashes >= 3 and fixed.crash_sites == 1
    assert varied.crash_sites > 1


def test_the_crash_log_says_where_when_and_from_which_start(tmp_path):
    from uav_eval.evaluate import main as evaluate_main
    from uav_eval.flights import CRASH_FIELDS, FlightSpec, evaluate_inprocess

    class Straight(torch.nn.Module):  # constant Q: the agent always picks action 3 (2 m/s ahead)
        def forward(self, x):
            return torch.tensor([[0.0, 0.0, 0.0, 1.0]]).expand(x.shape[0], 4), None

    fly = lambda log, **kw: evaluate_inprocess(FlightSpec("cnn", "", SMALL_WORLD, 300, **kw), Straight(), crash_log=log)  # noqa: E731
    fixed, varied = [], []
    r = fly(fixed)
    assert len(fixed) == r.crashes >= 3 and all(tuple(row) == CRASH_FIELDS for row in fixed)
    # From the fixed start every lap is the same: same length, same place, same start heading.
    assert fixed[0]["episode_step"] == fixed[0]["step"] and {row["episode_step"] for row in fixed} == {fixed[0]["episode_step"]}
    assert [row["step"] for row in fixed] == [fixed[0]["step"] * (i + 1) for i in range(len(fixed))]
    assert len({(row["x_m"], row["y_m"]) for row in fixed}) == 1 and {row["start_yaw_deg"] for row in fixed} == {0.0}
    assert {row["action"] for row in fixed} == {"a3_forward_2mps"}
    # The map teacher steers clear of the wall it flies into: it disagreed shortly before each crash, not always.
    assert all(0 <= row["steps_since_teacher_disagreed"] <= row["episode_step"] for row in fixed)
    assert 0.0 < r.teacher_agreement < 1.0, r.teacher_agreement
    assert evaluate_inprocess(FlightSpec("cnn", "", SMALL_WORLD, 300), Straight()).teacher_agreement == -1.0  # no log
    r = fly(varied, start_yaw_jitter_deg=180.0)
    assert len(varied) == r.crashes and len({row["start_yaw_deg"] for row in varied}) > 1
    assert sum(row["episode_step"] for row in varied) <= 300
    with pytest.raises(SystemExit) as e:
        evaluate_main(["--crash-log", "--out", str(tmp_path)])
    assert e.value.code == 2  # the ROS measurement has no crash log


def test_the_reward_is_described_with_its_extension():
    from uav_trainer.training_config import reward_description

    assert reward_description(TrainerConfig()) == "the paper's"
    assert reward_description(TrainerConfig(turn_penalty=1.0)) == "the paper's - 1 per turning step"


def test_inprocess_mix_world_flies_the_world_between_layouts(tmp_path, monkeypatch):
    from uav_sim.simulator import Simulator
    from uav_sim.world import WorldError

    entered = []
    enter = Simulator._enter
    monkeypatch.setattr(Simulator, "_enter", lambda sim, *a, **k: enter(sim, *a, **k) or entered.append(sim.world.name))
    cfg = TrainerConfig(model="cnn", seed=0, total_steps=60, learning_starts=10**6, epsilon_end=1.0)
    run_inprocess(cfg, tmp_path, log=lambda s: None, world="random_each_episode", mix_world_every=2, max_episode_steps=3)
    # The first episode is a layout; from then on every second episode flies mix_world.
    assert len(entered) >= 10 and entered[0::2] == ["complex"] * len(entered[0::2])
    assert all(n.startswith("random:") for n in entered[1::2])
    with pytest.raises(WorldError, match="'mix_world_every' \\(2\\): must be 0, or >= 2 with world:=random_each_episode"):
        run_inprocess(cfg, tmp_path / "no", log=lambda s: None, mix_world_every=2)


def test_inprocess_reads_the_recipe_train_reads_and_takes_trainer_flags(tmp_path, capsys):
    from uav_trainer import inprocess

    made = []
    real = inprocess.run
    inprocess.run = lambda cfg, run_dir, sim_cfg, worlds, **kw: made.append((cfg, sim_cfg, worlds))
    try:
        with pytest.raises(AttributeError):  # the stub returns no Training: the settings are what is checked
            inprocess.main(["--steps", "300", "--learning-rate", "0.001", "--run-dir", str(tmp_path)])
        with pytest.raises(AttributeError):
            inprocess.main(["--recipe", "paper", "--steps", "300", "--run-dir", str(tmp_path)])
    finally:
        inprocess.run = real
    (cfg, sim, worlds), (paper_cfg, paper_sim, paper_worlds) = made
    assert (cfg.turn_penalty, cfg.replay_ratio, cfg.snapshots, cfg.learner.learning_rate) == (0.0, 0.5, 9, 0.001)
    assert (cfg.teacher, worlds.layout_families) == ("stack", "mixed")  # the default recipe learns from the planner
    assert (sim.sensor, sim.sensor_scale, sim.reward_window_fraction, sim.max_episode_steps) == ("realsense_d435", 0.1, 0.2, 300)
    assert cfg.sam_readout == "query"
    assert sim.start_yaw_jitter_deg == 180.0
    assert (worlds.world, worlds.mix_world, worlds.mix_world_every) == ("random_each_episode", "basic", 4)
    assert (paper_cfg.turn_penalty, paper_sim.hfov_deg, paper_sim.reward_window_fraction, paper_worlds.world) == (
        0.0,
        90.0,
        0.2,
        "basic",
    )
    for bad, said in (
        (["--recipe", "nosuch"], "recipe 'nosuch': no file params/recipes/nosuch.yaml"),
        (["--sim-arg", "hfov:=90.0"], "'hfov' is not a setting (did you mean 'hfov_deg'?)"),
        (["--replay-ratio", "100"], "'replay_ratio'=100.0 is outside [0.001, 64.0]"),
    ):
        with pytest.raises(SystemExit) as e:
            inprocess.main([*bad, "--run-dir", str(tmp_path / "bad")])
        assert e.value.code == 2 and said in capsys.readouterr().err, bad
    assert not (tmp_path / "bad").exists()


def test_exploration_and_learning_start_follow_the_budget_unless_given(tmp_path):
    """A 3000-step run decays epsilon over its first third and starts learning after a thirtieth: it ends at
    epsilon_end, not at 0.7 as with a fixed 10 000-step decay. Given schedules longer than the budget are warned of."""
    short = TrainerConfig(total_steps=3000)
    assert (short.decay_steps, short.first_update_after) == (1000, 100)
    shipped = TrainerConfig(total_steps=30000)  # the shipped recipe's schedules, as before
    assert (shipped.decay_steps, shipped.first_update_after) == (10000, 1000)
    assert (TrainerConfig().decay_steps, TrainerConfig().first_update_after) == (10000, 1000)  # no budget
    logs = []
    t = Training(dataclasses.replace(small_cfg(learning_starts=0), total_steps=3000), tmp_path / "a", log=logs.append)
    t.env_steps = 3000
    assert t.epsilon() == pytest.approx(0.05) and not any("warning" in line for line in logs)
    t.close()
    explicit = small_cfg(total_steps=3000, epsilon_decay_steps=10000, learning_starts=5000)
    t = Training(explicit, tmp_path / "b", log=logs.append)
    t.close()
    said = " ".join(logs)
    assert "warning: epsilon_decay_steps=10000 is longer than total_steps=3000: epsilon ends at 0.715" in said
    assert "warning: learning_starts=5000 is not below total_steps=3000: the run makes no update" in said


def test_no_snapshot_is_written_before_the_first_update(tmp_path):
    logs = []
    t = Training(small_cfg(model="sam", total_steps=300, snapshots=2, learning_starts=1000), tmp_path, log=logs.append)
    try:
        feed(t, 295)
        assert t.learn_due() == [] and t.learner.updates == 0
        assert not list(tmp_path.glob("policy_sam_step*"))
        assert any("step 280: no update yet (learning starts after 1000), no snapshot" in line for line in logs), logs
    finally:
        t.close()


def no_space(*_args, **_kw):
    """What safetensors raises on a full disk (seen on a 3 MB tmpfs): its own error type, not OSError."""
    from safetensors import SafetensorError

    raise SafetensorError("Error while serializing: I/O error: No space left on device (os error 28)")


def test_a_checkpoint_the_disk_refuses_keeps_the_last_one_and_training_goes_on(tmp_path, monkeypatch):
    logs = []
    t = Training(small_cfg(), tmp_path, log=logs.append)
    feed(t, 120)
    while t.learn_once():
        pass
    kept = checkpoint.latest(t.checkpoint_dir)
    assert kept is not None and kept.name.startswith("ckpt-000000030")
    monkeypatch.setattr(checkpoint, "save_file", no_space)  # the disk is full from here on
    feed(t, 40, seed=1)
    while t.learn_once():  # updates 31..50 reach the checkpoints at 40 and 50: both fail, none raises
        pass
    assert t.learner.updates == 55 and t.checkpoint_failures == 2
    assert checkpoint.latest(t.checkpoint_dir) == kept
    assert not list(t.checkpoint_dir.glob(".ckpt-*")), "a failed write leaves no unfinished folder"
    assert any("No space left on device" in line and f"latest stays {kept.name}" in line for line in logs), logs
    monkeypatch.undo()  # space again: the next checkpoint is written
    assert t.save_checkpoint().name.startswith("ckpt-000000055")
    t.close()


def test_a_final_checkpoint_whose_replay_does_not_fit_is_written_without_it(tmp_path, monkeypatch):
    logs = []
    t = Training(small_cfg(), tmp_path, log=logs.append)
    feed(t, 120)
    while t.learn_once():
        pass
    feed(t, 5, seed=3)  # frames the periodic checkpoints have not journaled
    monkeypatch.setattr(safetensors.numpy, "save_file", no_space)  # the replay segment is what does not fit
    path = t.save_checkpoint(final=True)
    assert path is not None and (path / "state.safetensors").is_file() and not (path / checkpoint.SEGMENT_FILE).exists()
    assert checkpoint.latest(t.checkpoint_dir) == path and t.checkpoint_failures == 0
    assert any("writing it without" in line for line in logs), logs
    monkeypatch.undo()
    t.save_checkpoint()  # space again: this one carries the frames the refused segment held
    t.close()
    again = Training(small_cfg(), tmp_path, log=logs.append, resume=True)
    assert again.replay.writes == t.replay.writes and len(again.replay) == len(t.replay) > 0
    again.close()


def test_a_checkpoint_comes_by_time_too_and_stale_unfinished_ones_are_removed_at_start(tmp_path):
    logs = []
    stale = tmp_path / "checkpoints" / ".ckpt-000000007-000000100.tmp"
    stale.mkdir(parents=True)
    t = Training(small_cfg(checkpoint_interval_updates=10**6), tmp_path, log=logs.append)
    assert not stale.exists() and any("removed 1 unfinished checkpoint" in line for line in logs)
    feed(t, 60)
    assert t.learn_once() and checkpoint.latest(t.checkpoint_dir) is None  # not due by updates, nor yet by time
    t._checkpoint_wall -= t.cfg.checkpoint_interval_s  # the interval has passed since the start
    assert t.learn_once() and checkpoint.latest(t.checkpoint_dir).name.startswith("ckpt-000000002")
    t.close()


def test_an_unwritable_run_folder_is_refused_in_one_line(tmp_path):
    (tmp_path / "a_file").write_text("")
    with pytest.raises(RunDirError, match="run_dir '.*a_file/run': cannot write there"):
        Training(small_cfg(), tmp_path / "a_file" / "run", log=lambda s: None)
    r = run_to_exit("uav_trainer", "trainer_node", "-p", f"run_dir:={tmp_path / 'a_file' / 'run'}", timeout_s=60)
    assert r.returncode == 2 and "run_dir" in r.stderr and "cannot write there" in r.stderr and "Traceback" not in r.stderr


def test_a_resume_with_too_few_stored_transitions_refills_without_a_burst_of_updates(tmp_path):
    """A memory smaller than learning_starts (here collected since a crash that lost the journal too) is
    refilled, then learning goes on at replay_ratio: no burst of the updates the pause did not make, which
    would have stalled lockstep acting."""
    a = Training(small_cfg(), tmp_path, log=lambda s: None)
    feed(a, 120)
    while a.learn_once():
        pass
    a.save_checkpoint()
    a.close()
    shutil.rmtree(a.checkpoint_dir / checkpoint.JOURNAL_DIR)  # lost with the crash
    b = Training(small_cfg(), tmp_path, log=lambda s: None, resume=True)
    feed(b, 20, seed=1)
    b.save_checkpoint(final=True)  # a stop: its memory holds only the 20 transitions since the crash
    b.close()
    c = Training(small_cfg(), tmp_path, log=lambda s: None, resume=True)
    assert len(c.replay) == 20 and c.learner.updates == 35
    per_step = []
    rng = np.random.default_rng(2)
    for _ in range(60):
        c.add_step(int(rng.integers(4)), 2.0, False, rng.uniform(0, 10, (64, 64)).astype(np.float32))
        done = 0
        while c.learn_once():
            done += 1
        per_step.append(done)
    assert per_step[:29] == [0] * 29, "the memory refills to learning_starts (50) first"
    assert max(per_step) == 1 and sum(per_step) == 15, per_step  # then one update per two steps, no burst
    c.close()


def test_several_actors_learn_from_one_memory_each_exploring_at_its_own_rate_and_resume_by_refilling(tmp_path):
    logs = []
    cfg = small_cfg(epsilon_decay_steps=100, total_steps=1000)
    t = Training(cfg, tmp_path, log=logs.append, actors=3)
    assert "with 3 actors the replay memory is not journaled" in " ".join(logs)
    assert [t.epsilon(i) for i in range(3)] == [1.0, 1.0, 1.0]  # all start exploring fully
    rng = np.random.default_rng(0)
    frame = lambda: rng.uniform(0, 10, (64, 64)).astype(np.float32)  # noqa: E731
    sinks = [t.sink(i) for i in range(3)]
    for s in sinks:
        s.add_first(frame())
    for k in range(100):
        for i, s in enumerate(sinks):
            if i < 2 or k % 2:
                s.add_step(k % 4, 1.0, k % 30 == 29, frame())
        t.learn_due()
    assert t.actor_steps == [100, 100, 50] and t.env_steps == 250
    assert t.learner.updates == int((250 - 50) * 0.5)
    # Ape-X's spread over the decayed schedule: 0.05, 0.05^4.5, 0.05^8.
    assert [round(t.epsilon(i), 10) for i in range(3)] == [0.05, round(0.05**4.5, 10), round(0.05**8, 10)]
    # Each actor's own episodes: a crash at its k = 29, 59, 89, after 30 steps (15 for the actor at odd k only).
    assert [length for _step, length, _reward in t.stats.history] == [30, 30, 15] * 3
    t.save_checkpoint()
    t.close()
    again = Training(cfg, tmp_path, log=logs.append, resume=True, actors=3)
    assert (again.env_steps, again.learner.updates) == (250, 100)
    assert len(again.replay) == 0 and not again.can_learn()  # the memory refills before learning goes on


def test_an_inprocess_run_whose_final_weights_cannot_be_written_says_so_and_exits_non_zero(tmp_path, monkeypatch, capsys):
    """A full disk at the end of a run (the write error injected): the replay journal is freed before the final
    writes, and the trainer names the stale and missing files and the checkpoint that stays latest, and exits 1."""
    import errno

    from uav_trainer import inprocess

    run_dir = tmp_path / "run"
    real = wio.write_atomic
    journal_at_final = []

    def write(path, data):
        path = type(run_dir)(path)
        if path.name in ("policy_cnn.safetensors", "policy_cnn_step145.safetensors"):
            journal_at_final.append(any((run_dir / "checkpoints" / checkpoint.JOURNAL_DIR).glob("seg-*")))
            raise OSError(errno.ENOSPC, "No space left on device")
        real(path, data)

    monkeypatch.setattr(wio, "write_atomic", write)
    run_dir.mkdir()
    (run_dir / "policy_cnn.safetensors").write_bytes(b"an earlier run's weights")
    args = ["--model", "cnn", "--steps", "150", "--snapshots", "9", "--learning-starts", "20", "--recipe", "paper"]
    args += ["--checkpoint-interval-updates", "20", "--run-dir", str(run_dir), "--threads", "1"]
    assert inprocess.main(args) == 1
    err = capsys.readouterr().err
    assert f"{run_dir / 'policy_cnn.safetensors'} (stale: No space left on device)" in err, err
    assert f"{run_dir / 'policy_cnn_step145.safetensors'} (missing" in err and "latest checkpoint: " in err, err
    assert any(journal_at_final) and not journal_at_final[-1], "the journal, there mid-run, was freed before the final write"
    assert checkpoint.latest(run_dir / "checkpoints") is not None
    assert "weights: " not in capsys.readouterr().out


def test_a_release_carries_the_weights_the_learner_had_at_the_release_before(tmp_path):
    """Lockstep learning's order (trainer_node and the in-process loop): release a frame, then learn; the weights a
    step's updates make are taken at the next release and go out with the one after, so no frame waits for them."""
    t = Training(small_cfg(learning_starts=4, replay_ratio=1.0), tmp_path, log=lambda s: None)
    rng = np.random.default_rng(0)
    t.add_first(rng.uniform(1, 9, (64, 64)).astype(np.float32))
    initial = t.weights_blob()
    sent, learnt = [], []  # what each step's release carries; the weights after each step's updates
    for _ in range(8):
        t.add_step(0, 8.0, False, rng.uniform(1, 9, (64, 64)).astype(np.float32))
        sent.append(t.released_weights())
        t.after_release()
        t.learn_due()
        learnt.append(t.weights_blob())
    assert t.learner.updates >= 3 and len(set(learnt)) == 1 + t.learner.updates, "one update a step, once started"
    assert sent[0][1] == sent[1][1] == initial
    for k in range(2, 8):
        assert sent[k][1] == learnt[k - 2], f"step {k} is answered with the weights after step {k - 2}'s updates"
    versions = [v for v, _ in sent]
    assert versions == sorted(versions) and len(set(versions)) == len({b for _, b in sent}), "a new blob, a new version"
    t.close()


def test_a_teacher_labels_every_step_flies_a_falling_share_and_the_run_is_reproducible(tmp_path):
    """--teacher stack: the planner's action beside every transition in the replay memory, flown instead of the
    student's at a share falling from teacher_act_start to 0, the large-margin loss learnt; seeded, so reproducible."""
    teaching = TeacherConfig(teacher="stack", teacher_act_start=1.0)
    cfg = TrainerConfig(model="cnn", seed=2, total_steps=120, learning_starts=40, teaching=teaching)
    runs = []
    for k in range(2):
        t = run_inprocess(cfg, tmp_path / f"r{k}", log=lambda s: None, world="complex", window=0.2)
        m = t.replay
        done = np.flatnonzero(m.has_transition[: m.count])
        assert len(done) >= 100 and (m.teacher[done] >= 0).all() and (m.teacher[done] < 4).all(), "every step labelled"
        followed = m.action[done] == m.teacher[done]
        assert followed[:40].mean() > 0.75 and followed[-40:].mean() < followed[:40].mean(), "the teacher's share falls"
        runs.append((m.action[done].copy(), m.teacher[done].copy(), [p.detach().clone() for p in t.learner.online.parameters()]))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    for a, b in zip(runs[0][2], runs[1][2], strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_a_run_with_a_teacher_whose_frames_come_without_one_is_stopped_naming_why():
    """A teacher is sim_node's planner; frames with no teacher_label (a camera, or a sim_node without teacher:=...)
    would never be learnt from: the actor says so, naming the parameter, once it has heard a few frames."""
    from uav_trainer.actors import TEACHERLESS_FRAMES, ActorState

    actor = ActorState(0, "", "/step_outcome")
    actor.frames_heard = TEACHERLESS_FRAMES - 1
    assert actor.no_teacher("stack") is None, "a few frames may come before the first teacher action is matched"
    actor.frames_heard = TEACHERLESS_FRAMES
    assert actor.no_teacher("none") is None, "no teacher asked for"
    why = actor.no_teacher("stack")
    assert "'teacher'='stack'" in why and "no teacher_label" in why and "a camera has no world" in why
    actor.teachers_heard = 1
    assert actor.no_teacher("stack") is None


def test_reasons_travel_with_their_frames_through_the_replay_memory_and_its_journal():
    from uav_trainer.replay import ReplayMemory

    mem = ReplayMemory(16, (4, 4), frames=2, seed=0, reason_nodes=3)
    mem.add_first(np.ones((4, 4)))
    shares = [np.array([0.0, 0.5, 1.0], np.float32), None, np.array([1.0, 0.0, 0.0], np.float32)]
    for k, share in enumerate(shares):
        mem.add_transition(k % 4, 1.0, False, np.full((4, 4), 2.0 + k), teacher=k, reason=share)
    batch = mem.sample(64)
    for slot, teacher, reason in zip(batch["index"], batch["teacher"], batch["reason"], strict=True):
        assert teacher == slot and reason.tolist() == (np.zeros(3) if shares[slot] is None else shares[slot]).tolist()
    again = ReplayMemory(16, (4, 4), frames=2, seed=0, reason_nodes=3)
    again.load_segments([mem.segment(0)], mem.writes, 4)
    assert np.array_equal(again.reason, mem.reason)
    bad = {**mem.segment(0), "reason": np.full((mem.writes, 3), 2.0, np.float16)}
    with pytest.raises(ValueError, match="reason shares outside"):
        again.load_segments([bad], mem.writes, 4)
    plain = ReplayMemory(16, (4, 4), frames=2)
    plain.add_first(np.ones((4, 4)))
    plain.add_transition(0, 1.0, False, np.ones((4, 4)))
    assert "reason" not in plain.sample(4), "a memory without reasons gives batches as before"


def test_the_attention_loss_needs_a_teacher_and_sams_query_readout_and_the_cnn_ignores_it():
    pull = dict(attention_weight=0.5)
    for cfg, what in (
        (TrainerConfig(sam_readout="query", teaching=TeacherConfig(**pull)), "needs a teacher"),
        (TrainerConfig(sam_readout="attend", teaching=TeacherConfig(teacher="stack", **pull)), "sam_readout 'query'"),
    ):
        with pytest.raises(ValueError, match=what):
            cfg.validate()
    TrainerConfig(sam_readout="query", teaching=TeacherConfig(teacher="stack", **pull)).validate()
    TrainerConfig(model="cnn", teaching=TeacherConfig(**pull)).validate()  # a recipe for both models: the CNN has no attention
