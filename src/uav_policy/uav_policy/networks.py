"""D3QN-SAM and D3QN-CNN Q-networks (PyTorch, no ROS).

Both take the last `frames` depth images in metres, (B, frames, H, W), and normalise them
inside the network: +Inf/NaN -> max range, -Inf -> 0, then divide by the max range.

D3QN-SAM: conv trunk -> feature map sliced into one node per spatial cell, with the cell's
(x, y) in [-1, 1] appended (Zambaldi et al. 2018) -> linear projection -> relational block(s)
(multi-head scaled dot-product self-attention with residual + LayerNorm, then an MLP with
residual + LayerNorm) -> readout -> dueling head. The forward pass also returns the attention
weights (B, heads, nodes, nodes); each row sums to 1. Readout `max` (default, Zambaldi et al.): the
feature-wise max over nodes, which keeps what was seen but not where. Readout `flatten` (an
extension): each node is projected to the trunk's channel count and the nodes are flattened in
grid order into the CNN's hidden layer, so the head sees where each feature is, as the CNN does.
Readout `attend` (an extension): attention pooling, one learned query per head over the nodes (as in Set
Transformer's PMA); the heads' weighted values are the head's only input, so the weights shown are the weights
that form the Q-values. The forward pass then returns those readout weights (B, heads, 1, nodes) as the
attention the decision uses, in place of the relational block's.
Readout `query` (Mott et al. 2019): queries computed from the frame (a summary of the self-attended nodes), one per
action and one for the value, attend over the nodes *before* any self-attention mixing; each action's advantage (and
the value) is computed from its own attended vector alone, with no path around the attention. Returns
(B, heads, actions + 1, nodes).
Readout `topk` (Tang, Nguyen & Ha 2020): one learned query per head scores the self-attended nodes; only the top
nodes/TOPK_SHARE of each head, unmixed, reach the dueling head, weighted by their softmax over the kept ones
(B, heads, 1, nodes; zero off the kept nodes).

D3QN-CNN: the same trunk, flattened, a hidden layer, and the same dueling head.

With `local_map` (NetConfig) the state's last channel is the egocentric local map (0/1 occupancy, the vehicle at the
bottom centre): a second trunk of the same shape reads it. SAM's nodes are the image cells then the map cells, each
with its coordinates and a flag saying which (so attention ranges over both: (B, heads, m, 2 x cells)); the CNN
flattens both feature maps into its hidden layer.

Dueling head: Q = V + A - mean(A), with linear outputs (no ELU: Q-values must reach -10). With `feature_norm`
the features the heads read (the CNN's hidden layer, SAM's pooled vector or, with `query`, each attended vector)
pass a LayerNorm first (Bjorck et al. 2022 trace seed variance to features that saturate early in training).

QEnsemble (an extension; evaluate --ensemble K): several networks of one model (seeds, or one run's
snapshots) act as one by the mean of their Q-values; its attention is every member's heads side by
side (B, members x heads, nodes, nodes).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import torch
from torch import nn

from .net_config import MAX_FRAMES, MODELS, SAM_READOUTS, SIZE_FIELDS, SIZE_LIMITS, TOPK_SHARE, NetConfig

__all__ = ["MAX_FRAMES", "MODELS", "SAM_READOUTS", "SIZE_FIELDS", "SIZE_LIMITS", "TOPK_SHARE", "NetConfig"]


def normalise_depth(depth_m: torch.Tensor, max_range_m: float) -> torch.Tensor:
    """REP 117 depth in metres -> [0, 1]; far/invalid = 1, too close = 0."""
    x = torch.nan_to_num(depth_m.float(), nan=max_range_m, posinf=max_range_m, neginf=0.0)
    return x.clamp_(0.0, max_range_m) / max_range_m


class ConvTrunk(nn.Module):
    """Stride-2 4x4 convolutions: 64x64 -> 8x8 feature map with the default three layers. The depth trunk normalises
    its frames; the map trunk (`channels_in` 1, `depth` False) reads the 0/1 grid as it is."""

    def __init__(self, cfg: NetConfig, channels_in: int | None = None, depth: bool = True):
        super().__init__()
        c_in = cfg.frames if channels_in is None else channels_in
        layers, first = [], c_in
        for c_out in cfg.conv_channels:
            layers += [nn.Conv2d(c_in, c_out, kernel_size=4, stride=2, padding=1), nn.ReLU(inplace=True)]
            c_in = c_out
        self.net = nn.Sequential(*layers)
        self.max_range_m = cfg.max_range_m if depth else None
        with torch.no_grad():
            out = self.net(torch.zeros(1, first, cfg.height, cfg.width))
        self.out_channels, self.grid_h, self.grid_w = out.shape[1:]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.float() if self.max_range_m is None else normalise_depth(x, self.max_range_m))


def split_state(x: torch.Tensor, cfg: NetConfig) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(the depth frames, the local map channel or None) of a state (B, channels, H, W)."""
    if x.shape[1] != cfg.channels:
        what = f"{cfg.frames} depth frames" + (" and the local map" if cfg.local_map else "")
        raise ValueError(f"the network takes {cfg.channels} input channels ({what}), got {x.shape[1]}")
    return (x[:, : cfg.frames], x[:, cfg.frames :]) if cfg.local_map else (x, None)


