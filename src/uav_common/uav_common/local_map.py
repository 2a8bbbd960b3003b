"""The local map: what the depth camera showed in the last frames, kept where it is now (numpy and scipy, no ROS).

Every frame's *measured* depth pixels are back-projected through the camera's intrinsics (a level pinhole camera,
REP 118: z forward, x right, y down), moved into the odometry frame by the camera's pose, and those within `band_m`
of the camera's height and `range_m` of it are binned into cells of `resolution_m` on a grid fixed in the odometry
frame. The map remembers the cells of the last `frames` frames; a new episode (`reset`) forgets.

Weather (rain, snow, leaves) puts near returns into the depth image that are not obstacles. Three rules keep the
obstacles and drop them:

1. **Free-space carving**, as occupancy mapping does: a remembered cell that a later frame sees through (the pixels
   it projects to measure well beyond it) is cleared. Particles move with the vehicle, so the next frame looks
   through where a particle was.
2. **Standing from the floor**: a cell counts at once when its returns (with its neighbours') fill at least
   `solid_m` of height without a gap in one frame, or nearly all of the band that the camera sees at its range
   (close up the camera sees less than the band). Obstacles stand from the floor through the band; a raindrop is
   0.3 m tall, snow and leaves less, and two particles above one another leave a gap.
3. Otherwise **confirmed**: a cell counts when it (or a neighbour) was hit in `confirm_frames` of the remembered
   frames. A particle is never at the same place of the odometry frame twice.

What counts is `occupied()`; `clearance()` gives the distance from any points to the nearest occupied cell (a
distance transform over a window around the camera), the planner's and the shield's only knowledge of the world;
`egocentric()` is the grid turned into the body frame, x forward.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .settings import setting

# sim_node's camera sits this far ahead of base_link (m): what odometry gives is base_link's pose.
CAMERA_FORWARD_M = 0.22
_OFFSET = 1 << 20  # cell indices are stored as one int64 key: (ix + _OFFSET) << 21 | (iy + _OFFSET)
NEIGHBOURS_BEYOND_M = 2.0  # ... and beyond this range a cell's neighbours count with it (depth noise spreads a surface)
BIN_M = 0.1  # the height bins of the weather filter's standing-from-the-floor test
_NEIGHBOURS = np.array([(dx << 21) + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1)], dtype=np.int64)


@dataclasses.dataclass(frozen=True)
class MapConfig:
    """The local map's settings."""

    frames: int = setting(5, "frames the local map remembers (a new episode forgets)", 1, 32)
    resolution_m: float = setting(0.05, "local map cell size (m)", 0.01, 1.0)
    band_m: float = setting(0.5, "the local map keeps returns within this height of the camera (m)", 0.05, 3.0)
    range_m: float = setting(6.4, "the local map keeps returns within this horizontal range of the camera (m)", 0.5, 50.0)
    solid_m: float = setting(
        0.6, "weather filter: a cell whose returns in one frame span this much height stands from the floor (m)", 0.0, 10.0
    )
    confirm_frames: int = setting(3, "weather filter: otherwise a cell counts once seen in this many frames", 1, 32)
    confirm_cells: int = setting(0, "weather filter: ... or its neighbours within this many cells were", 0, 5)
    carve_m: float = setting(
        0.15,
        "weather filter: a remembered cell is cleared when a later frame sees this far beyond it (m; plus a noise "
        "allowance of 0.02 m per m^2 of depth)",
        0.0,
        5.0,
    )

    def validate(self) -> None:
        if self.band_m > 3.0:
            raise ValueError(f"map band_m {self.band_m} is invalid: expected at most 3.0 (60 height bins)")
        if self.confirm_frames > self.frames:
            raise ValueError(f"map confirm_frames {self.confirm_frames} exceeds frames {self.frames}")


