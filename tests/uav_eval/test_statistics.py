"""Figures that resolve and choices that never see the test: Poisson intervals, the aggregate over seeds, the
validation worlds and the rule that picks one network on them."""

import csv
import dataclasses
import itertools
import math
from pathlib import Path

import pytest

from uav_eval import selection
from uav_eval.flights import EvalResult
from uav_eval.stats import Rate, aggregate, poisson_interval
from uav_eval.tables import read_results_csvs, write_tables
from uav_sim.world import (
    BUILTIN_WORLDS,
    PARTITIONS,
    TRAINING_LAYOUTS_FROM,
    VALIDATION_FAMILIES,
    VALIDATION_SEEDS_FROM,
    VALIDATION_WORLDS,
    WorldError,
    load_world,
    procedural_world,
    training_layout,
    training_layouts,
)

# Garwood's exact 95 % limits for a Poisson mean (e.g. Ulm 1990, Table 1; the guide's 1.1-10.2 and 12-31).
PUBLISHED = {0: (0.0, 3.689), 1: (0.0253, 5.572), 2: (0.242, 7.225), 4: (1.090, 10.242), 10: (4.795, 18.390)}
PUBLISHED[20] = (12.217, 30.888)


@pytest.mark.parametrize("count", sorted(PUBLISHED))
def test_poisson_intervals_match_the_published_values(count):
    low, high = poisson_interval(count)
    assert low == pytest.approx(PUBLISHED[count][0], abs=6e-4) and high == pytest.approx(PUBLISHED[count][1], abs=6e-4)


def test_a_rate_scales_its_interval_to_crashes_per_1000_steps_and_bad_counts_are_refused():
    r = Rate(4, 2000)
    assert r.per_1000 == 2.0 and r.interval_per_1000 == pytest.approx((0.545, 5.121), abs=1e-3)
    assert str(r) == "2.00 [0.54, 5.12]"
    for bad in (-1, 2.5):
        with pytest.raises(ValueError, match="whole number"):
            poisson_interval(bad)


def test_the_iqm_ignores_one_outlier_seed_and_the_worst_seed_shows_it():
    agg = aggregate([1.0, 2.0, 3.0, 4.0, 100.0])
    assert agg.iqm == pytest.approx(3.0), "IQM of five: the mean of the middle three"
    assert agg.worst == 100.0 and agg.n == 5
    assert agg.low <= agg.iqm <= agg.high and agg.high < 100.0
    assert aggregate([1.0, 2.0, 3.0, 4.0, 100.0]) == agg, "the bootstrap is seeded: the same table gives the same interval"
    # A mean would be pulled to 22: the IQM is not.
    assert aggregate([2.0, 2.0, 2.0, 2.0, 2.0]) == dataclasses.replace(agg, iqm=2.0, low=2.0, high=2.0, worst=2.0)
    assert aggregate([5.0, 1.0], worst="min").worst == 1.0
    one = aggregate([3.0])
    assert one.n == 1 and math.isnan(one.low) and one.cell() == "3.00 (n=1)"
    with pytest.raises(ValueError, match="finite"):
        aggregate([1.0, math.nan])


def test_the_interval_does_not_depend_on_what_ran_before_in_the_process():
    """rliable's bootstrap drew from numpy's process-wide generator: a CI run got two intervals for one table."""
    import subprocess
    import sys

    import numpy as np

    table = [[1.0, 0.5], [2.0, 0.7], [3.0, 4.0], [4.0, 0.1], [100.0, 2.0]]
    here = aggregate(table)
    np.random.seed(12345)
    np.random.random(1000)  # anything that draws from, or seeds, numpy's global generator
    assert aggregate(table) == here
    assert aggregate(table) == aggregate(table), "two calls in a row agree"
    code = (
        "import numpy as np, uav_eval.evaluate, uav_eval.tables, torch; np.random.seed(7); torch.manual_seed(3);"
        f"from uav_eval.stats import aggregate; a = aggregate({table!r}); print(repr((a.low, a.high, a.iqm)))"
    )
    fresh = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert fresh == repr((here.low, here.high, here.iqm)), "a fresh process that imported what evaluate imports agrees"


