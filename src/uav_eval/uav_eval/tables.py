"""Result tables: runs pooled per policy, each policy's crash count with its exact Poisson interval, the
interquartile mean over policies (training seeds) with its stratified-bootstrap interval and the worst seed
beside the paper's numbers (results.md, uav_eval.stats), the rows as results.csv, and those rows read
back (`--from-csv`)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from uav_policy.insight import InsightSummary

from . import ENSEMBLE_SEP, LABELS, MODELS, PLANNER_WEIGHTS
from .flights import TURN_DEG, EvalResult
from .stats import Rate, aggregate

# The insight columns of results.csv, in InsightSummary's order (frames first).
INSIGHT_COLUMNS = ("insight_frames", *InsightSummary.NAMES)

PAPER = {  # Table 1 crashes / Table 2 mean reward, per 1000 test steps
    ("sam", "basic"): (0, 2.406),
    ("sam", "complex"): (1, 2.16),
    ("sam", "turbulent"): (1, -7.809),
    ("cnn", "basic"): (8, 2.459),
    ("cnn", "complex"): (5, 2.319),
    ("cnn", "turbulent"): (10, -7.83),
}


def pool(runs: list[EvalResult]) -> EvalResult:
    """Several evaluations of one weight file in one world as one (steps, crashes and distance summed)."""
    first = runs[0]
    steps = sum(r.steps for r in runs)
    reward = sum(r.mean_reward * r.steps for r in runs) / steps
    return EvalResult(
        first.model,
        first.world,
        first.weights,
        steps,
        sum(r.crashes for r in runs),
        reward,
        sum(r.distance_m for r in runs),
        *(
            sum(getattr(r, k) for r in runs) if all(getattr(r, k) >= 0 for r in runs) else -1
            for k in ("crash_sites", "turn_steps", "cells", "interventions")
        ),
        InsightSummary.pool([r.insight for r in runs]),
        sum(r.shield_overrides for r in runs) if all(r.shield_overrides >= 0 for r in runs) else -1,
        sum(r.teacher_agreement * r.steps for r in runs) / steps if all(r.teacher_agreement >= 0 for r in runs) else -1.0,
    )


# Two-sided 95% Student t quantiles by sample size n (n - 1 degrees of freedom); normal beyond 30.
T975 = {
    2: 12.706,
    3: 4.303,
    4: 3.182,
    5: 2.776,
    6: 2.571,
    7: 2.447,
    8: 2.365,
    9: 2.306,
    10: 2.262,
    11: 2.228,
    12: 2.201,
    13: 2.179,
    14: 2.160,
    15: 2.145,
    16: 2.131,
    17: 2.120,
    18: 2.110,
    19: 2.101,
    20: 2.093,
    21: 2.086,
    22: 2.080,
    23: 2.074,
    24: 2.069,
    25: 2.064,
    26: 2.060,
    27: 2.056,
    28: 2.052,
    29: 2.048,
    30: 2.045,
}


def mean_ci95(values) -> tuple[float, float]:
    """Mean and half-width of a 95% t confidence interval (nan for n < 2)."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return math.nan, math.nan
    if v.size < 2:
        return float(v.mean()), math.nan
    t = T975.get(v.size, 1.96)
    return float(v.mean()), float(t * v.std(ddof=1) / math.sqrt(v.size))


def fmt(mean: float, hw: float, digits: int = 2) -> str:
    if math.isinf(mean):
        return "no crash"
    return f"{mean:.{digits}f}" + ("" if math.isnan(hw) else f" ± {hw:.{digits}f}")


def distance_cell(runs: list[EvalResult]) -> str:
    dist, crashes = sum(r.distance_m for r in runs), sum(r.crashes for r in runs)
    free = sum(1 for r in runs if r.crashes == 0)
    head = f"{dist / crashes:.0f}" if crashes else f"no crash in {dist:.0f} m"
    return f"{head} ({free}/{len(runs)} runs crash-free)"


