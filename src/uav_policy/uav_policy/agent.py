"""Acting: epsilon-greedy action selection with a Q-network, thread-safe weight swaps."""

from __future__ import annotations

import threading

import numpy as np
import torch

from .networks import NetConfig


def resolve_device(name: str) -> str:
    """A torch device for 'auto' (cuda when present, else cpu), 'cpu' or 'cuda'; ValueError when cuda is
    asked for and there is none."""
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("'device'='cuda' but no CUDA device is available (use 'auto' or 'cpu')")
    return name


class Agent:
    def __init__(self, net: torch.nn.Module, cfg: NetConfig, device: str = "cpu", seed: int = 0):
        self.cfg = cfg
        self.device = torch.device(device)
        self._net = self._ready(net)
        self._lock = threading.Lock()
        self.rng = np.random.default_rng(seed)

    def _ready(self, net: torch.nn.Module) -> torch.nn.Module:
        """`net` on this agent's device, in eval mode (moved and switched only when needed: a push every other step)."""
        if any(t.device != self.device for t in net.parameters()):
            net = net.to(self.device)
        return net.eval() if net.training else net

    @property
    def net(self) -> torch.nn.Module:
        return self._net

    def swap(self, net: torch.nn.Module) -> None:
        """Replace the network atomically: an act() in flight finishes with the old one."""
        net = self._ready(net)
        with self._lock:
            self._net = net

    @torch.no_grad()
    def q_values(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Q (actions,) and attention weights (heads, nodes, nodes) or None, for one state."""
        with self._lock:
            net = self._net
        x = torch.from_numpy(np.ascontiguousarray(state, dtype=np.float32)).unsqueeze(0).to(self.device)
        q, w = net(x)
        return q[0].float().cpu().numpy(), None if w is None else w[0].float().cpu().numpy()

    def act(self, state: np.ndarray, epsilon: float) -> tuple[int, np.ndarray, np.ndarray | None, bool]:
        """(action, q, attention, explored): random with probability epsilon, else argmax Q."""
        q, w = self.q_values(state)
        if self.rng.random() < epsilon:
            return int(self.rng.integers(len(q))), q, w, True
        return int(np.argmax(q)), q, w, False
