"""The Double-Dueling DQN learner: Double DQN targets, Huber loss, Adam, gradient clipping,
periodic hard or Polyak target updates. Reads top to bottom; hyperparameters in one dataclass.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
import torch.nn.functional as F

from uav_policy.networks import NetConfig, build_network

from .teacher import TeacherConfig, teaching_terms
from .training_config import LearnerConfig


def double_dqn_target(reward, done, gamma, q_next_online, q_next_target):
    """y = r + gamma * (1 - done) * Q_target(s', argmax_a Q_online(s', a))."""
    best = q_next_online.argmax(dim=1, keepdim=True)
    return reward + gamma * (1.0 - done) * q_next_target.gather(1, best).squeeze(1)


class NonFiniteLoss(RuntimeError):
    """The loss became NaN or Inf: learning must stop; the last good checkpoint stays."""


class Learner:
    def __init__(self, net_cfg: NetConfig, cfg: LearnerConfig, device: str = "cpu", teaching: TeacherConfig = TeacherConfig()):
        self.net_cfg, self.cfg, self.teaching = net_cfg, cfg, teaching
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
        """One gradient step on a sampled batch; returns loss, mean Q and gradient norm. The teacher's terms
        (uav_trainer.teacher: the large-margin loss on its actions, the reason loss on the attention) add to the TD loss."""
        s, a, r, done, s2, teacher, reason = self._tensors(batch)
        with torch.no_grad():
            y = double_dqn_target(r, done, self.cfg.gamma, self.online(s2)[0], self.target(s2)[0])
        q, attention = self.online(s)
        q_taken = q.gather(1, a.unsqueeze(1)).squeeze(1)
        loss = F.huber_loss(q_taken, y, delta=self.cfg.huber_delta)
        for term in teaching_terms(self.teaching, q, attention, teacher, reason):
            loss = loss + term
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