def pooled_table(results, models, worlds, title: str, column: str, cell, intro: str = "") -> list[str]:
    """A Markdown table with one cell per (world, model) computed from all runs of that pair."""
    lines = [f"### {title}", "", *([intro, ""] if intro else [])]
    lines += ["| world | " + " | ".join(f"{LABELS[m]}{column}" for m in models) + " |", "|" + "---|" * (1 + len(models))]
    for world in worlds:
        cells = []
        for m in models:
            runs = [r for r in results if r.model == m and r.world == world]
            cells.append(cell(runs) if runs else "-")
        lines.append(f"| {world} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def seed_world_matrix(results: list[EvalResult], model: str, worlds: list[str], key) -> np.ndarray | None:
    """(weight files x worlds) of key(result) for a model, or None unless every file flew every world once."""
    files = list(dict.fromkeys(r.weights for r in results if r.model == model))
    cell = {(r.weights, r.world): key(r) for r in results if r.model == model}
    if not files or len(cell) != sum(1 for r in results if r.model == model):
        return None
    if any((f, w) not in cell for f in files for w in worlds):
        return None
    return np.array([[cell[f, w] for w in worlds] for f in files])


def crash_count_table(results: list[EvalResult], models: list[str], worlds: list[str]) -> list[str]:
    """One row per policy: crashes / steps and the rate per 1000 steps with its exact Poisson 95 % interval."""
    lines = [
        "### Crashes per policy: count / steps, per 1000 steps [exact Poisson 95 %]",
        "",
        "| model | weights | " + " | ".join(worlds) + " |",
        "|" + "---|" * (2 + len(worlds)),
    ]
    for m in models:
        for weights in dict.fromkeys(r.weights for r in results if r.model == m):
            row = {r.world: r for r in results if r.model == m and r.weights == weights}
            cells = [count_cell(row[w]) if w in row else "-" for w in worlds]
            lines.append(f"| {LABELS[m]} | {short_weights(weights)} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def count_cell(r: EvalResult) -> str:
    return f"{r.crashes} / {r.steps}: {Rate(r.crashes, r.steps)}"


def short_weights(weights: str) -> str:
    """A weights column as a table shows it: the packaged set, one file's name or a group's first and size."""
    if not weights:
        return "packaged"
    if weights == PLANNER_WEIGHTS:
        return "no weights"
    files = weights.split(ENSEMBLE_SEP)
    name = f"{Path(files[0]).parent.name}/{Path(files[0]).name}"
    return name if len(files) == 1 else f"{name} + {len(files) - 1} more"


def write_csv(results: list[EvalResult], csv_path: Path) -> Path:
    """results.csv: one row per run (crashes with their interval, reward, distance, behaviour, insight)."""
    with open(csv_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "model",
                "world",
                "weights",
                "steps",
                "crashes",
                "crashes_per_1000",
                "crashes_per_1000_low",
                "crashes_per_1000_high",
                "mean_reward",
                "distance_m",
                "distance_between_crashes_m",
                "crash_sites",
                "turn_steps",
                "cells_visited",
                "safety_interventions",
                "shield_overrides",
                *INSIGHT_COLUMNS,
                "faithfulness",
                "faithfulness_vs_mean_map",
            ]
        )
        for r in results:
            i = r.insight
            insight = [""] * (len(INSIGHT_COLUMNS) + 2)
            if i is not None:
                insight = [i.frames, *(f"{getattr(i, k):.4f}" for k in InsightSummary.FIELDS)]
                insight += [f"{i.faithfulness:.4f}", f"{i.faithfulness_vs_mean_map:.4f}"]
            w.writerow(
                [
                    r.model,
                    r.world,
                    r.weights,
                    r.steps,
                    r.crashes,
                    f"{1000 * r.crashes / r.steps:.2f}",
                    *(f"{v:.2f}" for v in Rate(r.crashes, r.steps).interval_per_1000),
                    f"{r.mean_reward:.4f}",
                    f"{r.distance_m:.2f}",
                    f"{r.distance_between_crashes_m:.2f}",
                    r.crash_sites,
                    r.turn_steps,
                    r.cells,
                    r.interventions,
                    r.shield_overrides,
                    *insight,
                ]
            )
    return csv_path


def write_tables(results: list[EvalResult], out_dir: Path, steps: int, protocol: str = "") -> tuple[Path, Path]:
    """results.csv (one row per run) and results.md (Tables 1-2 and distance, mean ± 95% CI over seeds)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = write_csv(results, out_dir / "results.csv")
    models = sorted({r.model for r in results}, key=MODELS.index)
    worlds = list(dict.fromkeys(r.world for r in results))
    lines = [
        f"Exploit-only (epsilon 0) evaluation, {steps} lockstep steps per run"
        + (" at most (each row's steps are its own)" if any(r.steps != steps for r in results) else "")
        + "; over the weight files (training seeds) the interquartile mean (IQM) with its stratified-bootstrap 95 % "
        "interval and the worst seed (docs/RESULTS.md, 'How we measure'); n = weight files per cell."
        + (f" {protocol}" if protocol else ""),
        "",
    ]
    lines += crash_count_table(results, models, worlds)
    for title, key, digits, idx, worst in (  # idx: the column of PAPER
        ("Table 1: crashes per 1000 steps", lambda r: 1000 * r.crashes / r.steps, 2, 0, "max"),
        ("Table 2: mean reward per step", lambda r: r.mean_reward, 3, 1, "min"),
    ):
        lines += [f"### {title}", ""]
        lines += [
            "| world | " + " | ".join(f"{LABELS[m]} IQM [95 %] | worst seed | paper" for m in models) + " |",
            "|" + "---|" * (1 + 3 * len(models)),
        ]
        for world in worlds:
            cells = []
            for m in models:
                vals = [key(r) for r in results if r.model == m and r.world == world]
                agg = aggregate(vals, worst) if vals else None
                cells += [agg.cell(digits), f"{agg.worst:.{digits}f}"] if agg else ["-", "-"]
                paper = PAPER.get((m, world))
                cells.append(str(paper[idx]) if paper else "-")
            lines.append(f"| {world} | " + " | ".join(cells) + " |")
        if len(worlds) > 1:  # all worlds at once: seeds x worlds, resampled over seeds within each world
            cells = []
            for m in models:
                matrix = seed_world_matrix(results, m, worlds, key)
                agg = aggregate(matrix, worst) if matrix is not None else None
                cells += [agg.cell(digits), f"{agg.worst:.{digits}f}"] if agg else ["-", "-"]
                cells.append("-")
            lines.append("| all worlds | " + " | ".join(cells) + " |")
        lines.append("")
    # Distance between crashes pooled over runs: runs without a crash would otherwise be dropped.
    lines += pooled_table(results, models, worlds, "Distance flown between crashes (m), pooled over runs", "", distance_cell)
    if results and all(r.crash_sites >= 0 for r in results):
        intro = (
            "A site is where a crashing step began (0.1 m grid), counted per run. With a fixed start pose a "
            "deterministic policy repeats its flight after every crash, so many crashes at few sites are one "
            "failure counted again."
        )
        lines += pooled_table(
            results,
            models,
            worlds,
            "Crashes and distinct crash sites, summed over runs",
            " crashes / sites",
            lambda runs: f"{sum(r.crashes for r in runs)} / {sum(r.crash_sites for r in runs)}",
            intro,
        )
    if results and all(r.turn_steps >= 0 and r.cells >= 0 for r in results):
        intro = (
            f"A turning step changes the heading by more than {TURN_DEG:g}°; the area is the number of distinct "
            "1 m x 1 m cells flown through, per run. A policy that circles on the spot crashes rarely but turns "
            "on almost every step and covers little. Mean ± 95% CI over the weight files."
        )
        lines += pooled_table(
            results,
            models,
            worlds,
            "Flight behaviour: turning steps (%) / floor area covered (m² per 1000 steps)",
            "",
            lambda runs: (
                fmt(*mean_ci95([100 * r.turn_steps / r.steps for r in runs]), 0)
                + " / "
                + fmt(*mean_ci95([1000 * r.cells / r.steps for r in runs]), 0)
            ),
            intro,
        )
    for field, title, intro in (
        (
            "interventions",
            "Safety layer interventions per 1000 steps (commands it changed; the crashes above are with it on)",
            "Counted by policy_node (/diagnostics) over each flight. Mean ± 95% CI over the weight files.",
        ),
        (
            "shield_overrides",
            "Shield interventions per 1000 steps (decisions it changed; the crashes above are with it on)",
            "Counted over each flight: the network flew the rest. Mean ± 95% CI over the weight files.",
        ),
    ):
        if results and all(getattr(r, field) >= 0 for r in results):
            per_1000 = lambda runs, f=field: fmt(*mean_ci95([1000 * getattr(r, f) / r.steps for r in runs]), 0)  # noqa: E731
            lines += pooled_table(results, models, worlds, title, "", per_1000, intro)
    if results and all(r.insight is not None for r in results):
        lines += insight_table(results, models, worlds)
    md_path = out_dir / "results.md"
    md_path.write_text("\n".join(lines))
    return md_path, csv_path


def insight_table(results: list[EvalResult], models: list[str], worlds: list[str]) -> list[str]:
    """What the decisions looked at (uav_policy.insight), one row per model and world, mean ± 95% CI over the
    weight files; the deletion test's rates pooled over them, their ratio the faithfulness."""
    lines = [
        "### What the decisions look at (SAM: the attention they use; CNN: Grad-CAM saliency)",
        "",
        "Every step measured. Entropy: per query, normalised (1 = uniform). Top 10 %: the mass on the top tenth of "
        "the nodes (0.1 = uniform). Map correlation: median correlation of each frame's map with the run's mean map "
        "(1 = the same map whatever is seen). Deletion: the share of steps whose action changes when the top 10 % "
        "of nodes, as many random ones, or the top 10 % of the mean of the maps before it read 'no return'; "
        "faithfulness = top / random, and top / mean map (a fixed prior scores about 1 against the mean map). Near: the "
        "mass on pixels nearer than 3 m over their share of the image (1 = no preference). Curves (RISE): the mean "
        "lead of the chosen action's Q over the best other as the nodes are removed (deletion: lower is more "
        "faithful) or restored into an image of no return (insertion: higher is), in the map's / the mean map's / a "
        "random order.",
        "",
        "| model | world | entropy | top 10 % | map correlation | deletion top / random / mean map | faithfulness "
        "| faithfulness vs mean map | near | deletion curve | insertion curve |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in models:
        for world in worlds:
            got = [r.insight for r in results if r.model == m and r.world == world]
            if not got:
                continue
            cell = lambda k, got=got: fmt(*mean_ci95([getattr(i, k) for i in got if not math.isnan(getattr(i, k))]), 2)  # noqa: E731
            top, rand = (float(np.mean([getattr(i, k) for i in got])) for k in ("deletion_top", "deletion_random"))
            prior = [i.deletion_mean_map for i in got if not math.isnan(i.deletion_mean_map)]
            by_prior = float(np.mean(prior)) if prior else math.nan

            def curve(kind: str, got=got) -> str:
                areas = [np.nanmean([getattr(i, f"{kind}_area{b}") for i in got]) for b in ("", "_mean_map", "_random")]
                return " / ".join(f"{a:.2f}" for a in areas)

            lines.append(
                f"| {LABELS[m]} | {world} | {cell('entropy')} | {cell('top_share')} | {cell('map_correlation')} "
                f"| {top:.3f} / {rand:.3f} / {by_prior:.3f} | {InsightSummary.ratio(top, rand):.2f} "
                f"| {InsightSummary.ratio(top, by_prior) if prior else math.nan:.2f} | {cell('near_ratio')} "
                f"| {curve('deletion')} | {curve('insertion')} |"
            )
    return [*lines, *checks_table(results, models, worlds), ""]


def checks_table(results: list[EvalResult], models: list[str], worlds: list[str]) -> list[str]:
    """Why a map can be ignored (conicity, sufficiency) and how much of it is on the planner's reason."""
    lines = [
        "",
        "### Can the map be ignored? Does it show the reason?",
        "",
        "Conicity: the mean cosine of the values the attention weighs with their mean (1 = all alike: any weighting "
        "gives the same output; the CNN's Grad-CAM weighs none). Sufficiency: the share of steps that keep their action "
        "with only the top 10 % of the nodes kept (the rest 'no return'), in the map's / a random / the mean map's "
        "order. Reason: what the planner's decision on the frame is about (uav_sim.planner, docs/INSIGHT.md); the "
        "map's mass on its pixels over their share of the image, and the share of steps whose top node sees it "
        "(steps where the reason shows in the newest frame).",
        "",
        "| model | world | conicity | sufficiency top / random / mean map | mass on the reason | top node on the reason |",
        "|---|---|---|---|---|---|",
    ]
    for m in models:
        for world in worlds:
            got = [r.insight for r in results if r.model == m and r.world == world and r.insight is not None]
            if not got:
                continue

            def mean(k: str, got=got) -> float:
                v = [getattr(i, k) for i in got if not math.isnan(getattr(i, k))]
                return float(np.mean(v)) if v else math.nan

            num = lambda v, unit="": "-" if math.isnan(v) else f"{v:.2f}{unit}"  # noqa: E731
            kept = " / ".join(num(mean(k)) for k in ("sufficiency_top", "sufficiency_random", "sufficiency_mean_map"))
            top = mean("reason_top")
            lines.append(
                f"| {LABELS[m]} | {world} | {num(mean('conicity'))} | {kept} | {num(mean('reason_mass'), 'x')} "
                f"| {'-' if math.isnan(top) else f'{100 * top:.0f} %'} |"
            )
    return lines


def _csv_insight(row: dict, where: str) -> InsightSummary | None:
    """The insight columns of a row, or None when the row has none (tables written before them, or not measured)."""
    if row.get("insight_frames") in (None, ""):
        return None
    values = [_csv_whole(row, "insight_frames", where)]
    for column in INSIGHT_COLUMNS[1:]:
        try:
            values.append(float(row.get(column) or "nan"))
        except ValueError:
            raise ValueError(f"{where}: {column} must be a number, got {row[column]!r}") from None
    return InsightSummary(*values)


RESULTS_COLUMNS = ("model", "world", "weights", "steps", "crashes", "mean_reward", "distance_m")


def _csv_whole(row: dict, column: str, where: str, default: int | None = None) -> int:
    text = row.get(column)
    if text in (None, "") and default is not None:
        return default
    try:
        return int(text)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {column} must be a whole number, got {text!r}") from None


def _csv_number(row: dict, column: str, where: str) -> float:
    try:
        value = float(row[column])
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value):
        raise ValueError(f"{where}: {column} must be a finite number, got {row[column]!r}")
    return value


def read_results_csvs(paths: list[str]) -> list[EvalResult]:
    """The rows of earlier results.csv files (write_tables' format) as EvalResults, in order. ValueError,
    naming the file and line, for a missing or unreadable file, a missing column, a model other than sam
    or cnn, a count that is not a whole number or is impossible (crashes > steps), a number that is not
    finite, or no rows at all. The optional columns (crash_sites, turn_steps, cells_visited, safety_interventions,
    shield_overrides) default to -1 (unknown), as for tables written before they existed."""
    results = []
    for path in paths:
        try:
            with open(path, newline="") as f:
                reader = csv.DictReader(f)
                missing = [c for c in RESULTS_COLUMNS if c not in (reader.fieldnames or [])]
                if missing:
                    raise ValueError(f"{path}: no column {', '.join(missing)} (not an evaluate results.csv?)")
                rows = list(reader)
        except (OSError, UnicodeDecodeError, csv.Error) as e:
            raise ValueError(f"{path}: cannot read it ({e})") from None
        for line, r in enumerate(rows, start=2):
            where = f"{path} line {line}"
            if r["model"] not in MODELS:
                raise ValueError(f"{where}: model must be one of {', '.join(MODELS)}, got {r['model']!r}")
            if not r["world"] or not r["weights"]:
                raise ValueError(f"{where}: world and weights must not be empty (a short row?)")
            steps, crashes = _csv_whole(r, "steps", where), _csv_whole(r, "crashes", where)
            if steps < 1 or not 0 <= crashes <= steps:
                raise ValueError(f"{where}: needs steps >= 1 and 0 <= crashes <= steps, got {steps} and {crashes}")
            results.append(
                EvalResult(
                    r["model"],
                    r["world"],
                    r["weights"],
                    steps,
                    crashes,
                    _csv_number(r, "mean_reward", where),
                    _csv_number(r, "distance_m", where),
                    _csv_whole(r, "crash_sites", where, -1),
                    _csv_whole(r, "turn_steps", where, -1),
                    _csv_whole(r, "cells_visited", where, -1),
                    _csv_whole(r, "safety_interventions", where, -1),
                    _csv_insight(r, where),
                    _csv_whole(r, "shield_overrides", where, -1),
                )
            )
    if not results:
        raise ValueError(f"no rows in {', '.join(paths)}")
    return results
