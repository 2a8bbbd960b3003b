"""The teacher: everything the privileged planner gives a training run, in one place, for the in-process loop and
trainer_node alike (docs/ALGORITHM.md, "The privileged planner and the teacher"):

- its settings (`TeacherConfig`: which planner, how often it flies, how much of it the learner takes);
- the label of a frame: the planner's action in process, sim_node's `uav_interfaces/TeacherLabel` over ROS
  (`label_action` refuses a label that names no action of the table or scores another number of actions);
- the reason's cells: the share of each attention node the pixels of its reason cover, image cells then, with the
  local map, the map cells those pixels put there (`reason_shares`);
- the DAgger draw: whether the teacher flies a step instead of the student (`DaggerDraw`);
- what it teaches: DQfD's large-margin loss on its action and the loss pulling SAM's attention onto its reason
  (`teaching_terms`).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from uav_common import contract
from uav_common.frame_stack import node_shares
from uav_common.local_map import LocalMap
from uav_common.settings import setting

if TYPE_CHECKING:  # the losses take tensors; the settings and labels load without torch (train starts without it)
    import torch

NO_LABEL = -1  # a frame without the teacher's action


@dataclasses.dataclass(frozen=True)
class TeacherConfig:
    """The teacher's settings (trainer_node parameters and in-process flags of the same names)."""

    teacher: str = setting(
        "none",
        "A teacher for every training frame (uav_sim.planner; over ROS sim_node's teacher_label, which train turns on): "
        "stack, the planner knowing what the last frame_stack frames showed (realizable from the state); all, knowing the "
        "whole world; map, planning on the local map of the measured depth and odometry (what a drone knows); none, pure RL",
        choices=contract.TEACHERS,
    )
    teacher_act_start: float = setting(
        1.0,
        "With a teacher: the probability that it flies a step instead of the student at the start, falling linearly "
        "to 0 at the end of the budget (DAgger: the student's own states are labelled too)",
        0.0,
        1.0,
    )
    teacher_weight: float = setting(
        1.0, "With a teacher: weight of the large-margin loss on its actions (DQfD's lambda_2) beside the TD loss", 0.0, 100.0
    )
    teacher_margin: float = setting(0.8, "With a teacher: the margin the teacher's action must lead by (DQfD's 0.8)", 0.0, 100.0)
    attention_weight: float = setting(
        0.0,
        "With a teacher, SAM's query readout: weight of the loss pulling the attention shown onto the cells of the "
        "teacher's reason in the newest frame (-log of the map's mass there; over ROS the reason of sim_node's teacher_label); "
        "0 = none; the CNN has no attention and ignores it",
        0.0,
        100.0,
    )

    @property
    def teaches(self) -> bool:
        return self.teacher != "none"

    def pulls_attention(self, model: str) -> bool:
        """attention_weight acts on `model`: SAM's attention is pulled onto the teacher's reason (the CNN has none)."""
        return self.attention_weight > 0.0 and model == "sam"


def label_action(label, actions: int) -> int:
    """The action of a TeacherLabel (anything with `action` and `scores`); NO_LABEL for a label that names no action
    of a table of `actions` or scores another number of actions."""
    return label.action if 0 <= label.action < actions and len(label.scores) == actions else NO_LABEL


def reason_shares(
    on_input: np.ndarray,
    cells: tuple[int, int],
    local_map: LocalMap | None = None,
    map_grid: tuple[int, float] | None = None,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """The share of each attention node the teacher's reason covers: `on_input` the reason's mask on the network's
    input, shared over the image's `cells`; with `local_map` (and its `map_grid`) the map's cells too, those the
    reason's pixels (`mask`, on the camera image the map was built from) put there. Image nodes first, as the
    network orders them."""
    shares = node_shares(on_input, cells)
    if local_map is None:
        return shares
    grid = local_map.egocentric(*map_grid, near_keys=local_map.keys_at(mask))
    return np.concatenate([shares, node_shares(grid > 0, cells)])


class DaggerDraw:
    """Who flies a labelled step: the teacher with the given probability (the run's schedule), else the student.
    One draw per labelled decision, from a generator of the run's seed, in process as over ROS."""

    def __init__(self, seed: int):
        self._rng = np.random.default_rng([seed, 7])

    def __call__(self, label: int, probability: float) -> int | None:
        """The teacher's action `label` when it flies this step, None when the student does (or there is no label)."""
        if label < 0:
            return None
        return label if self._rng.random() < probability else None


def large_margin_loss(q: torch.Tensor, teacher: torch.Tensor, margin: float) -> torch.Tensor:
    """DQfD's supervised loss (Hester et al. 2018): J_E = max_a [Q(s, a) + l(a_E, a)] - Q(s, a_E), l = `margin` for
    a != a_E and 0 for the teacher's a_E, averaged over the states with a teacher action (teacher >= 0); 0 when none.
    It is 0 once the teacher's action leads every other by the margin, and pushes the others below it until then."""
    labelled = teacher >= 0
    if not bool(labelled.any()):
        return q.sum() * 0.0
    q, a_e = q[labelled], teacher[labelled].unsqueeze(1)
    lift = q.new_full(q.shape, margin).scatter_(1, a_e, 0.0)
    return ((q + lift).max(dim=1).values - q.gather(1, a_e).squeeze(1)).mean()


def reason_attention_loss(weights: torch.Tensor, reason: torch.Tensor) -> torch.Tensor:
    """-log of the attention's mass on the teacher's reason, averaged over the states with one in view: `weights` the
    query readout's (B, heads, queries, cells), `reason` (B, cells) the share of each cell the reason covers. The map
    is what insight shows (every head's and query's weights averaged), the mass is weighed by each cell's share over
    the largest, so it is 0 once the map lies on the cells the reason fills; 0 when no state has a reason."""
    shown = reason.amax(dim=1) > 0
    if not bool(shown.any()):
        return weights.sum() * 0.0
    cells = reason[shown] / reason[shown].amax(dim=1, keepdim=True)
    mass = (weights[shown].mean(dim=(1, 2)) * cells).sum(dim=1)
    return -mass.clamp_min(1e-6).log().mean()


def teaching_terms(
    cfg: TeacherConfig, q: torch.Tensor, attention, teacher: torch.Tensor | None, reason: torch.Tensor | None
) -> list[torch.Tensor]:
    """What the teacher adds to a batch's TD loss, term by term: teacher_weight x the large-margin loss on its actions
    (where the batch has any), attention_weight x the reason loss on SAM's attention (where it has reasons)."""
    terms = []
    if cfg.teacher_weight > 0.0 and teacher is not None and bool((teacher >= 0).any()):  # a run without one: TD alone
        terms.append(cfg.teacher_weight * large_margin_loss(q, teacher, cfg.teacher_margin))
    if cfg.attention_weight > 0.0 and reason is not None:
        terms.append(cfg.attention_weight * reason_attention_loss(attention, reason))
    return terms
