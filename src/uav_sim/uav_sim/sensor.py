"""Depth sensors as real ones measure: presets for common stereo and time-of-flight cameras, seeded.

A preset fixes the camera's own resolution and field of view, its range limits, and its errors: noise
growing with distance squared (stereo: sigma_z = z^2 sigma_d / (f b)), pixels that return nothing at
random (dropout), holes beside depth edges (stereo occlusion, time-of-flight mixed pixels), and 16UC1's
millimetre steps. `ideal` (the paper's protocol, the default) changes nothing.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class SensorPreset:
    name: str
    width: int
    height: int
    hfov_deg: float
    min_range_m: float
    max_range_m: float
    noise_per_m2: float  # sigma of the depth error at depth z is noise_per_m2 * z^2 (m)
    dropout: float  # share of pixels with no return
    edge_jump_m: float  # a pixel beyond a depth step larger than this (to its left) returns nothing
    quantum_m: float  # depth resolution (16UC1: 1 mm)
    about: str


PRESETS = {
    p.name: p
    for p in (
        SensorPreset(
            "realsense_d435",
            848,
            480,
            87.0,
            0.3,
            10.0,
            0.005,
            0.02,
            0.3,
            0.001,
            "Intel RealSense D435-like active stereo: 848x480, 87x57 deg, 0.3-10 m, sigma 2 cm at 2 m",
        ),
        SensorPreset(
            "tof_vga",
            640,
            480,
            70.0,
            0.2,
            6.0,
            0.0025,
            0.01,
            0.5,
            0.001,
            "VGA time-of-flight-like: 640x480, 70x55 deg, 0.2-6 m, sigma 1 cm at 2 m",
        ),
    )
}
SENSORS = ("ideal", *PRESETS)


class SensorModel:
    """`measure(depth_m)`: what the preset's camera reports for the true depth (+Inf: no return)."""

    def __init__(self, preset: SensorPreset, seed: int):
        self.preset = preset
        self.rng = np.random.default_rng(seed)

    def measure(self, depth_m: np.ndarray) -> np.ndarray:
        p = self.preset
        z = np.asarray(depth_m, dtype=np.float64)
        finite = np.isfinite(z)
        noisy = np.where(finite, z, 0.0)
        noisy = noisy + self.rng.standard_normal(z.shape) * p.noise_per_m2 * noisy**2
        out = np.where(finite, noisy, np.inf)
        if p.edge_jump_m > 0:
            # The far side of a step (its first pixel) is shadowed: stereo's occlusion, ToF's mixed pixels.
            jump = np.zeros(z.shape, dtype=bool)
            with np.errstate(invalid="ignore"):
                jump[:, 1:] = (z[:, 1:] - z[:, :-1]) > p.edge_jump_m
                jump[:, :-1] |= (z[:, :-1] - z[:, 1:]) > p.edge_jump_m
            out[jump] = np.inf
        out[self.rng.random(z.shape) < p.dropout] = np.inf
        out[(out < p.min_range_m) | (out > p.max_range_m)] = np.inf
        if p.quantum_m > 0:
            out = np.where(np.isfinite(out), np.round(out / p.quantum_m) * p.quantum_m, np.inf)
        return out.astype(np.float32)


def preset(name: str) -> SensorPreset | None:
    """The preset called `name`, None for ideal; ValueError naming the choices otherwise."""
    if name == "ideal":
        return None
    if name not in PRESETS:
        raise ValueError(f"sensor must be one of {', '.join(SENSORS)}, got {name!r}")
    return PRESETS[name]


TRAINING_SCALE = 0.1  # what the sensor recipes render at (params/recipes/shipped.yaml), and weights fly at


def preset_for_camera(hfov_deg: float | None) -> str:
    """The sensor a weights file trained behind `hfov_deg` (its recorded camera) is flown behind: the preset of that
    field of view (files record only the field of view), else ideal."""
    for name, p in PRESETS.items():
        if hfov_deg is not None and abs(p.hfov_deg - hfov_deg) <= 0.5:
            return name
    return "ideal"


def sim_args_for_camera(hfov_deg: float | None) -> list[str]:
    """sim_node arguments for the sensor weights trained behind `hfov_deg` are flown behind (sim_node's own default is
    a preset: an ideal camera is named too)."""
    sensor = preset_for_camera(hfov_deg)
    return ["sensor:=ideal"] if sensor == "ideal" else [f"sensor:={sensor}", f"sensor_scale:={TRAINING_SCALE}"]


def scaled_size(p: SensorPreset, scale: float) -> tuple[int, int]:
    """(width, height) rendered for a preset at `scale` of its resolution (at least 8 px a side)."""
    return max(8, round(p.width * scale)), max(8, round(p.height * scale))