@dataclasses.dataclass(frozen=True)
class PinholeCamera:
    """A level depth camera's intrinsics (pixels, principal point at cx, cy: sensor_msgs/CameraInfo's K)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> PinholeCamera:
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, f, f, width / 2.0, height / 2.0)


@dataclasses.dataclass
class _Frame:
    keys: np.ndarray  # (n,) int64, sorted, unique: the cells this frame hit
    z_lo: np.ndarray  # (n,) lowest and highest return in each cell, relative to the camera (m)
    z_hi: np.ndarray
    solid: np.ndarray  # (n,) bool: the cell stands from the floor in this frame


class LocalMap:
    """The memory: `insert` one frame with the camera's pose, then ask `occupied`, `clearance` or `egocentric`."""

    def __init__(self, config: MapConfig = MapConfig()):
        config.validate()
        self.config = config
        self._frames: list[_Frame] = []
        self._bins = int(math.ceil(2 * config.band_m / BIN_M))
        self._pose = (0.0, 0.0, 0.0, 0.0)
        self._pixel_keys: np.ndarray | None = None  # the newest frame's cell per pixel (-1: not mapped)
        self._occupied: np.ndarray | None = None
        self._field = None
        self.carved = 0  # remembered cells cleared by later frames (a count for diagnostics)

    # -- memory ---------------------------------------------------------------------------------
    def reset(self) -> None:
        """A new episode: nothing is remembered."""
        self._frames.clear()
        self._pixel_keys, self._occupied, self._field = None, None, None

    @property
    def pose(self) -> tuple[float, float, float, float]:
        """The newest frame's camera pose (x, y, z, yaw) in the odometry frame."""
        return self._pose

    def insert(self, depth_m: np.ndarray, camera: PinholeCamera, x_m: float, y_m: float, z_m: float, yaw_rad: float):
        """Add one measured frame (metres along the optical axis; +Inf, NaN or 0: no return) seen from the camera at
        (x, y, z, yaw) in the odometry frame."""
        depth = np.asarray(depth_m, dtype=np.float32)
        if depth.shape != (camera.height, camera.width):
            raise ValueError(f"depth image {depth.shape} does not match the camera's {camera.height}x{camera.width}")
        cfg, res = self.config, self.config.resolution_m
        self._pose = (float(x_m), float(y_m), float(z_m), float(yaw_rad))
        self._carve(depth, camera)
        h, w = depth.shape
        u = (np.arange(w, dtype=np.float32) + 0.5 - camera.cx) / camera.fx
        v = (np.arange(h, dtype=np.float32) + 0.5 - camera.cy) / camera.fy
        with np.errstate(invalid="ignore"):
            z = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
            left, up = -u[None, :] * z, -v[:, None] * z
            keep = (np.abs(up) <= cfg.band_m) & (np.hypot(z, left) <= cfg.range_m)
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        wx = x_m + c * z[keep] - s * left[keep]
        wy = y_m + s * z[keep] + c * left[keep]
        keys = _keys(np.floor(wx / res).astype(np.int64), np.floor(wy / res).astype(np.int64))
        pixel_keys = np.full(depth.shape, -1, dtype=np.int64)
        pixel_keys[keep] = keys
        self._pixel_keys = pixel_keys
        cells, inverse = np.unique(keys, return_inverse=True)
        z_lo = np.full(len(cells), np.inf, dtype=np.float32)
        z_hi = np.full(len(cells), -np.inf, dtype=np.float32)
        np.minimum.at(z_lo, inverse, up[keep])
        np.maximum.at(z_hi, inverse, up[keep])
        fwd = np.zeros(len(cells), dtype=np.float32)
        np.maximum.at(fwd, inverse, z[keep])
        heights = np.zeros(len(cells), dtype=np.int64)  # a bit per BIN_M of height with a return in it
        bins = np.clip(((up[keep] + cfg.band_m) / BIN_M).astype(np.int64), 0, self._bins - 1)
        np.bitwise_or.at(heights, inverse, np.left_shift(1, bins))
        solid = self._solid(cells, heights, fwd, camera)
        self._frames.append(_Frame(cells, z_lo, z_hi, solid))
        del self._frames[: -cfg.frames]
        self._occupied, self._field = None, None

    def _solid(self, cells, heights, fwd, camera: PinholeCamera) -> np.ndarray:
        """Whether each cell's returns (with its neighbours') fill, without a gap, the height an obstacle standing
        from the floor shows at that range: solid_m, or nearly all of the band the camera sees there."""
        if not len(cells):
            return np.zeros(0, dtype=bool)
        cfg = self.config
        # Noise spreads one surface over neighbouring cells: the heights of each cell's 3x3 neighbourhood.
        near = (cells[:, None] + _NEIGHBOURS[None, :]).ravel()
        at = np.searchsorted(cells, near).clip(0, len(cells) - 1)
        found = (cells[at] == near).reshape(len(cells), -1)
        mask = np.bitwise_or.reduce(np.where(found, heights[at].reshape(found.shape), 0), axis=1)
        # Close up the noise is millimetres: a cell alone (particles side by side must not add up).
        mask = np.where(fwd > NEIGHBOURS_BEYOND_M, mask, heights)
        run = np.zeros(len(cells), dtype=np.int64)  # the longest run of filled bins
        while mask.any():
            run += mask != 0
            mask &= mask >> 1
        seen = np.minimum(cfg.band_m, fwd * camera.cy / camera.fy) + np.minimum(
            cfg.band_m, fwd * (camera.height - camera.cy) / camera.fy
        )
        return run * BIN_M >= np.minimum(cfg.solid_m, 0.8 * seen - BIN_M)

    def _carve(self, depth: np.ndarray, camera: PinholeCamera) -> None:
        """Clear the remembered cells that this frame sees through (two of the three pixels sampled over a cell's
        height, or all when fewer fall in the image, measure beyond it)."""
        if not self._frames:
            return
        res = self.config.resolution_m
        x, y, _, yaw = self._pose
        c, s = math.cos(yaw), math.sin(yaw)
        for frame in self._frames:
            if not len(frame.keys):
                continue
            cx, cy = _centres(frame.keys, res)
            dx, dy = cx - x, cy - y
            fwd, left = c * dx + s * dy, -s * dx + c * dy
            ahead = fwd > 2 * res
            col = np.floor(camera.cx - left / np.where(ahead, fwd, 1.0) * camera.fx).astype(np.int64)
            inside = ahead & (col >= 0) & (col < camera.width)
            if not inside.any():
                continue
            idx = np.flatnonzero(inside)
            f = fwd[idx]
            beyond = np.zeros((len(idx), 3), dtype=bool)
            valid = np.zeros((len(idx), 3), dtype=bool)
            for j, share in enumerate((0.0, 0.5, 1.0)):
                up = frame.z_lo[idx] + share * (frame.z_hi[idx] - frame.z_lo[idx])
                row = np.floor(camera.cy - up / f * camera.fy).astype(np.int64)
                ok = (row >= 0) & (row < camera.height)
                d = depth[row.clip(0, camera.height - 1), col[idx]]
                finite = ok & np.isfinite(d) & (d > 0)
                valid[:, j] = finite
                beyond[:, j] = finite & (d > f + self.config.carve_m + 0.02 * f * f)
            n_valid, n_beyond = valid.sum(axis=1), beyond.sum(axis=1)
            cleared = (n_beyond >= 1) & (n_beyond >= np.minimum(2, n_valid))
            if cleared.any():
                keep = np.ones(len(frame.keys), dtype=bool)
                keep[idx[cleared]] = False
                self.carved += int(cleared.sum())
                frame.keys, frame.z_lo, frame.z_hi, frame.solid = (
                    frame.keys[keep],
                    frame.z_lo[keep],
                    frame.z_hi[keep],
                    frame.solid[keep],
                )

    # -- what counts ------------------------------------------------------------------------------
    def occupied(self) -> np.ndarray:
        """The cells that count as obstacles (sorted int64 keys): remembered, not seen through since, and standing
        from the floor or seen in confirm_frames frames."""
        if self._occupied is not None:
            return self._occupied
        frames, need = self._frames, self.config.confirm_frames
        if not frames:
            self._occupied = np.zeros(0, dtype=np.int64)
            return self._occupied
        # Each frame's cells (with their neighbours within confirm_cells), counted once per frame.
        r = np.arange(-self.config.confirm_cells, self.config.confirm_cells + 1, dtype=np.int64)
        near = ((r[:, None] << 21) + r[None, :]).ravel()
        all_spread = np.concatenate([np.unique((f.keys[:, None] + near[None, :]).ravel()) for f in frames])
        cells, counts = np.unique(all_spread, return_counts=True)
        out = []
        for f in frames:
            at = np.searchsorted(cells, f.keys)
            confirmed = counts[at] >= need if len(f.keys) else np.zeros(0, dtype=bool)
            out.append(f.keys[f.solid | confirmed])
        self._occupied = np.unique(np.concatenate(out))
        return self._occupied

    def occupied_xy(self) -> np.ndarray:
        """(n, 2) the occupied cells' centres in the odometry frame."""
        cx, cy = _centres(self.occupied(), self.config.resolution_m)
        return np.stack([cx, cy], axis=-1)

    def pixels_near(self, keys, radius_cells: int = 1) -> np.ndarray:
        """(H, W) bool: the newest frame's pixels that put a return within radius_cells of the given cells."""
        if self._pixel_keys is None:
            raise RuntimeError("the local map has no frame yet")
        keys = np.asarray(keys, dtype=np.int64).ravel()
        r = np.arange(-radius_cells, radius_cells + 1, dtype=np.int64)
        near = np.unique((keys[:, None] + ((r[:, None] << 21) + r[None, :]).ravel()[None, :]).ravel())
        return np.isin(self._pixel_keys, near) & (self._pixel_keys >= 0)

    # -- distances ------------------------------------------------------------------------------
    def clearance(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance to the nearest occupied cell's edge (m; +Inf where none is known within the window), that cell's
        key (-1 where none)) for points in the odometry frame, shaped like them."""
        x, y = np.asarray(x_m), np.asarray(y_m)
        field = self._distance_field()
        if field is None:
            return np.full(x.shape, np.inf), np.full(x.shape, -1, dtype=np.int64)
        dist, nearest, (ix0, iy0), n = field
        res = self.config.resolution_m
        ix = np.floor(x / res).astype(np.int64) - ix0
        iy = np.floor(y / res).astype(np.int64) - iy0
        inside = (ix >= 0) & (ix < n) & (iy >= 0) & (iy < n)
        ixc, iyc = ix.clip(0, n - 1), iy.clip(0, n - 1)
        d = np.where(inside, dist[ixc, iyc], np.inf)
        k = np.where(inside, nearest[ixc, iyc], -1)
        return d, k

    def _distance_field(self):
        """The distance transform over a window of twice range_m around the newest camera position (cached)."""
        if self._field is not None:
            return self._field or None
        keys = self.occupied()
        if not len(keys):
            self._field = ()
            return None
        res, half = self.config.resolution_m, self.config.range_m + 1.5
        n = int(math.ceil(2 * half / res))
        ix0 = int(math.floor(self._pose[0] / res)) - n // 2
        iy0 = int(math.floor(self._pose[1] / res)) - n // 2
        ix, iy = (keys >> 21) - _OFFSET - ix0, (keys & ((1 << 21) - 1)) - _OFFSET - iy0
        ok = (ix >= 0) & (ix < n) & (iy >= 0) & (iy < n)
        free = np.ones((n, n), dtype=bool)
        free[ix[ok], iy[ok]] = False
        if free.all():
            self._field = ()
            return None
        from scipy import ndimage  # here, not at the top: it takes 0.2 s to import and most nodes never call this

        edt, (ni, nj) = ndimage.distance_transform_edt(free, return_indices=True)
        dist = np.maximum(edt * res - res / 2, 0.0)  # to the cell's edge, not its centre
        nearest = _keys(ni + ix0, nj + iy0)
        self._field = (dist, nearest, (ix0, iy0), n)
        return self._field

    # -- the student's view ------------------------------------------------------------------------
    def keys_at(self, mask: np.ndarray) -> np.ndarray:
        """The cells (sorted int64 keys) that the newest frame's pixels under `mask` (a bool image) fell in."""
        if self._pixel_keys is None:
            raise RuntimeError("the local map has no frame yet")
        keys = self._pixel_keys[np.asarray(mask, dtype=bool)]
        return np.unique(keys[keys >= 0])

    def egocentric(self, cells: int, resolution_m: float, near_keys: np.ndarray | None = None) -> np.ndarray:
        """(cells, cells) float32 occupancy in the body frame of the newest pose: row 0 is farthest ahead, the
        vehicle at the bottom centre looking up the image, left on the left. With `near_keys`, only the occupied
        cells within one cell of those (say the cells a decision's reason put there)."""
        grid = np.zeros((cells, cells), dtype=np.float32)
        occupied = self.occupied()
        if near_keys is not None:
            r = np.arange(-1, 2, dtype=np.int64)
            near = ((r[:, None] << 21) + r[None, :]).ravel()
            occupied = occupied[np.isin(occupied, (np.asarray(near_keys, np.int64)[:, None] + near[None, :]).ravel())]
        cx, cy = _centres(occupied, self.config.resolution_m)
        xy = np.stack([cx, cy], axis=-1)
        if not len(xy):
            return grid
        x, y, _, yaw = self._pose
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = xy[:, 0] - x, xy[:, 1] - y
        fwd, left = c * dx + s * dy, -s * dx + c * dy
        row = cells - 1 - np.floor(fwd / resolution_m + cells / 4).astype(np.int64)  # a quarter of it behind
        col = cells // 2 - 1 - np.floor(left / resolution_m).astype(np.int64)
        ok = (row >= 0) & (row < cells) & (col >= 0) & (col < cells)
        grid[row[ok], col[ok]] = 1.0
        return grid


def camera_position(x_m: float, y_m: float, yaw_rad: float, forward_m: float = CAMERA_FORWARD_M) -> tuple[float, float]:
    """Where a camera `forward_m` ahead of base_link at (x, y, yaw) is (the pose odometry gives is base_link's)."""
    return x_m + forward_m * math.cos(yaw_rad), y_m + forward_m * math.sin(yaw_rad)


def _keys(ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    return ((np.asarray(ix, dtype=np.int64) + _OFFSET) << 21) | (np.asarray(iy, dtype=np.int64) + _OFFSET)


def _centres(keys: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray]:
    ix = (keys >> 21) - _OFFSET
    iy = (keys & ((1 << 21) - 1)) - _OFFSET
    return (ix + 0.5) * res, (iy + 0.5) * res
