"""The Double-Dueling DQN learner: Double DQN targets, Huber loss, Adam, gradient clipping,
periodic hard or Polyak target updates. Reads top to bottom; hyperparameters in one dataclass.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
import torch.nn.functional as F

from uav_policy.networks import NetConfig, build_network

from .training_config import LearnerConfig


def double_dqn_target(reward, done, gamma, q_next_online, q_next_target):
    """y = r + gamma * (1 - done) * Q_target(s', argmax_a Q_online(s', a))."""
    best = q_next_online.argmax(dim=1, keepdim=True)
    return reward + gamma * (1.0 - done) * q_next_target.gather(1, best).squeeze(1)


def large_margin_loss(q: torch.Tensor, teacher: torch.Tensor, margin: float) -> torch.Tensor:
    """DQfD's supervised loss (Hester et al. 2018): J_E = max_a [Q(s, a) + l(a_E, a)] - Q(s, a_E), l = `margin` for
    a != a_E and 0 for the teacher's a_E, averaged over the states with a teacher action (teacher >= 0); 0 when none.
    It is 0 once the teacher's action leads every other by the margin, and pushes the others below it until then."""
    labelled = teacher >= 0
    if not bool(labelled.any()):
        return q.sum() * 0.0
    q, a_e = q[labelled], teacher[labelled].unsqueeze(1)
    lift = torch.full_like(q, margin).scatter_(1, a_e, 0.0)
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
    return -torch.log(mass.clamp_min(1e-6)).mean()


class NonFiniteLoss(RuntimeError):
    """The loss became NaN or Inf: learning must stop; the last good checkpoint stays."""


class Learner:
    def __init__(self, net_cfg: NetConfig, cfg: LearnerConfig, device: str = "cpu"):
        self.net_cfg, self.cfg = net_cfg, cfg
        self.device = torch.device(device)
        torch.manual_seed(cfg.seed)
        self.online = build_network(net_cfg, seed=cfg.seed).to(self.device)
        self.target = copy.deepcopy(self.online).eval()
        for p in self.target.parameters():
            p.requires_grad_(False)
        self.optimizer = torch.optim.Adam(self.online.parameters(), lr=cfg.learning_rate)
        self.updates = 0

    def _tensors(self, batch: dict[str, np.ndarray]):
        d = self.device
        return (
            torch.from_numpy(batch["state"]).to(d),
            torch.from_numpy(batch["action"]).to(d),
            torch.from_numpy(batch["reward"]).to(d),
            torch.from_numpy(batch["done"]).to(d),
            torch.from_numpy(batch["next_state"]).to(d),
            torch.from_numpy(batch["teacher"]).to(d) if "teacher" in batch else None,
            torch.from_numpy(batch["reason"]).to(d) if "reason" in batch else None,
        )

    def update(self, batch: dict[str, np.ndarray]) -> dict[str, float]:
        """One gradient step on a sampled batch; returns loss, mean Q and gradient norm. With teacher_weight > 0 the
        large-margin loss on the batch's teacher actions is added to the TD loss; with attention_weight > 0 the loss
        pulling the attention onto the batch's reasons too."""
        s, a, r, done, s2, teacher, reason = self._tensors(batch)
        with torch.no_grad():
            y = double_dqn_target(r, done, self.cfg.gamma, self.online(s2)[0], self.target(s2)[0])
        q, attention = self.online(s)
        q_taken = q.gather(1, a.unsqueeze(1)).squeeze(1)
        loss = F.huber_loss(q_taken, y, delta=self.cfg.huber_delta)
        if self.cfg.teacher_weight > 0.0 and teacher is not None and bool((teacher >= 0).any()):  # a run without one: TD alone
            loss = loss + self.cfg.teacher_weight * large_margin_loss(q, teacher, self.cfg.teacher_margin)
        if self.cfg.attention_weight > 0.0 and reason is not None:
            loss = loss + self.cfg.attention_weight * reason_attention_loss(attention, reason)
        if not torch.isfinite(loss):
            raise NonFiniteLoss(f"loss is {loss.item()} at update {self.updates}")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.online.parameters(), self.cfg.grad_clip_norm)
        self.optimizer.step()
        self.updates += 1
        if self.updates % self.cfg.target_update_interval == 0:
            self.sync_target()
        return {"loss": float(loss.item()), "q_mean": float(q.mean().item()), "grad_norm": float(grad_norm)}

    @torch.no_grad()
    def sync_target(self) -> None:
        tau = self.cfg.target_tau
        for t, o in zip(self.target.parameters(), self.online.parameters(), strict=True):
            t.mul_(1.0 - tau).add_(o, alpha=tau)
