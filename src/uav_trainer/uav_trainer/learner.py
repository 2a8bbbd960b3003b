"""The Double-Dueling DQN learner: Double DQN targets, Huber loss, Adam, gradient clipping,
periodic hard or Polyak target updates. Reads top to bottom; hyperparameters in one dataclass.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import torch
import torch.nn.functional as F

from uav_policy.networks import NetConfig, build_network


@dataclasses.dataclass(frozen=True)
class LearnerConfig:
    gamma: float = 0.99  # discount
    learning_rate: float = 2.5e-4  # Adam
    batch_size: int = 32
    grad_clip_norm: float = 10.0  # max global gradient norm
    target_update_interval: int = 250  # updates between target syncs
    target_tau: float = 1.0  # 1.0: hard copy; < 1: Polyak averaging at every sync
    huber_delta: float = 1.0
    seed: int = 0
    # Learning-rate annealing: > 0 lowers the rate linearly to lr_end_fraction x learning_rate over
    # this many updates, then keeps it there (0 = constant rate, as the paper).
    lr_anneal_updates: int = 0
    lr_end_fraction: float = 0.1
    # Weight averaging: > 0 keeps an exponential moving average of the online weights,
    # ema <- decay * ema + (1 - decay) * online after every update (0 = off). It never acts in
    # training; the trainer writes it as policy_<model>_ema.safetensors for evaluation.
    ema_decay: float = 0.0
    # Random-shift augmentation (DrQ, Kostrikov et al. 2021; not in the paper): > 0 shifts every
    # sampled state and next state by up to this many pixels in each direction before the update,
    # edges repeated (0 = off, as the paper). The whole frame stack of a state moves together; the
    # state and its next state draw their own shifts. Acting is never augmented.
    augment_shift_px: int = 0


def double_dqn_target(reward, done, gamma, q_next_online, q_next_target):
    """y = r + gamma * (1 - done) * Q_target(s', argmax_a Q_online(s', a)); gamma may be a per-sample
    tensor (n-step returns: gamma^m)."""
    best = q_next_online.argmax(dim=1, keepdim=True)
    return reward + gamma * (1.0 - done) * q_next_target.gather(1, best).squeeze(1)


# The largest random shift accepted (px): an eighth of the paper-sized 64 px input.
MAX_SHIFT_PX = 8


def random_shift(x: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """Shift each sample of a (batch, frames, height, width) tensor by its own whole-pixel offset in
    [-pad, pad] along each image axis, repeating the edge rows and columns (DrQ's pad-and-crop with
    replicate padding); all frames of a sample move together. pad = 0 returns x."""
    if pad <= 0:
        return x
    b, _, h, w = x.shape
    dy, dx = torch.randint(-pad, pad + 1, (2, b, 1), generator=generator).to(x.device)  # drawn on the CPU
    rows = (torch.arange(h, device=x.device) + dy).clamp_(0, h - 1)  # (b, h)
    cols = (torch.arange(w, device=x.device) + dx).clamp_(0, w - 1)  # (b, w)
    batch = torch.arange(b, device=x.device)[:, None, None]
    # Advanced indices around the frames slice broadcast to (b, h, w) and come first: (b, h, w, frames).
    return x[batch, :, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2).contiguous()


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
        if not 0.0 <= cfg.ema_decay < 1.0:
            raise ValueError(f"ema_decay must be in [0, 1), got {cfg.ema_decay}")
        if cfg.lr_anneal_updates < 0 or not 0.0 < cfg.lr_end_fraction <= 1.0:
            raise ValueError(
                "lr_anneal_updates must be >= 0 and lr_end_fraction in (0, 1], "
                f"got {cfg.lr_anneal_updates}, {cfg.lr_end_fraction}"
            )
        if not 0 <= cfg.augment_shift_px <= MAX_SHIFT_PX:
            raise ValueError(f"augment_shift_px must be in [0, {MAX_SHIFT_PX}], got {cfg.augment_shift_px}")
        # The shifts' own random stream (checkpointed), so that nothing else drawing from torch's
        # global one changes them.
        self.shift_rng = torch.Generator().manual_seed(cfg.seed)
        self.ema = None
        if cfg.ema_decay > 0.0:
            self.ema = copy.deepcopy(self.online).eval()
            for p in self.ema.parameters():
                p.requires_grad_(False)

    def learning_rate(self, updates: int | None = None) -> float:
        """The rate for the next update (linear annealing when lr_anneal_updates > 0)."""
        c = self.cfg
        u = self.updates if updates is None else updates
        if c.lr_anneal_updates <= 0:
            return c.learning_rate
        frac = min(u / c.lr_anneal_updates, 1.0)
        return c.learning_rate * (1.0 - frac * (1.0 - c.lr_end_fraction))

    def _tensors(self, batch: dict[str, np.ndarray]):
        d = self.device
        return (
            torch.from_numpy(batch["state"]).to(d),
            torch.from_numpy(batch["action"]).to(d),
            torch.from_numpy(batch["reward"]).to(d),
            torch.from_numpy(batch["done"]).to(d),
            torch.from_numpy(batch["next_state"]).to(d),
        )

    def update(self, batch: dict[str, np.ndarray]) -> dict[str, float | np.ndarray]:
        """One gradient step on a sampled batch; returns loss, mean Q, gradient norm and `td_abs`
        (each sample's |Q - y|, for prioritized replay). A batch with `discount` (n-step returns)
        bootstraps with it instead of gamma; one with `weight` (prioritized replay) weights each
        sample's Huber loss by it."""
        s, a, r, done, s2 = self._tensors(batch)
        if self.cfg.augment_shift_px > 0:
            s = random_shift(s, self.cfg.augment_shift_px, self.shift_rng)
            s2 = random_shift(s2, self.cfg.augment_shift_px, self.shift_rng)
        gamma = torch.from_numpy(batch["discount"]).to(self.device) if "discount" in batch else self.cfg.gamma
        with torch.no_grad():
            y = double_dqn_target(r, done, gamma, self.online(s2)[0], self.target(s2)[0])
        q = self.online(s)[0]
        q_taken = q.gather(1, a.unsqueeze(1)).squeeze(1)
        if "weight" in batch:
            w = torch.from_numpy(batch["weight"]).to(self.device)
            loss = (w * F.huber_loss(q_taken, y, reduction="none", delta=self.cfg.huber_delta)).mean()
        else:
            loss = F.huber_loss(q_taken, y, delta=self.cfg.huber_delta)
        if not torch.isfinite(loss):
            raise NonFiniteLoss(f"loss is {loss.item()} at update {self.updates}")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.online.parameters(), self.cfg.grad_clip_norm)
        if self.cfg.lr_anneal_updates > 0:
            for g in self.optimizer.param_groups:
                g["lr"] = self.learning_rate()
        self.optimizer.step()
        self.updates += 1
        if self.ema is not None:
            self._update_ema()
        if self.updates % self.cfg.target_update_interval == 0:
            self.sync_target()
        return {
            "loss": float(loss.item()),
            "q_mean": float(q.mean().item()),
            "grad_norm": float(grad_norm),
            "td_abs": (q_taken - y).abs().detach().cpu().numpy(),
        }

    @torch.no_grad()
    def _update_ema(self) -> None:
        d = self.cfg.ema_decay
        for e, o in zip(self.ema.parameters(), self.online.parameters(), strict=True):
            e.mul_(d).add_(o, alpha=1.0 - d)
        for e, o in zip(self.ema.buffers(), self.online.buffers(), strict=True):
            e.copy_(o)

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
