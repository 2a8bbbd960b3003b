"""The evaluation harness, the attention figures, the shipped pretrained weights and the tools that compare runs."""

import csv
import os
import shutil
import subprocess
import sys

import pytest
import torch

from conftest import ROOT, executable, read_bag
from uav_eval.flights import Behaviour, FlightSpec
from uav_eval.ros_flights import evaluate_once
from uav_eval.tables import INSIGHT_COLUMNS
from uav_interfaces.msg import StepOutcome
from uav_policy import weights as wio
from uav_policy.networks import NetConfig, build_network


def run_tool(pkg, exe, *args, domain: str, timeout=240):
    """An installed tool in the calling test's own ROS domain."""
    env = dict(os.environ, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    return subprocess.run([str(executable(pkg, exe)), *args], env=env, capture_output=True, text=True, timeout=timeout)


def test_evaluate_on_a_tiny_budget_writes_well_formed_tables(tmp_path):
    ws = []
    for seed in (0, 1):
        w = tmp_path / f"sam{seed}.safetensors"
        wio.save_file(build_network(NetConfig(), seed=seed), NetConfig(), w)
        ws.append(str(w))
    r = run_tool(
        "uav_eval",
        "evaluate",
        "--model",
        "sam",
        "--weights",
        *ws,
        "--worlds",
        "basic",
        "--steps",
        "50",
        "--insight-every",
        "0",
        "--out",
        str(tmp_path / "eval"),
        "--params-dir",
        str(ROOT / "params"),
        "--record",
        str(tmp_path / "bags"),
        domain="75",
    )
    assert r.returncode == 0, r.stderr[-3000:]
    # Redirected, no bar: a progress line per row, with its place in the whole and an ETA.
    assert "[1/2, " in r.stdout and "[2/2, " in r.stdout and "ETA" in r.stdout, r.stdout[-2000:]
    md = (tmp_path / "eval" / "results.md").read_text()
    for title in ("Table 1: crashes per 1000 steps", "Table 2: mean reward per step", "Distance flown between crashes"):
        assert title in md
    row = next(line for line in md.splitlines() if line.startswith("| basic |") and "2.406" in line)
    assert "(n=2)" in row and "| 2.406 |" in row  # two seeds, beside the paper's number
    rows = list(csv.DictReader(open(tmp_path / "eval" / "results.csv")))
    assert len(rows) == 2 and {r["world"] for r in rows} == {"basic"}
    for r in rows:
        assert int(r["steps"]) == 50 and 0 <= int(r["crashes"]) <= 50
        assert min(1, int(r["crashes"])) <= int(r["crash_sites"]) <= int(r["crashes"])
        assert float(r["crashes_per_1000"]) == pytest.approx(1000 * int(r["crashes"]) / 50)
    # --record kept each flight, from its first frame: the bag's outcomes give the row's crashes.
    for group, row in enumerate(rows):
        got = read_bag(tmp_path / "bags" / f"sam_basic_w{group}_seed0")
        assert got["/step_outcome"][0] == "uav_interfaces/msg/StepOutcome", "the bag names the stack's own type"
        outcomes = {(m.header.stamp.sec, m.header.stamp.nanosec): m.event for m in got["/step_outcome"][1]}
        steps = [outcomes[s] for s in sorted(outcomes)][1:51]  # the first frame is no step
        assert len(steps) == 50 and sum(x == StepOutcome.COLLIDED for x in steps) == int(row["crashes"])
        assert len(got["/action"][1]) >= 50 and "/attention" in got


def test_evaluate_pools_repeats_with_a_random_start_heading(tmp_path):
    w = tmp_path / "sam.safetensors"
    wio.save_file(build_network(NetConfig(), seed=2), NetConfig(), w)
    args = ["--weights", str(w), "--worlds", "basic", "--steps", "40", "--params-dir", str(ROOT / "params")]
    r = run_tool(
        "uav_eval",
        "evaluate",
        *args,
        "--start-yaw-jitter-deg",
        "180",
        "--repeats",
        "2",
        "--inprocess",  # pooling is the tool's; repeats over ROS: test_inprocess_evaluation_measures_exactly_...
        "--insight-every",
        "0",
        "--out",
        str(tmp_path / "e"),
        domain="85",
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "random heading (uniform ±180°), 2 x 40 steps" in (tmp_path / "e" / "results.md").read_text()
    rows = list(csv.DictReader(open(tmp_path / "e" / "results.csv")))
    assert len(rows) == 1 and int(rows[0]["steps"]) == 80  # two runs of one weight file pooled into one row
    bad = run_tool("uav_eval", "evaluate", *args, "--start-yaw-jitter-deg", "200", domain="85")
    assert bad.returncode == 2 and "--start-yaw-jitter-deg" in bad.stderr


def test_inprocess_evaluation_measures_exactly_what_the_ros_nodes_measure(tmp_path):
    w = tmp_path / "sam.safetensors"
    wio.save_file(build_network(NetConfig(), seed=3), NetConfig(), w)
    args = ["--weights", str(w), "--worlds", "complex", "--steps", "40", "--params-dir", str(ROOT / "params")]
    args += ["--start-yaw-jitter-deg", "180", "--repeats", "2", "--sim-arg", "hfov_deg:=120.0"]
    paper = run_tool(  # crashes and reward only
        "uav_eval", "evaluate", *args, "--inprocess", "--insight-every", "0", "--out", str(tmp_path / "paper"), domain="77"
    )
    # Half of each side: the floor enters the reward window 1.15 m ahead; both paths must see the change.
    args += ["--sim-arg", "reward_window_fraction:=0.5"]
    ros = run_tool("uav_eval", "evaluate", *args, "--out", str(tmp_path / "ros"), domain="77")
    local = run_tool("uav_eval", "evaluate", *args, "--inprocess", "--out", str(tmp_path / "local"), domain="77")
    assert ros.returncode == 0 and local.returncode == 0, ros.stderr[-2000:] + local.stderr[-2000:]
    assert "Measured in-process" in (tmp_path / "local" / "results.md").read_text()
    a, b = ([r for r in csv.DictReader(open(tmp_path / d / "results.csv"))] for d in ("ros", "local"))
    assert len(a) == len(b) == 1 and int(a[0]["steps"]) == 80
    assert 0 <= int(a[0]["turn_steps"]) <= 80 and 1 <= int(a[0]["cells_visited"]) <= 80
    assert "Flight behaviour" in (tmp_path / "ros" / "results.md").read_text()
    for k in ("crashes", "mean_reward", "distance_m", "crash_sites", "turn_steps", "cells_visited"):
        assert a[0][k] == b[0][k], (k, a[0], b[0])
    # What the decisions looked at, measured on every step: policy_node (its /diagnostics, 3 decimals a run, two
    # runs pooled) and in process alike. No frame comes after the budget's last step, so both measure the same frames.
    assert int(a[0]["insight_frames"]) == int(b[0]["insight_frames"]) == 80
    for k in ("entropy", "top10_share", "map_correlation", "deletion_top", "deletion_random", "near_ratio"):
        assert float(a[0][k]) == pytest.approx(float(b[0][k]), abs=0.0006), (k, a[0], b[0])  # 3 decimals, then 4 in results.csv
    top, rand = float(b[0]["deletion_top"]), float(b[0]["deletion_random"])
    if rand > 0.001:  # the ratio of the two rates, each as reported to within 0.0006
        bound = (0.0006 + top / rand * 0.0006) / (rand - 0.0006) + 0.0001
        assert float(a[0]["faithfulness"]) == pytest.approx(float(b[0]["faithfulness"]), abs=bound), (a[0], b[0])
    else:
        assert a[0]["faithfulness"] == b[0]["faithfulness"], (a[0], b[0])
    assert "What the decisions look at" in (tmp_path / "ros" / "results.md").read_text()
    assert paper.returncode == 0, paper.stderr[-2000:]
    c = next(csv.DictReader(open(tmp_path / "paper" / "results.csv")))
    assert (
        c["crashes"] == a[0]["crashes"] and float(a[0]["mean_reward"]) < float(c["mean_reward"]) - 0.5
    )  # same flight, less reward
    bad = run_tool("uav_eval", "evaluate", *args, "--inprocess", "--sim-arg", "weather:=rain", domain="77")
    assert bad.returncode == 2 and "--inprocess takes only --sim-arg hfov_deg" in bad.stderr


def test_attention_figures_are_written(tmp_path):
    r = run_tool(
        "uav_eval",
        "attention_figures",
        "--model",
        "sam",
        "--worlds",
        "turbulent",
        "--steps",
        "12",
        "--panels",
        "3",
        "--out",
        str(tmp_path),
        domain="86",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    png, gif = tmp_path / "attention_turbulent.png", tmp_path / "flight_turbulent.gif"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and gif.read_bytes()[:6] in (b"GIF89a", b"GIF87a")


PACKAGED_FILES = {"sam": 1, "cnn": 1}  # how many networks each packaged policy is (one each, chosen on validation)


@pytest.mark.parametrize("model", ["sam", "cnn"])
def test_shipped_weights_load_and_fly_200_steps_in_basic_without_a_crash(model, monkeypatch, ros_domain):
    from uav_sim.sensor import preset_for_camera

    shipped = sorted((ROOT / "src" / "uav_policy" / "weights" / model).glob("*.safetensors"))
    assert len(shipped) == PACKAGED_FILES[model], f"the shipped {model} weights: {len(shipped)} files"
    # What policy_node loads (the installed copies, in this order) is these files.
    assert [p.read_bytes() for p in wio.packaged_weights(model)] == [p.read_bytes() for p in shipped]
    wio.load_files(shipped, model)  # valid for the architecture (several: as one ensemble)
    # Trained behind a RealSense D435-like camera and the paper's reward window: evaluate and fly put the simulator
    # behind that sensor preset (its field of view, recorded in the files).
    assert {preset_for_camera(wio.read_file_camera(p)) for p in shipped} == {"realsense_d435"}
    assert {wio.read_file_window(p) for p in shipped} == {None}
    monkeypatch.setenv("ROS_DOMAIN_ID", ros_domain)
    r = evaluate_once(FlightSpec(model, "", "basic", 200))  # "" = what policy_node uses by default: the packaged files
    assert r.steps == 200 and r.crashes == 0, r


def test_behaviour_tells_circling_on_the_spot_from_flying_through_the_room():
    import math

    circling, straight = Behaviour(0.5, 0.5, 0.0), Behaviour(0.5, 0.5, 0.0)
    for k in range(1, 13):  # 30 degrees and 0.5 m per step: a circle of radius ~0.95 m, twice round
        yaw = k * math.radians(30)
        circling.step(0.5 + 0.95 * math.sin(yaw), 0.5 + 0.95 * (1 - math.cos(yaw)), yaw, False)
        straight.step(0.5 + 0.5 * k, 0.5, 0.0, False)
    assert circling.turn_steps == 12 and len(circling.cells) <= 6
    assert straight.turn_steps == 0 and len(straight.cells) == 7
    # A crash puts the vehicle back at the start with another heading: not a turn.
    straight.step(0.5, 0.5, math.pi, True)
    assert straight.turn_steps == 0 and len(straight.cells) == 7


def test_tables_rebuilt_from_several_csv_files_equal_the_measured_ones(tmp_path):
    """`--from-csv` joins per-run CSVs and, given the same protocol flags, rewrites the same tables;
    a flatten-readout SAM file is flown with its own readout."""
    from uav_eval.evaluate import main

    flat = NetConfig(sam_readout="flatten")
    ws = [tmp_path / "max.safetensors", tmp_path / "flat.safetensors"]
    wio.save_file(build_network(NetConfig(), seed=0), NetConfig(), ws[0])
    wio.save_file(build_network(flat, seed=0), flat, ws[1])
    proto = ["--inprocess", "--worlds", "basic", "--steps", "30", "--start-yaw-jitter-deg", "180", "--repeats", "2"]
    proto += ["--insight-every", "3"]  # measured, and rebuilt from the CSVs too
    assert main([*proto, "--weights", *map(str, ws), "--out", str(tmp_path / "both")]) == 0
    for i, w in enumerate(ws):
        assert main([*proto, "--weights", str(w), "--out", str(tmp_path / f"one{i}")]) == 0
    parts = [str(tmp_path / f"one{i}" / "results.csv") for i in range(2)]
    assert main([*proto, "--from-csv", *parts, "--out", str(tmp_path / "joined")]) == 0
    for name in ("results.md", "results.csv"):
        assert (tmp_path / "joined" / name).read_text() == (tmp_path / "both" / name).read_text()
    assert "random heading (uniform ±180°), 2 x 30 steps" in (tmp_path / "joined" / "results.md").read_text()


def test_from_csv_refuses_a_table_it_cannot_read_naming_file_and_line(tmp_path, capsys):
    """Bad rows in `--from-csv` files stop evaluate with the file, the line and what is wrong, and
    write no tables."""
    from uav_eval.evaluate import main

    head = "model,world,weights,steps,crashes,crashes_per_1000,mean_reward,distance_m\n"
    good = "sam,basic,a.safetensors,1000,2,2.00,1.5,900.00\n"
    cases = {
        "no_column.csv": ("model,world,weights,steps\nsam,basic,a,1000\n", "no column crashes, mean_reward, distance_m"),
        "model.csv": (head + good + "dqn,basic,a,1000,0,0.00,1.0,1.0\n", "line 3: model must be one of sam, cnn, planner"),
        "count.csv": (head + "sam,basic,a,1000,two,2.00,1.5,900.00\n", "line 2: crashes must be a whole number, got 'two'"),
        "impossible.csv": (head + "sam,basic,a,10,11,0,1.5,9.0\n", "needs steps >= 1 and 0 <= crashes <= steps, got 10 and 11"),
        "nan.csv": (head + "sam,basic,a,1000,0,0,nan,9.0\n", "line 2: mean_reward must be a finite number, got 'nan'"),
        "empty.csv": (head, "no rows in"),
        "short.csv": (head + "sam\n", "line 2: world and weights must not be empty (a short row?)"),
        "binary.csv": (b"\xff\xfe\x00garbage", "cannot read it"),
    }
    for name, (text, message) in cases.items():
        path = tmp_path / name
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        out = tmp_path / f"out_{name}"
        with pytest.raises(SystemExit) as e:
            main(["--from-csv", str(path), "--out", str(out)])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert f"--from-csv: {path}" in err or "no rows in" in err, err
        assert message in err, (name, err)
        assert not out.exists()
    with pytest.raises(SystemExit):
        main(["--from-csv", str(tmp_path / "missing.csv"), "--out", str(tmp_path / "m")])
    assert "cannot read it" in capsys.readouterr().err
    (tmp_path / "good.csv").write_text(head + good)
    assert main(["--from-csv", str(tmp_path / "good.csv"), "--out", str(tmp_path / "ok")]) == 0
    head_out, line = (tmp_path / "ok" / "results.csv").read_text().splitlines()[:2]
    row = dict(zip(head_out.split(","), line.split(","), strict=True))
    assert [row[k] for k in ("model", "world", "weights", "steps", "crashes")] == ["sam", "basic", "a.safetensors", "1000", "2"]
    assert (row["crashes_per_1000_low"], row["crashes_per_1000_high"]) == ("0.24", "7.22"), "its exact Poisson interval"
    assert [row[k] for k in ("turn_steps", "cells_visited", "safety_interventions")] == ["-1", "-1", "-1"]
    later = list(row)[list(row).index("insight_frames") :]
    assert set(INSIGHT_COLUMNS) <= set(later) and all(row[k] == "" for k in later), (
        "a row measured before the insight columns existed has none"
    )


def test_evaluate_flies_an_ensemble_of_weights_files_as_one_policy(tmp_path, capsys):
    """--ensemble K groups the files in order; two copies of one network fly exactly as that network."""
    from uav_eval.evaluate import main

    def save(name, seed, cfg=NetConfig()):
        path = tmp_path / name / "policy_sam.safetensors"
        path.parent.mkdir()
        wio.save_file(build_network(cfg, seed=seed), cfg, path, camera_hfov_deg=120.0)
        return str(path)

    a, a_copy, b = save("e_sam_seed0", 0), save("e_sam_seed1", 0), save("e_sam_seed2", 1)
    flat = save("flat_sam_seed0", 0, NetConfig(sam_readout="flatten"))
    proto = ["--inprocess", "--worlds", "basic", "--steps", "40", "--start-yaw-jitter-deg", "180", "--insight-every", "0"]
    assert main([*proto, "--weights", a, "--out", str(tmp_path / "one")]) == 0
    assert main([*proto, "--ensemble", "2", "--weights", a, a_copy, "--out", str(tmp_path / "ens")]) == 0
    progress = [line.split("] ", 1)[-1] for line in capsys.readouterr().out.splitlines() if "] sam basic " in line]
    assert progress[-1].startswith(f"sam basic      ensemble of 2 ({a} ... {a_copy}): "), progress  # not every file
    one, ens = (next(csv.DictReader(open(tmp_path / d / "results.csv"))) for d in ("one", "ens"))
    assert ens["weights"] == f"{a}+{a_copy}"
    assert "Each policy is 2 weights files flown as one" in (tmp_path / "ens" / "results.md").read_text()
    assert "flown as one" not in (tmp_path / "one" / "results.md").read_text()
    for key in ("steps", "crashes", "mean_reward", "distance_m", "turn_steps", "cells_visited"):
        assert ens[key] == one[key], key
    assert main([*proto, "--ensemble", "2", "--weights", a, b, "--out", str(tmp_path / "mixed")]) == 0
    for bad, says in (
        (["--ensemble", "2", "--weights", a, b, b], "not a multiple of 2"),
        (["--ensemble", "2", "--weights", a, flat], "one architecture"),
        (["--ensemble", "0", "--weights", a], "must be >= 1"),
        (["--ensemble", "2"], "give the sam weights files"),
    ):
        with pytest.raises(SystemExit) as e:
            main([*proto, *bad])
        assert e.value.code == 2 and says in capsys.readouterr().err
    comma = tmp_path / "a,b.safetensors"
    shutil.copy(a, comma)
    refused = run_tool("uav_eval", "evaluate", "--weights", str(comma), "--steps", "5", domain="78")
    assert refused.returncode == 2 and "cannot take a path with a comma" in refused.stderr
    # Through the ROS nodes (policy_node gets both files as its weights list): the same flight.
    ros_args = [*proto[1:], "--params-dir", str(ROOT / "params"), "--out", str(tmp_path / "ros")]
    ros = run_tool("uav_eval", "evaluate", *ros_args, "--ensemble", "2", "--weights", a, b, domain="78")
    assert ros.returncode == 0, ros.stderr[-3000:]
    local, over_ros = (next(csv.DictReader(open(tmp_path / d / "results.csv"))) for d in ("mixed", "ros"))
    assert over_ros["weights"] == f"{a}+{b}" and "Measured in-process" not in (tmp_path / "ros" / "results.md").read_text()
    for key in ("steps", "crashes", "mean_reward", "distance_m", "crash_sites", "turn_steps", "cells_visited"):
        assert over_ros[key] == local[key], (key, over_ros, local)
    from uav_eval import compare_models as compare

    assert compare.run_name(ens["weights"]) == "e_sam_ens2" and compare.seeds_of(ens["weights"]) == (0, 1)
    snaps = "runs/t_sam_seed4/policy_sam_step28999.safetensors+runs/t_sam_seed4/policy_sam.safetensors"
    assert compare.run_name(snaps) == "t_sam_snap2" and compare.seeds_of(snaps) == (4, 4)
    two_runs = snaps + "+" + snaps.replace("seed4", "seed5")
    assert compare.run_name(two_runs) == "t_sam_snap2_ens2" and compare.seeds_of(two_runs) == (4, 4, 5, 5)
    assert compare.run_name(f"{a}+{a_copy}+{b.replace('policy_sam', 'policy_sam_step9')}") == "e_sam_ens3"  # one file a run
    # --paired: an ensemble against the mean of its members (b = the single files)
    x, y = compare.partners([1.0, 5.0], [(0, 1), (2, 3)], [0.0, 4.0, 2.0], [(0,), (1,), (2,)])
    assert x.tolist() == [1.0] and y.tolist() == [2.0]  # (2, 3) has no partner: seed 3 is missing
    x, y = compare.partners([1.0, 5.0], [(4, 4, 4, 4, 4), (5, 5, 5, 5, 5)], [3.0, 7.0], [(5, 5, 5), (4, 4, 4)])
    assert x.tolist() == [1.0, 5.0] and y.tolist() == [7.0, 3.0]  # snapshot ensembles of one run pair by its seed


def test_compare_models_tells_a_real_difference_from_none(tmp_path):
    def write(name, sam, cnn):
        path = tmp_path / name
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["model", "world", "weights", "steps", "crashes", "mean_reward"])
            for model, crashes in (("sam", sam), ("cnn", cnn)):
                for i, c in enumerate(crashes):
                    w.writerow([model, "complex", f"{model}{i}", 1000, c, 2.0 + 0.1 * i])
        return path

    script = executable("uav_eval", "compare_models")
    run = lambda p: subprocess.run([sys.executable, str(script), str(p)], capture_output=True, text=True)  # noqa: E731
    differ = run(write("differ.csv", [0, 1, 0, 1, 0, 1], [9, 10, 11, 9, 10, 11]))
    assert differ.returncode == 0, differ.stderr
    row = next(line for line in differ.stdout.splitlines() if "crashes / 1000" in line)
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:5] == ["0.500 (6)", "10.000 (6)", "-9.500"]
    assert float(cells[6]) < 0.01  # 6 vs 6 fully separated: exact p = 2 / 924
    same = run(write("same.csv", [1, 2, 3], [3, 2, 1]))
    row = next(line for line in same.stdout.splitlines() if "crashes / 1000" in line)
    assert row.strip("|").split("|")[6].strip() == "1.000"
    one = run(write("one.csv", [1], [3, 2]))
    assert one.returncode == 2 and "two or more" in one.stderr
    # --by run: two training variants of one model, told apart by their run folders.
    rows = [
        ["sam", "complex", f"runs/{v}_sam_seed{i}/policy_sam.safetensors", 1000, c, 2.0]
        for v, cs in (("new", [0, 0, 1]), ("old", [4, 5, 6]))
        for i, c in enumerate(cs)
    ]
    path = tmp_path / "runs.csv"
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows([["model", "world", "weights", "steps", "crashes", "mean_reward"], *rows])
    by_run = subprocess.run(
        [sys.executable, str(script), str(path), "--by", "run", "--a", "new_sam", "--b", "old_sam"],
        capture_output=True,
        text=True,
    )
    row = next(line for line in by_run.stdout.splitlines() if "crashes / 1000" in line)
    assert [c.strip() for c in row.strip("|").split("|")][2:5] == ["0.333 (3)", "5.000 (3)", "-4.667"], by_run.stdout
    # --pool-worlds: each weights file's worlds summed into one row (crashes per 1000 of all its steps).
    rows += [
        ["sam", "basic", f"runs/{v}_sam_seed{i}/policy_sam.safetensors", 3000, 3, 1.0] for v in ("new", "old") for i in range(3)
    ]
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows([["model", "world", "weights", "steps", "crashes", "mean_reward"], *rows])
    pooled = subprocess.run(
        [sys.executable, str(script), str(path), "--by", "run", "--a", "new_sam", "--b", "old_sam", "--pool-worlds", "both"],
        capture_output=True,
        text=True,
    )
    lines = [line for line in pooled.stdout.splitlines() if line.startswith("| both |")]
    assert len(lines) == 2 and "complex" not in pooled.stdout.split("\n", 1)[1], pooled.stdout
    assert [c.strip() for c in lines[0].strip("|").split("|")][2:5] == [
        "0.833 (3)",
        "2.000 (3)",
        "-1.167",
    ]  # (0 + 3) / 4 and (4 + 3) / 4 for seed 0
    assert [c.strip() for c in lines[1].strip("|").split("|")][2:4] == ["1.250 (3)", "1.250 (3)"]  # (2 + 3) / 4


def test_compare_models_paired_by_seed_sees_a_consistent_small_gain(tmp_path):
    """Seeds far apart from each other, each improved by 1 crash: unpaired cannot tell, paired can."""
    script = executable("uav_eval", "compare_models")
    base = [0, 10, 20, 30, 40, 50, 60, 70]
    rows = [["sam", "complex", f"runs/short_sam_seed{i}/policy_sam.safetensors", 1000, c, 2.0] for i, c in enumerate(base)]
    long = "runs/long_sam_seed{}/policy_sam_step60.safetensors"
    rows += [["sam", "complex", long.format(i), 1000, c - 1, 2.0] for i, c in enumerate(base)]
    rows.append(["sam", "complex", "runs/short_sam_seed99/policy_sam.safetensors", 1000, 500, 2.0])  # no partner: left out
    path = tmp_path / "paired.csv"
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows([["model", "world", "weights", "steps", "crashes", "mean_reward"], *rows])

    def row(*extra):
        out = subprocess.run(
            [sys.executable, str(script), str(path), "--by", "run", "--a", "long_sam_step60", "--b", "short_sam", *extra],
            capture_output=True,
            text=True,
        )
        assert out.returncode == 0, out.stderr
        return [c.strip() for c in next(x for x in out.stdout.splitlines() if "crashes / 1000" in x).strip("|").split("|")]

    unpaired, paired = row(), row("--paired")
    assert float(unpaired[6]) > 0.5
    assert paired[2:5] == ["34.000 (8)", "35.000 (8)", "-1.000"] and paired[5] == "-1.000 to -1.000"
    assert float(paired[6]) < 0.01  # 8 equal signs: exact p = 2 / 256
    bad = subprocess.run([sys.executable, str(script), str(path), "--paired"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--by run" in bad.stderr
    # --by file: the same weights files in two tables (flown two ways), one group per table, paired by seed;
    # --pool-worlds keeps a file's rows of the two tables apart.
    header = ["model", "world", "weights", "steps", "crashes", "mean_reward"]
    same = [f"runs/short_sam_seed{i}/policy_sam.safetensors" for i in range(len(base))]
    one, two = tmp_path / "one.csv", tmp_path / "two.csv"
    for table, shift in ((one, 0), (two, 2)):
        with open(table, "w", newline="") as f:
            table_rows = (["sam", "complex", w, 1000, c + shift, 2.0] for w, c in zip(same, base, strict=True))
            csv.writer(f).writerows([header, *table_rows])
    for extra in ((), ("--pool-worlds", "all")):
        out = subprocess.run(
            [sys.executable, str(script), str(two), str(one), "--by", "file", "--paired", "--a", "shifted", "--b", "base"]
            + list(extra),
            capture_output=True,
            text=True,
        )
        assert out.returncode == 0, out.stderr
        cells = [c.strip() for c in next(x for x in out.stdout.splitlines() if "crashes / 1000" in x).strip("|").split("|")]
        assert cells[2:6] == ["37.000 (8)", "35.000 (8)", "+2.000", "+2.000 to +2.000"], out.stdout
    for bad_args in ((str(one), "--by", "file"), (str(one), str(two), "--by", "file", "--a", "x", "--b", "x")):
        bad = subprocess.run([sys.executable, str(script), *bad_args], capture_output=True, text=True)
        assert bad.returncode == 2 and "--by file needs two results.csv files" in bad.stderr


def test_compare_models_counts_the_seeds_at_the_bar(tmp_path):
    """--bar: a seed counts when it is at or under the bar in every world; the shares get a Fisher exact test."""
    script = executable("uav_eval", "compare_models")
    from uav_eval import compare_models as compare

    assert compare.fisher_exact(3, 4, 1, 4) == pytest.approx(17 / 35)  # Fisher's tea tasting: two-sided 0.486
    assert compare.fisher_exact(4, 4, 0, 4) == pytest.approx(2 / 70) and compare.fisher_exact(2, 4, 2, 4) == pytest.approx(1.0)
    assert compare.parse_bar("paper") == {"basic": 0.0, "complex": 1.0, "turbulent": 1.0}
    # seed: (basic, complex, turbulent) crashes in 1000 steps; "new" seeds 0-2 at the bar, 3 not (basic 1),
    # "old" seed 0 at the bar, 1 not (complex 2), 2 not (turbulent 3); "new" seed 4 lacks turbulent: not counted.
    new = {0: (0, 0, 0), 1: (0, 1, 1), 2: (0, 1, 0), 3: (1, 0, 0), 4: (0, 0, None)}
    old = {0: (0, 1, 1), 1: (0, 2, 0), 2: (0, 0, 3)}
    rows = [
        ["sam", world, f"runs/{v}_sam_seed{i}/policy_sam.safetensors", 1000, c, 2.0]
        for v, seeds in (("new", new), ("old", old))
        for i, crashes in seeds.items()
        for world, c in zip(("basic", "complex", "turbulent"), crashes, strict=True)
        if c is not None
    ]
    path = tmp_path / "bar.csv"
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows([["model", "world", "weights", "steps", "crashes", "mean_reward"], *rows])
    run = lambda *extra: subprocess.run(  # noqa: E731
        [sys.executable, str(script), str(path), "--by", "run", "--a", "new_sam", "--b", "old_sam", *extra],
        capture_output=True,
        text=True,
    )
    out = run("--bar", "paper")
    assert out.returncode == 0, out.stderr
    # By hand: 4 successes of 7, 4 drawn; P(k of new) = C(4,k) C(3,4-k) / 35 = 4, 18, 12, 1 (/35) for k = 1..4, and the
    # tables no likelier than the observed k = 3 (12/35) are k = 1, 3, 4: p = 17/35 = 0.486.
    assert "new_sam 3 of 4, old_sam 1 of 3; Fisher exact two-sided p = 0.486." in out.stdout
    two = run("--bar", "basic=0, complex=1")  # only the worlds named count: old seed 2 and new seed 4 now do
    assert "new_sam 4 of 5, old_sam 2 of 3" in two.stdout, two.stdout
    for bad in ("basic=-1", "basic", "=1", "basic=one"):
        refused = run("--bar", bad)
        assert refused.returncode == 2 and "is not WORLD=CRASHES_PER_1000" in refused.stderr
    assert "does not go with --pool-worlds" in run("--bar", "paper", "--pool-worlds", "all").stderr


def test_package_weights_writes_the_files_in_order_with_their_camera_and_window(tmp_path, capsys):
    """Packaged files hold the same tensors with the training camera and reward window; what was there goes."""
    import importlib.util
    import types

    from safetensors.torch import load_file

    spec = importlib.util.spec_from_file_location("package_weights", ROOT / "scripts" / "package_weights.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)  # its main() in this process: no interpreter and torch to start for each call

    def run(*args):
        try:
            code = script.main(list(map(str, args)))
        except SystemExit as e:  # argparse's error(): exit 2 with the message on stderr
            code = e.code
        out, err = capsys.readouterr()
        return types.SimpleNamespace(returncode=code, stdout=out, stderr=err)

    nets = [build_network(NetConfig(), seed=s) for s in range(3)]
    src = []
    for i, net in enumerate(nets):
        src.append(tmp_path / f"policy_sam_step{i}.safetensors")
        wio.save_file(net, NetConfig(), src[-1], camera_hfov_deg=150.0, reward_window_fraction=0.078)
    out = tmp_path / "weights" / "sam"
    out.mkdir(parents=True)
    (out / "old.safetensors").write_bytes(b"stale")
    r = run(*src, "--model", "sam", "--out", out)
    assert r.returncode == 0, r.stderr
    made = sorted(out.glob("*.safetensors"))
    assert [p.name for p in made] == ["sam_00.safetensors", "sam_01.safetensors", "sam_02.safetensors"]
    for a, b in zip(src, made, strict=True):
        before, after = load_file(str(a)), load_file(str(b))
        assert before.keys() == after.keys() and all(before[k].equal(after[k]) for k in before)
        assert wio.read_file_camera(b) == 150.0 and wio.read_file_window(b) == 0.078
    # A file without a camera needs --camera-hfov-deg; one that says another camera is refused. Nothing is replaced.
    bare = tmp_path / "bare.safetensors"
    wio.save_file(nets[0], NetConfig(), bare)
    assert "records no camera: give --camera-hfov-deg" in run(src[1], bare, "--model", "sam", "--out", out).stderr
    assert "records a 150 deg camera, not 120" in run(src[0], "--model", "sam", "--camera-hfov-deg", "120", "--out", out).stderr
    cam120 = tmp_path / "cam120.safetensors"
    wio.save_file(nets[0], NetConfig(), cam120, camera_hfov_deg=120.0)
    assert "different cameras (120, 150 deg)" in run(src[0], cam120, "--model", "sam", "--out", out).stderr
    assert [p.read_bytes() for p in sorted(out.glob("*.safetensors"))] == [p.read_bytes() for p in made]
    assert "cannot read" in run(tmp_path / "missing.safetensors", "--model", "sam", "--out", out).stderr


def test_same_run_tells_identical_runs_weights_and_rows_from_different_ones(tmp_path):
    """scripts/same_run.py: episodes and weights tensor by tensor, a run against the packaged files, and a
    run's evaluate rows against another run's: 'same' (exit 0) only when nothing differs."""

    def same_run(*args):
        r = subprocess.run([sys.executable, str(ROOT / "scripts" / "same_run.py"), *args], capture_output=True, text=True)
        assert r.returncode in (0, 1), r.stderr
        return r.returncode, r.stdout

    (packaged,) = wio.packaged_weights("sam")
    a, b = tmp_path / "a", tmp_path / "b"
    for run in (a, b):
        run.mkdir()
        (run / "episodes.csv").write_text("episode,env_step,length,reward,end\n1,7,7,-3.000,crash\n")
        for name in [f"policy_sam_step{n}.safetensors" for n in range(21000, 30000, 1000)] + ["policy_sam.safetensors"]:
            shutil.copy(packaged, run / name)
    rc, out = same_run(str(a), str(b))
    assert rc == 0 and out.endswith("same\n") and "policy_sam_step29000.safetensors: identical" in out
    assert "no validation.csv" in same_run(str(a), "--packaged", "sam")[1]
    (a / "validation.csv").write_text("weights,steps,crashes,complete,chosen\npolicy_sam_step24000.safetensors,4000,8,1,1\n")
    rc, out = same_run(str(a), "--packaged", "sam")
    assert rc == 0 and "policy_sam_step24000.safetensors (chosen) = packaged sam_00.safetensors: identical" in out, out
    net = wio.load_file(packaged, wio.config_for("sam", packaged))
    with torch.no_grad():
        net.trunk.net[0].bias[0] += 1e-6  # one value of one tensor
    camera, window = wio.read_file_camera(packaged), wio.read_file_window(packaged)
    wio.save_file(net, net.cfg, b / "policy_sam_step24000.safetensors", camera, window)
    rc, out = same_run(str(a), str(b))
    assert rc == 1
    tensors = len(net.state_dict())
    assert f"policy_sam_step24000.safetensors: 1 of {tensors} tensors differ" in out and out.endswith("DIFFERENT\n")
    (b / "validation.csv").write_bytes((a / "validation.csv").read_bytes())
    assert same_run(str(b), "--packaged", "sam")[0] == 1, "the chosen file differs from the packaged one"
    assert "policy_sam_step23000.safetensors: identical" in out
    (b / "episodes.csv").write_text("episode,env_step,length,reward,end\n1,7,7,-3.001,crash\n")
    rc, out = same_run(str(a), str(b))
    assert rc == 1 and "episodes.csv (1 episodes): differs" in out
    header = "model,world,weights,steps,crashes,mean_reward\n"

    def row(run, world, crashes):
        return f"sam,{world},{run}/policy_sam_step21000.safetensors+{run}/policy_sam.safetensors,1000,{crashes},3.1\n"

    ta, tb = tmp_path / "ta.csv", tmp_path / "tb.csv"
    ta.write_text(header + row("x/a", "basic", 0) + row("x/a", "complex", 1) + row("x/other", "basic", 5))
    tb.write_text(header + row("y/b", "complex", 1) + row("y/b", "basic", 0))
    assert same_run("x/a", "y/b", "--tables", str(ta), str(tb)) == (0, "sam basic: identical\nsam complex: identical\nsame\n")
    tb.write_text(header + row("y/b", "complex", 2) + row("y/b", "basic", 0))
    rc, out = same_run("x/a", "y/b", "--tables", str(ta), str(tb))
    assert rc == 1 and "sam complex: crashes differ" in out


@pytest.mark.parametrize(
    ("jitter", "hfov", "trained_hfov", "readout", "size", "sam_sizes", "safety", "shield"),
    [  # each readout, jitter or not, a camera given or the weights', other sizes, the safety layer, the shield
        (180.0, 120.0, None, "attend", 64, {}, True, False),
        (180.0, None, 90.0, "max", 64, {}, False, False),
        (0.0, 90.0, None, "flatten", 48, {"d_model": 24, "heads": 2, "relational_blocks": 2, "frames": 7}, False, False),
        (180.0, 120.0, None, "query", 64, {}, False, True),
        (180.0, 120.0, None, "query", 64, {"local_map": True}, False, False),  # the map from sim_node's odom
    ],
)
def test_ros_evaluation_equals_the_in_process_measurement(
    tmp_path, jitter, hfov, trained_hfov, readout, size, sam_sizes, safety, shield, monkeypatch, ros_domain
):
    """Same simulator, stack, network and decision path (uav_policy.pilot, the shield and safety layer included): flying through
    the ROS nodes changes nothing (and the random start heading, extra sim parameters, the weights' SAM readout, input
    size, layer sizes and frame stack and, without an hfov_deg argument, the camera recorded in the weights and the
    reward window it records reach the nodes; a network with the local map gets it from the frames and odom)."""
    from uav_eval.flights import evaluate_inprocess
    from uav_sim.simulator import SimConfig

    w = tmp_path / "w.safetensors"
    cfg = NetConfig(sam_readout=readout, height=size, width=size, **sam_sizes)
    window = 0.5 if trained_hfov is not None else None  # recorded with the camera: flown by both paths unasked
    wio.save_file(build_network(cfg, seed=4), cfg, w, camera_hfov_deg=trained_hfov, reward_window_fraction=window)
    monkeypatch.setenv("ROS_DOMAIN_ID", ros_domain)
    sim_args = (f"hfov_deg:={hfov}",) if hfov is not None else ()
    kw = dict(seed=3, start_yaw_jitter_deg=jitter, safety=safety, shield=shield)
    world = "complex" if shield else "basic"  # the shield overrides this network there (34-50 times in 100 steps)
    over_ros = evaluate_once(FlightSpec("sam", str(w), world, 100, sim_args=sim_args, **kw))
    flown = hfov if hfov is not None else trained_hfov
    local = evaluate_inprocess(FlightSpec("sam", str(w), world, 100, hfov_deg=flown, **kw))
    assert (over_ros.crashes, over_ros.steps, over_ros.crash_sites) == (local.crashes, local.steps, local.crash_sites)
    assert (over_ros.turn_steps, over_ros.cells, over_ros.interventions) == (local.turn_steps, local.cells, local.interventions)
    assert local.interventions > 0 if safety else local.interventions == -1, local.interventions
    assert over_ros.shield_overrides == local.shield_overrides, "the shield overrode the same decisions"
    assert local.shield_overrides > 0 if shield else local.shield_overrides == -1, local.shield_overrides
    assert abs(over_ros.mean_reward - local.mean_reward) < 1e-5 and abs(over_ros.distance_m - local.distance_m) < 1e-6
    if trained_hfov is not None:  # the recorded camera was used: the default camera flies otherwise
        assert trained_hfov != SimConfig.hfov_deg
        fly = lambda **kw: evaluate_inprocess(FlightSpec("sam", str(w), "basic", 100, 3, jitter, **kw))  # noqa: E731
        by_header, default = fly(), fly(hfov_deg=SimConfig.hfov_deg)
        assert by_header.mean_reward == local.mean_reward and default.mean_reward != local.mean_reward
        paper_window = fly(reward_window_fraction=SimConfig.reward_window_fraction)  # same flight, another reward
        assert paper_window.crashes == local.crashes and paper_window.mean_reward != local.mean_reward


def test_the_planner_is_a_row_of_the_tables_in_process_only(tmp_path, capsys):
    """evaluate --model planner flies the privileged planner beside a network; over ROS it is refused by name."""
    from uav_eval.evaluate import main

    out = tmp_path / "p"
    args = ["--inprocess", "--model", "planner", "--worlds", "complex", "--steps", "40", "--insight-every", "0"]
    assert main([*args, "--start-yaw-jitter-deg", "180", "--out", str(out)]) == 0
    row = next(csv.DictReader(open(out / "results.csv")))
    assert (row["model"], row["weights"], row["steps"], row["crashes"]) == ("planner", "none", "40", "0")
    md = (out / "results.md").read_text()
    assert "| planner (5 frames) | no weights | 0 / 40: " in md and "flies behind the packaged networks' camera" in md
    assert main(["--from-csv", str(out / "results.csv"), "--out", str(tmp_path / "again")]) == 0, "its rows read back"
    assert main([*args[:2], "planner_map", *args[3:], "--out", str(tmp_path / "m")]) == 0
    assert "| planner (local map) | no weights | " in (tmp_path / "m" / "results.md").read_text()
    with pytest.raises(SystemExit) as e:
        main(["--model", "planner", "--worlds", "basic", "--out", str(tmp_path / "ros")])
    assert e.value.code == 2 and "--model planner needs --inprocess" in capsys.readouterr().err
