"""Rain, snow and falling leaves: visual-only particles around the vehicle.

They have no collision shape (flying through rain is not a crash) but the depth camera sees
them, so they put near returns into the image as the paper's Turbulent environment does.
Particles live in a box in front of the vehicle and fall through it; one that leaves the box
re-enters at the top at a seeded random place.
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as p

from .world import Weather

# Box in the vehicle frame (x forward, y left, z up), metres, relative to the camera.
VOLUME_X_M = (0.4, 4.0)
VOLUME_Y_M = (-2.0, 2.0)
VOLUME_Z_M = (-1.2, 1.2)

# kind: (half extents of the box shape (m), fall speed (m/s), lateral flutter amplitude (m/s))
KINDS = {
    "rain": ((0.02, 0.02, 0.15), 6.0, 0.0),
    "snow": ((0.04, 0.04, 0.04), 0.8, 0.3),
    "leaves": ((0.10, 0.08, 0.005), 1.0, 0.8),
}


class Particles:
    """Seeded particle field; `update` moves it by dt and places it around the camera."""

    def __init__(self, client: int, weather: Weather, seed: int):
        self.client = client
        self.rng = np.random.default_rng(seed)
        kinds = ["rain"] * weather.rain + ["snow"] * weather.snow + ["leaves"] * weather.leaves
        self.kinds = kinds
        n = len(kinds)
        self.rel = self._spawn(n, full_height=True)
        self.fall = np.array([KINDS[k][1] for k in kinds], dtype=np.float64)
        self.flutter = np.array([KINDS[k][2] for k in kinds], dtype=np.float64)
        self.phase = self.rng.uniform(0, 2 * math.pi, n)
        self.bodies = []
        shapes = {k: p.createVisualShape(p.GEOM_BOX, halfExtents=KINDS[k][0], physicsClientId=client) for k in set(kinds)}
        for k in kinds:
            self.bodies.append(
                p.createMultiBody(
                    baseMass=0,
                    baseCollisionShapeIndex=-1,
                    baseVisualShapeIndex=shapes[k],
                    basePosition=(0, 0, -100),
                    physicsClientId=client,
                )
            )
        self.time_s = 0.0

    def _spawn(self, n: int, full_height: bool) -> np.ndarray:
        xyz = np.empty((n, 3))
        xyz[:, 0] = self.rng.uniform(*VOLUME_X_M, n)
        xyz[:, 1] = self.rng.uniform(*VOLUME_Y_M, n)
        xyz[:, 2] = self.rng.uniform(*VOLUME_Z_M, n) if full_height else VOLUME_Z_M[1]
        return xyz

    def update(self, dt_s: float, camera_xyz, yaw_rad: float) -> None:
        """Advance the particles by dt and move their bodies into place around the camera."""
        if not self.bodies:
            return
        self.time_s += dt_s
        self.rel[:, 2] -= self.fall * dt_s
        self.rel[:, 1] += self.flutter * np.sin(2.0 * self.time_s + self.phase) * dt_s
        out = (self.rel[:, 2] < VOLUME_Z_M[0]) | (np.abs(self.rel[:, 1]) > VOLUME_Y_M[1])
        if out.any():
            self.rel[out] = self._spawn(int(out.sum()), full_height=False)
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        for i, body in enumerate(self.bodies):
            rx, ry, rz = self.rel[i]
            pos = (camera_xyz[0] + c * rx - s * ry, camera_xyz[1] + s * rx + c * ry, camera_xyz[2] + rz)
            orn = p.getQuaternionFromEuler((0.0, 0.3 * math.sin(self.phase[i] + self.time_s), yaw_rad))
            p.resetBasePositionAndOrientation(body, pos, orn, physicsClientId=self.client)