def trunk_features(net: nn.Module, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    depth, grid = split_state(x, net.cfg)
    return net.trunk(depth), None if grid is None else net.map_trunk(grid)


class MultiHeadSelfAttention(nn.Module):
    """Scaled dot-product self-attention that also returns its per-head weights."""

    def __init__(self, d_model: int, heads: int):
        super().__init__()
        self.heads, self.d_head = heads, d_model // heads
        self.qkv = nn.Linear(d_model, 3 * d_model)
        self.out = nn.Linear(d_model, d_model)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, n, d = x.shape
        q, k, v = self.qkv(x).view(b, n, 3, self.heads, self.d_head).permute(2, 0, 3, 1, 4)
        weights = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(self.d_head), dim=-1)  # (b, h, n, n)
        mixed = (weights @ v).transpose(1, 2).reshape(b, n, d)
        return self.out(mixed), weights


class RelationalBlock(nn.Module):
    """Self-attention and an MLP, each with a residual connection and LayerNorm."""

    def __init__(self, d_model: int, heads: int, mlp_hidden: int):
        super().__init__()
        self.attention = MultiHeadSelfAttention(d_model, heads)
        self.norm1 = nn.LayerNorm(d_model)
        self.mlp = nn.Sequential(nn.Linear(d_model, mlp_hidden), nn.ReLU(inplace=True), nn.Linear(mlp_hidden, d_model))
        self.norm2 = nn.LayerNorm(d_model)

    def forward(self, nodes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        attended, weights = self.attention(nodes)
        nodes = self.norm1(nodes + attended)
        nodes = self.norm2(nodes + self.mlp(nodes))
        return nodes, weights


class AttentionPooling(nn.Module):
    """One learned query per head attends over the nodes: (B, n, d) -> (B, d) and the weights (B, heads, 1, n)."""

    def __init__(self, d_model: int, heads: int):
        super().__init__()
        self.heads, self.d_head = heads, d_model // heads
        self.query = nn.Parameter(torch.randn(heads, 1, self.d_head) / math.sqrt(self.d_head))
        self.kv = nn.Linear(d_model, 2 * d_model)
        self.out = nn.Linear(d_model, d_model)

    def forward(self, nodes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, n, d = nodes.shape
        k, v = self.kv(nodes).view(b, n, 2, self.heads, self.d_head).permute(2, 0, 3, 1, 4)  # (b, h, n, d_head) each
        weights = torch.softmax(self.query @ k.transpose(-1, -2) / math.sqrt(self.d_head), dim=-1)  # (b, h, 1, n)
        return self.out((weights @ v).reshape(b, d)), weights


class QueryReadout(nn.Module):
    """Frame-dependent queries, one per action and one for the value, over the unmixed nodes (see the module doc)."""

    def __init__(self, d_model: int, heads: int, actions: int, hidden: int, feature_norm: bool = False):
        super().__init__()
        self.heads, self.d_head, self.actions = heads, d_model // heads, actions
        self.queries = nn.Linear(d_model, (actions + 1) * d_model)
        self.feature_norm = nn.LayerNorm(d_model) if feature_norm else nn.Identity()
        self.norm = nn.LayerNorm(d_model)
        self.kv = nn.Linear(d_model, 2 * d_model)
        self.hidden = nn.Sequential(nn.Linear(d_model, hidden), nn.ReLU(inplace=True))
        self.advantage = nn.Parameter(torch.randn(actions, hidden) / math.sqrt(hidden))
        self.advantage_bias = nn.Parameter(torch.zeros(actions))
        self.value = nn.Linear(hidden, 1)

    def forward(self, unmixed: torch.Tensor, mixed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, n, d = unmixed.shape
        m = self.actions + 1
        q = self.queries(mixed.mean(dim=1)).view(b, m, self.heads, self.d_head).transpose(1, 2)  # (b, h, m, d_head)
        k, v = self.kv(self.norm(unmixed)).view(b, n, 2, self.heads, self.d_head).permute(2, 0, 3, 1, 4)
        weights = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(self.d_head), dim=-1)  # (b, h, m, n)
        attended = self.feature_norm((weights @ v).transpose(1, 2).reshape(b, m, d))
        h = self.hidden(attended)  # (b, m, hidden): one vector per query
        a = (h[:, : self.actions] * self.advantage).sum(dim=-1) + self.advantage_bias
        return self.value(h[:, self.actions]) + a - a.mean(dim=-1, keepdim=True), weights


class TopKPooling(nn.Module):
    """One learned query per head scores the self-attended nodes; only each head's top k unmixed nodes are pooled."""

    def __init__(self, d_model: int, heads: int, keep: int):
        super().__init__()
        self.heads, self.d_head, self.keep = heads, d_model // heads, keep
        self.query = nn.Parameter(torch.randn(heads, 1, self.d_head) / math.sqrt(self.d_head))
        self.key = nn.Linear(d_model, d_model)
        self.norm = nn.LayerNorm(d_model)
        self.value = nn.Linear(d_model, d_model)
        self.out = nn.Linear(d_model, d_model)

    def forward(self, unmixed: torch.Tensor, mixed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, n, d = unmixed.shape
        k = self.key(mixed).view(b, n, self.heads, self.d_head).transpose(1, 2)  # (b, h, n, d_head)
        v = self.value(self.norm(unmixed)).view(b, n, self.heads, self.d_head).transpose(1, 2)
        logits = self.query @ k.transpose(-1, -2) / math.sqrt(self.d_head)  # (b, h, 1, n)
        kth = logits.topk(min(self.keep, n), dim=-1).values[..., -1:]
        weights = torch.softmax(logits.masked_fill(logits < kth, -math.inf), dim=-1)  # zero off the kept nodes
        return self.out((weights @ v).reshape(b, d)), weights


class DuelingHead(nn.Module):
    """Q = V + A - mean(A)."""

    def __init__(self, d_in: int, hidden: int, actions: int, feature_norm: bool = False):
        super().__init__()
        self.norm = nn.LayerNorm(d_in) if feature_norm else nn.Identity()
        self.value = nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 1))
        self.advantage = nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, actions))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        features = self.norm(features)
        a = self.advantage(features)
        return self.value(features) + a - a.mean(dim=-1, keepdim=True)