def result(weights: str, world: str, steps: int, crashes: int, reward: float = 1.0) -> EvalResult:
    return EvalResult("sam", world, weights, steps, crashes, reward, 100.0)


def test_the_tables_give_each_policys_count_and_interval_and_the_iqm_over_seeds(tmp_path):
    rates = {"a": 1, "b": 2, "c": 3, "d": 4, "e": 40}  # crashes in 1000 steps of each world
    worlds = ("basic", "complex")
    results = [result(f"runs/{w}/policy_sam.safetensors", world, 1000, c) for w, c in rates.items() for world in worlds]
    md, path = write_tables(results, tmp_path, 1000)
    text = md.read_text()
    assert "| D3QN-SAM | a/policy_sam.safetensors | 1 / 1000: 1.00 [0.03, 5.57] | 1 / 1000: 1.00 [0.03, 5.57] |" in text
    row = next(line for line in text.splitlines() if line.startswith("| basic |") and "IQM" not in line and "[" in line)
    assert row.startswith("| basic | 3.00 [") and "(n=5) | 40.00 | 0 |" in row, row
    assert "| all worlds | 3.00 [" in text
    rows = list(csv.DictReader(open(path)))
    assert (rows[0]["crashes_per_1000_low"], rows[0]["crashes_per_1000_high"]) == ("0.03", "5.57")
    assert len(read_results_csvs([str(path)])) == len(results), "tables with the interval columns read back"


def test_validation_training_held_out_and_test_worlds_are_disjoint():
    seeds = [VALIDATION_SEEDS_FROM + int(name.split(":")[1]) for name in VALIDATION_WORLDS]
    assert len(set(seeds)) == len(VALIDATION_WORLDS) >= 8
    # The training stream of any seed starts at random:1000 and counts up; the validation layouts lie below it.
    assert max(seeds) < TRAINING_LAYOUTS_FROM
    first = next(training_layouts(0))
    assert first.name == f"random:{TRAINING_LAYOUTS_FROM}"
    # The held-out layouts docs/RESULTS.md reports (random:0..2, random_partitions:0..2) are not among them.
    assert min(seeds) > 2
    worlds = [load_world(name) for name in VALIDATION_WORLDS]
    assert {w.name for w in worlds} == set(VALIDATION_WORLDS) and not set(VALIDATION_WORLDS) & set(BUILTIN_WORLDS)
    reported = {procedural_world(s, partitions=p).obstacles for s in range(3) for p in (False, True)}
    test = {load_world(name).obstacles for name in BUILTIN_WORLDS}
    assert not {w.obstacles for w in worlds} & (reported | test)
    # The mixed training stream (plain, partitions, doorways) shares no layout with validation or the tests either.
    mixed = [w for seed in range(5) for w in itertools.islice(training_layouts(seed, families="mixed"), 30)]
    assert {w.name.split(":")[0] for w in mixed} == {"random", PARTITIONS, "doorways"}
    assert min(int(w.name.split(":")[1]) for w in mixed) >= TRAINING_LAYOUTS_FROM
    assert not {w.obstacles for w in mixed} & ({w.obstacles for w in worlds} | reported | test)
    with pytest.raises(ValueError, match="start at 1000"):
        training_layout(999, "mixed")
    # Every family is there, with what it promises.
    families = [VALIDATION_FAMILIES[int(n.split(":")[1]) % len(VALIDATION_FAMILIES)] for n in VALIDATION_WORLDS]
    assert set(families) == set(VALIDATION_FAMILIES)
    for w, family in zip(worlds, families, strict=True):
        sx, sy, _ = w.start_xyz_m
        assert all(math.hypot(o.x_m - sx, o.y_m - sy) >= 2.0 for o in w.obstacles if o.shape == "cylinder"), w.name
        assert w.weather.any == (family == "weather"), w.name
        if family == "doorways":
            walls = [o for o in w.obstacles if o.shape == "box"]
            assert len(walls) >= 2 and all(o.size_x_m == pytest.approx(0.2) for o in walls)
            # The wall segments at one x leave a doorway of 1.4-2.0 m across the room.
            for x in {o.x_m for o in walls}:
                across = sum(o.size_y_m for o in walls if o.x_m == x)
                assert 1.4 <= w.width_m - across <= 2.0, (w.name, x)
    for bad in ("validation", "validation:100", "validation:x"):
        with pytest.raises(WorldError, match="validation:K"):
            load_world(bad)


