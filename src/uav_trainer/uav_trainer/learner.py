"""The Double-Dueling DQN learner: Double DQN targets, Huber loss, Adam, gradient clipping,
periodic hard or Polyak target updates. Reads top to bottom; hyperparameters in one dataclass.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import torch
import torch.nn.functional as F

from uav_common.settings import setting
from uav_policy.networks import NetConfig, build_network


@dataclasses.dataclass(frozen=True)
class LearnerConfig:
    gamma: float = setting(0.99, "Discount factor", 0.0, 1.0)
    learning_rate: float = setting(2.5e-4, "Adam learning rate", 1e-7, 1.0)
    batch_size: int = setting(32, "Transitions per update", 1, 4096)
    grad_clip_norm: float = setting(10.0, "Max global gradient norm", 0.01, 1e6)
    target_update_interval: int = setting(250, "Updates between target-network syncs", 1, 10**7)
    target_tau: float = setting(1.0, "1.0: hard copy at each sync; < 1: Polyak averaging factor", 0.0001, 1.0)
    huber_delta: float = setting(1.0, "Huber loss threshold", 0.01, 100.0)
    seed: int = 0  # TrainerConfig's seed (not a setting of its own)


def double_dqn_target(reward, done, gamma, q_next_online, q_next_target):
    """y = r + gamma * (1 - done) * Q_target(s', argmax_a Q_online(s', a))."""
    best = q_next_online.argmax(dim=1, keepdim=True)
    return reward + gamma * (1.0 - done) * q_next_target.gather(1, best).squeeze(1)


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
        )

    def update(self, batch: dict[str, np.ndarray]) -> dict[str, float]:
        """One gradient step on a sampled batch; returns loss, mean Q and gradient norm."""
        s, a, r, done, s2 = self._tensors(batch)
        with torch.no_grad():
            y = double_dqn_target(r, done, self.cfg.gamma, self.online(s2)[0], self.target(s2)[0])
        q, _ = self.online(s)
        q_taken = q.gather(1, a.unsqueeze(1)).squeeze(1)
        loss = F.huber_loss(q_taken, y, delta=self.cfg.huber_delta)
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


def linear_epsilon(step: int, start: float, end: float, decay_steps: int) -> float:
    """Linear decay from start to end over decay_steps environment steps, then constant."""
    if decay_steps <= 0 or step >= decay_steps:
        return end
    frac = min(max(step, 0) / decay_steps, 1.0)
    return start + frac * (end - start)
