"""Episode bookkeeping shared by the trainer node, the in-process trainer and evaluation, and reading a
run's progress rows back."""

from __future__ import annotations

import dataclasses
from collections import deque


@dataclasses.dataclass
class EpisodeStats:
    """Running episode length/reward, one episode open per actor; `window` recent episodes for the paper's
    training curves."""

    window: int = 20
    episodes: int = 0
    history: list = dataclasses.field(default_factory=list)  # (env_step, length, reward)

    def __post_init__(self):
        self._recent = deque(maxlen=self.window)
        self._open: dict[int, tuple[int, float]] = {}  # actor: (length, reward) of its episode so far

    def step(self, reward: float, ended: bool, env_step: int, actor: int = 0) -> tuple[int, float] | None:
        """Account one step of `actor`; returns (length, reward) when it ended that actor's episode (a
        collision or a time limit)."""
        length, total = self._open.get(actor, (0, 0.0))
        done = (length + 1, total + reward)
        if not ended:
            self._open[actor] = done
            return None
        self._open.pop(actor, None)
        self.history.append((env_step, *done))
        self._recent.append(done)
        self.episodes += 1
        return done

    def mean_length(self) -> float:
        return sum(x[0] for x in self._recent) / len(self._recent) if self._recent else float("nan")

    def mean_reward(self) -> float:
        return sum(x[1] for x in self._recent) / len(self._recent) if self._recent else float("nan")


def steady_metrics_rows(rows: list[dict]) -> list[dict]:
    """A run's metrics.csv rows (csv.DictReader's) once learning runs: after the first row with updates,
    whose rates still mix in the steps before learning started."""
    return [r for r in rows if int(r["updates"]) > 0][1:]