def grid_coordinates(h: int, w: int) -> torch.Tensor:
    """(h*w, 2) node coordinates in [-1, 1], row-major (x = column, y = row)."""
    ys = torch.linspace(-1.0, 1.0, h) if h > 1 else torch.zeros(1)
    xs = torch.linspace(-1.0, 1.0, w) if w > 1 else torch.zeros(1)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=-1)


class D3QNSam(nn.Module):
    def __init__(self, cfg: NetConfig):
        super().__init__()
        self.cfg = cfg
        self.trunk = ConvTrunk(cfg)
        self.map_trunk = ConvTrunk(cfg, 1, depth=False) if cfg.local_map else None
        coords = grid_coordinates(self.trunk.grid_h, self.trunk.grid_w)
        if cfg.local_map:  # a third coordinate: 0 on image cells, 1 on map cells
            flag = torch.cat([torch.zeros(len(coords), 1), torch.ones(len(coords), 1)])
            coords = torch.cat([torch.cat([coords, coords]), flag], dim=1)
        self.register_buffer("coords", coords, persistent=False)
        self.node_projection = nn.Linear(self.trunk.out_channels + coords.shape[1], cfg.d_model)
        self.relational_blocks = nn.ModuleList(
            RelationalBlock(cfg.d_model, cfg.heads, cfg.mlp_hidden) for _ in range(cfg.relational_blocks)
        )
        self.pooling = self.query_readout = None
        if cfg.sam_readout == "attend":
            self.pooling = AttentionPooling(cfg.d_model, cfg.heads)
        if cfg.sam_readout == "topk":
            self.pooling = TopKPooling(cfg.d_model, cfg.heads, max(1, len(coords) // TOPK_SHARE))
        self.readout = None
        if cfg.sam_readout == "query":
            self.query_readout = QueryReadout(cfg.d_model, cfg.heads, cfg.actions, cfg.head_hidden, cfg.feature_norm)
            self.dueling_head = None  # its own heads, one per query
        elif cfg.sam_readout == "flatten":
            c, n = self.trunk.out_channels, len(coords)
            self.readout = nn.Sequential(
                nn.Linear(cfg.d_model, c), nn.Flatten(1), nn.Linear(n * c, cfg.cnn_hidden), nn.ReLU(inplace=True)
            )
            self.dueling_head = DuelingHead(cfg.cnn_hidden, cfg.head_hidden, cfg.actions, cfg.feature_norm)
        else:
            self.dueling_head = DuelingHead(cfg.d_model, cfg.head_hidden, cfg.actions, cfg.feature_norm)

    @property
    def grid_hw(self) -> tuple[int, int]:
        return self.trunk.grid_h, self.trunk.grid_w

    def forward(self, depth_m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Q-values (B, actions) and the attention the decision uses: the last block's weights (B, heads, nodes,
        nodes), or the readout's weights with `attend` / `topk` (B, heads, 1, nodes) and `query` (B, heads,
        actions + 1, nodes)."""
        return self.from_features(*self.features(depth_m))

    def features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The trunks' feature maps of a state: the image's, the local map's (None without one)."""
        return trunk_features(self, x)

    def unmixed_nodes(self, fmap: torch.Tensor, map_fmap: torch.Tensor | None = None) -> torch.Tensor:
        """(B, nodes, d_model): one node per cell of the feature map (row-major; then the map's), its coordinates
        appended, projected."""
        nodes = fmap.flatten(2).transpose(1, 2)  # (B, h*w, C), row-major cells
        if self.map_trunk is not None:
            nodes = torch.cat([nodes, map_fmap.flatten(2).transpose(1, 2)], dim=1)
        coords = self.coords.unsqueeze(0).expand(nodes.shape[0], -1, -1)
        return self.node_projection(torch.cat([nodes, coords], dim=-1))

    def from_features(self, fmap: torch.Tensor, map_fmap: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """forward() from the trunks' feature maps (B, C, h, w) on."""
        nodes = unmixed = self.unmixed_nodes(fmap, map_fmap)
        weights = None
        for block in self.relational_blocks:
            nodes, weights = block(nodes)
        if self.query_readout is not None:
            return self.query_readout(unmixed, nodes)
        if isinstance(self.pooling, TopKPooling):
            pooled, weights = self.pooling(unmixed, nodes)
        elif self.pooling is not None:
            pooled, weights = self.pooling(nodes)
        elif self.readout is None:
            pooled = nodes.max(dim=1).values  # feature-wise max pooling over nodes
        else:
            pooled = self.readout(nodes)  # (B, nodes, d) -> per-node projection -> flattened in grid order
        return self.dueling_head(pooled), weights


class D3QNCnn(nn.Module):
    def __init__(self, cfg: NetConfig):
        super().__init__()
        self.cfg = cfg
        self.trunk = ConvTrunk(cfg)
        self.map_trunk = ConvTrunk(cfg, 1, depth=False) if cfg.local_map else None
        flat = self.trunk.out_channels * self.trunk.grid_h * self.trunk.grid_w * (2 if cfg.local_map else 1)
        self.hidden = nn.Sequential(nn.Linear(flat, cfg.cnn_hidden), nn.ReLU(inplace=True))
        self.dueling_head = DuelingHead(cfg.cnn_hidden, cfg.head_hidden, cfg.actions, cfg.feature_norm)

    @property
    def grid_hw(self) -> tuple[int, int]:
        """The trunk's feature grid (Grad-CAM's cells)."""
        return self.trunk.grid_h, self.trunk.grid_w

    def forward(self, depth_m: torch.Tensor) -> tuple[torch.Tensor, None]:
        return self.from_features(*self.features(depth_m))

    def features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The trunks' feature maps of a state: the image's, the local map's (None without one)."""
        return trunk_features(self, x)

    def from_features(self, fmap: torch.Tensor, map_fmap: torch.Tensor | None = None) -> tuple[torch.Tensor, None]:
        """forward() from the trunks' feature maps (B, C, h, w) on."""
        flat = fmap.flatten(1) if map_fmap is None else torch.cat([fmap.flatten(1), map_fmap.flatten(1)], dim=1)
        return self.dueling_head(self.hidden(flat)), None


class QEnsemble(nn.Module):
    """Networks of one architecture (e.g. several training seeds) acting as one: Q is the mean of
    the members' Q-values, the attention the members' heads concatenated (None for CNN)."""

    def __init__(self, members: list[nn.Module]):
        super().__init__()
        if len(members) < 2:
            raise ValueError(f"an ensemble needs at least 2 networks, got {len(members)}")
        first = dataclasses.asdict(members[0].cfg)
        for i, m in enumerate(members[1:], 1):
            differ = {k: (v, first[k]) for k, v in dataclasses.asdict(m.cfg).items() if v != first[k]}
            if differ:
                raise ValueError(f"ensemble members must share one architecture: member {i} differs from member 0 in {differ}")
        self.members = nn.ModuleList(members)
        self.cfg = members[0].cfg

    @property
    def grid_hw(self) -> tuple[int, int]:
        return self.members[0].grid_hw

    def forward(self, depth_m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        qs, ws = zip(*(m(depth_m) for m in self.members), strict=True)
        q = torch.stack(qs).mean(dim=0)
        return q, None if ws[0] is None else torch.cat(ws, dim=1)


def build_network(cfg: NetConfig, seed: int | None = None) -> nn.Module:
    """A freshly initialised network; with a seed, the same seed gives the same weights."""
    if seed is not None:
        gen_state = torch.random.get_rng_state()
        torch.manual_seed(seed)
    try:
        return D3QNSam(cfg) if cfg.model == "sam" else D3QNCnn(cfg)
    finally:
        if seed is not None:
            torch.random.set_rng_state(gen_state)


@functools.lru_cache(maxsize=64)
def forward_flops(cfg: NetConfig) -> int:
    """Floating-point operations of one forward pass on one state, counted on the meta device: nothing of
    the network is allocated, so an architecture is priced before it is built (a pushed one, say)."""
    from torch.utils.flop_counter import FlopCounterMode

    with torch.device("meta"):
        net = D3QNSam(cfg) if cfg.model == "sam" else D3QNCnn(cfg)
        with FlopCounterMode(display=False) as counter:
            net(torch.zeros(1, cfg.channels, cfg.height, cfg.width))
    return int(counter.get_total_flops())


def parameter_count(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


def swap_notes(replaced: nn.Module, net: nn.Module, cfg: NetConfig) -> list[str]:
    """What a user should hear when pushed weights replace `replaced` (of architecture `cfg`)."""
    notes = []
    if isinstance(replaced, QEnsemble):
        notes.append(f"pushed weights replace the ensemble of {len(replaced.members)} networks")
    if net.cfg != cfg:
        sizes = ", ".join(f"{k} {getattr(net.cfg, k)}" for k in SIZE_FIELDS)
        notes.append(f"pushed weights changed the layer sizes: {sizes} ({parameter_count(net)} parameters)")
    return notes
