"""A network's architecture as data (no torch): the configuration stored in every weights file, its bounds and
the names a launcher offers (models, SAM readouts), so that what only parses or checks settings (`train`, the
trainer's settings) starts without loading torch. The networks themselves: networks.py."""

from __future__ import annotations

import dataclasses
import json

MODELS = ("sam", "cnn")
SAM_READOUTS = ("max", "flatten", "attend", "query", "topk")
TOPK_SHARE = 8  # the topk readout keeps a node in every TOPK_SHARE (8 of the default 64)
# With `local_map`, the state's last channel is the local map (uav_common.local_map.LocalMap.egocentric) of
# height x width cells covering MAP_EXTENT_M ahead and behind (a quarter of it behind), 1 where an obstacle is.
MAP_EXTENT_M = 6.4
# The most depth frames in a state (policy_node's frame_stack range; a file's header may not ask for more).
MAX_FRAMES = 16
# The layer sizes inside the network: nothing outside it (camera, frame stack, action set) depends
# on them, so whoever loads a weights file takes them from the file (weights.config_for).
SIZE_FIELDS = ("conv_channels", "d_model", "heads", "relational_blocks", "mlp_hidden", "cnn_hidden", "head_hidden")
# Upper bounds on those sizes: a weights file's header cannot make a loader build a network that
# no file within weights.MAX_BYTES could fill.
SIZE_LIMITS = {
    "conv_channels": 512,
    "d_model": 1024,
    "heads": 64,
    "relational_blocks": 16,
    "mlp_hidden": 4096,
    "cnn_hidden": 4096,
    "head_hidden": 4096,
}


@dataclasses.dataclass(frozen=True)
class NetConfig:
    """Architecture; stored in every weights file so that a mismatch is caught on load."""

    model: str = "sam"
    frames: int = 5
    height: int = 64
    width: int = 64
    actions: int = 4
    max_range_m: float = 10.0
    conv_channels: tuple[int, ...] = (16, 32, 32)
    d_model: int = 48  # node feature size, split over the heads
    heads: int = 3
    relational_blocks: int = 1
    mlp_hidden: int = 96
    cnn_hidden: int = 128
    head_hidden: int = 64
    sam_readout: str = "max"  # how SAM turns nodes into one vector: max | flatten | attend (cnn: always max)
    feature_norm: bool = (
        False  # LayerNorm before the dueling heads: files that record it load; no recipe trains it (it did not help)
    )
    # The local map as a last input channel beside the depth frames (a second trunk; SAM attends over image and map
    # cells): the network needs odometry.
    local_map: bool = False

    @property
    def channels(self) -> int:
        """Input channels: the depth frames, and the local map's grid with `local_map`."""
        return self.frames + int(self.local_map)

    @property
    def map_grid(self) -> tuple[int, float] | None:
        """The local map input's (cells a side, cell size in m): StackedSim's map_grid; None without one."""
        return (self.height, MAP_EXTENT_M / self.height) if self.local_map else None

    def __post_init__(self):
        # The CNN has no readout choice: a sam_readout set for SAM (e.g. in params/policy.yaml)
        # must not make CNN weights look like another architecture.
        if self.model == "cnn" and self.sam_readout in SAM_READOUTS:
            object.__setattr__(self, "sam_readout", "max")
        self.validate()  # once, where it is made: every NetConfig in use is a valid one

    def validate(self) -> None:
        for name in ("feature_norm", "local_map"):
            if type(getattr(self, name)) is not bool:
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if self.local_map and self.height != self.width:
            raise ValueError(f"the local map input needs a square input, got {self.width}x{self.height}")
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        if self.sam_readout not in SAM_READOUTS:
            raise ValueError(f"sam_readout must be one of {SAM_READOUTS}, got {self.sam_readout!r}")
        for name in SIZE_FIELDS:
            value = getattr(self, name)
            values = value if name == "conv_channels" else (value,)
            if not values or any(type(v) is not int or not 1 <= v <= SIZE_LIMITS[name] for v in values):
                raise ValueError(f"{name} must be integer(s) in [1, {SIZE_LIMITS[name]}], got {value!r}")
        if self.d_model % self.heads:
            raise ValueError(f"d_model ({self.d_model}) must be divisible by heads ({self.heads})")
        if type(self.frames) is not int or not 1 <= self.frames <= MAX_FRAMES or self.actions < 2:
            raise ValueError(f"need frames in [1, {MAX_FRAMES}] and actions >= 2, got {self.frames!r} and {self.actions!r}")
        if self.height < 8 or self.width < 8:
            raise ValueError(f"input {self.width}x{self.height} is too small (>= 8x8)")
        # Each trunk layer (4x4, stride 2, padding 1) halves the input, rounding down.
        if min(self.height, self.width) >> len(self.conv_channels) < 1:
            raise ValueError(
                f"{len(self.conv_channels)} conv layers leave nothing of a {self.width}x{self.height} input "
                f"(each halves it): use at most {min(self.height, self.width).bit_length() - 1}"
            )

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @staticmethod
    def from_json(text: str) -> NetConfig:
        d = json.loads(text)
        if not isinstance(d, dict):
            raise ValueError("network config must be a JSON object")
        fields = {f.name for f in dataclasses.fields(NetConfig)}
        unknown = set(d) - fields
        if unknown:
            raise ValueError(f"unknown network config fields: {sorted(unknown)}")
        if "conv_channels" in d:
            d["conv_channels"] = tuple(d["conv_channels"])
        return NetConfig(**d)
