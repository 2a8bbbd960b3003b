"""What trainer_node reports (no ROS): the values on /diagnostics and the progress line in its log."""

from __future__ import annotations

from collections import Counter


def status_values(training, actors, counts: dict, push_latency_ms: list[float]) -> dict:
    """/diagnostics: progress, the pairing counts of every actor summed, each actor's steps and epsilon when there
    are several, and the node's own counts."""
    t = training
    lat = sorted(push_latency_ms[-100:])
    pairing = Counter()
    for actor in actors:
        pairing.update(actor.pairing.report())
    per_actor = {}
    if len(actors) > 1:
        for a in actors:
            per_actor[f"steps {a.ns}"] = t.actor_steps[a.index]
            per_actor[f"epsilon {a.ns}"] = f"{t.epsilon(a.index):.3f}"
    return {
        "env_steps": t.env_steps,
        "updates": t.learner.updates,
        "episodes": t.stats.episodes,
        "epsilon": f"{t.epsilon():.3f}",
        "loss": f"{t.last_loss:.4f}",
        "replay_transitions": len(t.replay),
        "checkpoint_failures": t.checkpoint_failures,
        "push_latency_p50_ms": f"{lat[len(lat) // 2]:.1f}" if lat else "nan",
        "total_steps": t.cfg.total_steps,
        "actors": len(actors),
        "actors_silent": sum(a.silent is not None for a in actors),
        **per_actor,
        **pairing,
        **counts,
    }


def progress_line(row: dict, status: dict, training, actors) -> str:
    """The log's progress line from a metrics row and the status values."""
    total = training.cfg.total_steps
    pct = f" ({100.0 * row['env_steps'] / total:.1f}%)" if total else ""
    unpaired = status["frames_without_action"] + status["frames_without_outcome"] + status["outcomes_or_actions_without_frame"]
    per_actor = ""
    if len(actors) > 1:
        per_actor = " | actors " + " ".join(f"{a.ns} {training.actor_steps[a.index]}" for a in actors)
    ratio = row["updates_per_s"] / max(row["env_steps_per_s"], 1e-9)
    return (
        f"steps {row['env_steps']}{pct} updates {row['updates']} episodes {row['episodes']} "
        f"mean len {row['mean_episode_length']:.1f} mean ep reward {row['mean_episode_reward']:.1f} "
        f"eps {row['epsilon']:.3f} loss {row['loss']:.4f} | {row['env_steps_per_s']:.0f} steps/s "
        f"{row['updates_per_s']:.1f} updates/s (ratio {ratio:.2f})"
        f" | unpaired {unpaired} breaks {status['chain_breaks']} restarts {status['stamp_restarts']}{per_actor}"
    )