def test_the_rule_picks_the_fewest_validation_crashes_ties_to_the_later_file_and_stops_files_that_cannot_win(
    tmp_path, monkeypatch
):
    crashes = {"policy_sam_step10": 3, "policy_sam_step20": 1, "policy_sam_step30": 1, "policy_sam": 2}
    flown = []

    def fake(spec, *_):
        weights, world, steps, max_crashes = spec.weights, spec.world, spec.steps, spec.max_crashes
        name = Path(weights).stem
        flown.append((name, world))
        i = list(VALIDATION_WORLDS).index(world)
        c = crashes[name] if i == 1 else 0  # each file's crashes all come in the second validation world
        if max_crashes and c >= max_crashes:
            return result(weights, world, steps // 2, max_crashes)
        return result(weights, world, steps, c)

    monkeypatch.setattr("uav_eval.flights.evaluate_inprocess", fake)
    for name in crashes:
        (tmp_path / f"{name}.safetensors").write_bytes(b"")
    files = selection.run_files(tmp_path, "sam")
    assert [f.stem for f in files] == list(crashes), "snapshots by step, then the final weights"
    chosen = selection.choose_run(tmp_path, "sam", steps=10, log=lambda _: None)
    assert Path(chosen.weights).stem == "policy_sam_step30", "1 crash ties step20's: the later file wins"
    assert chosen.steps == 10 * len(VALIDATION_WORLDS) and chosen.complete
    # step20 could only tie, step10 only lose: both stopped in the second world, never flown further.
    for name in ("policy_sam_step20", "policy_sam_step10"):
        assert [w for n, w in flown if n == name] == list(VALIDATION_WORLDS[:2]), name
    rows = list(csv.DictReader(open(tmp_path / "validation.csv")))
    assert [(r["weights"], r["chosen"]) for r in rows if r["chosen"] == "1"] == [("policy_sam_step30.safetensors", "1")]
    assert selection.read_chosen(tmp_path) == chosen
    flown.clear()
    assert selection.choose_run(tmp_path, "sam", steps=10, log=lambda _: None) == chosen and not flown, "reused"
    assert selection.choose_run(tmp_path, "sam", steps=10, log=lambda _: None, again=True) == chosen and flown


def test_choose_names_one_file_per_run_and_one_across_runs(tmp_path, monkeypatch, capsys):
    per_run = {"r0": {"policy_cnn_step5": 4, "policy_cnn": 6}, "r1": {"policy_cnn_step5": 2, "policy_cnn": 2}}

    def fake(spec, *_):
        weights, world, steps, max_crashes = spec.weights, spec.world, spec.steps, spec.max_crashes
        c = per_run[Path(weights).parent.name][Path(weights).stem] if world == VALIDATION_WORLDS[0] else 0
        return result(weights, world, steps, min(c, max_crashes) if max_crashes else c)

    monkeypatch.setattr("uav_eval.flights.evaluate_inprocess", fake)
    for run, files in per_run.items():
        (tmp_path / run).mkdir()
        for name in files:
            (tmp_path / run / f"{name}.safetensors").write_bytes(b"")
    assert selection.main([str(tmp_path / "r0"), str(tmp_path / "r1"), "--steps", "5", "--across-runs"]) == 0
    out = capsys.readouterr().out
    assert f"chosen: {tmp_path / 'r0' / 'policy_cnn_step5.safetensors'} (4 crashes" in out
    assert f"chosen: {tmp_path / 'r1' / 'policy_cnn.safetensors'} (2 crashes" in out
    assert f"chosen across the runs: {tmp_path / 'r1' / 'policy_cnn.safetensors'}" in out
    assert selection.main([str(tmp_path / "none")]) == 2
    assert "none: holds no weights files" in capsys.readouterr().err


def test_confidence_interval_matches_a_hand_computed_t_interval():
    from uav_eval.tables import mean_ci95

    mean, hw = mean_ci95([0.0, 1.0, 2.0])  # s = 1, n = 3: 4.303 * 1 / sqrt(3)
    assert mean == 1.0 and hw == pytest.approx(4.303 / 3**0.5)
    assert math.isnan(mean_ci95([5.0])[1])
