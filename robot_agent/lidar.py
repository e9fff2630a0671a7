"""A simulated 2-D lidar (LDS-01-like: 360 beams, 3.5 m) cast against an occupancy grid with NumPy.

All beams march at once along their rays at a fraction of a cell; the first sample that lands in an occupied
cell names the cell hit, and the range is the exact distance at which the ray enters that cell's square, so
a wall's range is right to the grid, not to the sampling step. Ranges follow REP 117: +inf when nothing lies
within `range_max`, -inf when something is closer than `range_min` (too close to measure).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from robot_agent.backend import LaserScan, Pose
from robot_agent.zone_geometry import GridFrame


@dataclass(frozen=True)
class LidarParams:
    """The sensor; defaults are the TurtleBot3's LDS-01 (ROBOTIS: 360 samples per turn, 0.12-3.5 m, 5 Hz)."""

    beams: int = 360
    range_min: float = 0.12
    range_max: float = 3.5
    rate_hz: float = 5.0
    noise_std: float = 0.0
    """Standard deviation (m) of Gaussian noise added to each valid range; 0 for an exact sensor."""
    step_cells: float = 0.5
    """March step as a fraction of a cell: smaller misses fewer corner cells, costs more."""

    def __post_init__(self) -> None:
        if self.beams < 1:
            raise ValueError("a lidar needs at least one beam")
        if not 0 <= self.range_min < self.range_max:
            raise ValueError("need 0 <= range_min < range_max")
        if self.rate_hz <= 0 or self.noise_std < 0 or not 0 < self.step_cells <= 1:
            raise ValueError("rate_hz must be > 0, noise_std >= 0, 0 < step_cells <= 1")

    @property
    def angle_increment(self) -> float:
        return 2.0 * math.pi / self.beams

    @property
    def angle_min(self) -> float:
        return 0.0


@lru_cache(maxsize=16)
def _samples(params: LidarParams, resolution: float) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """Sample distances along a ray (in cells) and the beams' angles relative to the robot."""
    range_cells = params.range_max / resolution
    count = math.ceil(range_cells / params.step_cells) + 1
    t = (np.arange(1, count + 1, dtype=np.float32) * np.float32(params.step_cells)).astype(np.float32)
    angles = params.angle_min + np.arange(params.beams, dtype=np.float64) * params.angle_increment
    return t, angles


def cast_scan(
    occupied: NDArray[np.bool_],
    frame: GridFrame,
    pose: Pose,
    params: LidarParams,
    stamp: float,
    rng: np.random.Generator | None = None,
) -> LaserScan:
    """One sweep from `pose` (the sensor at the robot's centre) against `occupied` (row 0 = map bottom).

    Cells outside the grid count as free. With `rng` and `params.noise_std > 0`, valid ranges get noise.
    """
    ranges = cast_ranges(occupied, frame, pose, params)
    if rng is not None and params.noise_std > 0:
        valid = np.isfinite(ranges)
        noisy = ranges[valid] + rng.normal(0.0, params.noise_std, int(valid.sum())).astype(np.float32)
        ranges[valid] = np.clip(noisy, params.range_min, params.range_max)
    return LaserScan(
        stamp=stamp,
        pose=pose,
        angle_min=params.angle_min,
        angle_increment=params.angle_increment,
        range_min=params.range_min,
        range_max=params.range_max,
        ranges=ranges,
    )


def cast_ranges(
    occupied: NDArray[np.bool_], frame: GridFrame, pose: Pose, params: LidarParams
) -> NDArray[np.float32]:
    """The ranges alone (metres, float32, REP 117 infinities), for callers that build their own message."""
    height, width = occupied.shape
    res = frame.resolution
    t, rel = _samples(params, res)
    x, y, yaw = pose
    u0 = (x - frame.origin_x) / res
    v0 = (y - frame.origin_y) / res
    angles = rel + yaw
    dx = np.cos(angles)
    dy = np.sin(angles)
    # Continuous cell coordinates of every sample: (beams, samples).
    us = np.float32(u0) + np.outer(dx.astype(np.float32), t)
    vs = np.float32(v0) + np.outer(dy.astype(np.float32), t)
    inside = (us >= 0) & (us < width) & (vs >= 0) & (vs < height)
    cols = us.astype(np.intp)
    rows = vs.astype(np.intp)
    flat = rows * width + cols
    flat[~inside] = 0
    hit = occupied.ravel()[flat]
    hit &= inside
    first = hit.argmax(axis=1)
    any_hit = hit[np.arange(len(first)), first]

    ranges = np.full(len(rel), np.inf, dtype=np.float32)
    start_row, start_col = math.floor(v0), math.floor(u0)
    if 0 <= start_row < height and 0 <= start_col < width and occupied[start_row, start_col]:
        ranges[:] = -np.inf  # the sensor sits inside an obstacle
        return ranges
    beams = np.flatnonzero(any_hit)
    if len(beams) == 0:
        return ranges
    k = first[beams]
    hit_col = cols[beams, k].astype(np.float64)
    hit_row = rows[beams, k].astype(np.float64)
    enter = np.maximum(_slab_entry(u0, dx[beams], hit_col), _slab_entry(v0, dy[beams], hit_row))
    dist = np.maximum(enter, 0.0) * res
    out = np.where(dist > params.range_max, np.inf, dist)
    out = np.where(out < params.range_min, -np.inf, out)
    ranges[beams] = out.astype(np.float32)
    return ranges


def _slab_entry(p0: float, d: NDArray[np.float64], cell: NDArray[np.float64]) -> NDArray[np.float64]:
    """Ray parameter (cells) at which a ray from p0 along d enters the slab [cell, cell + 1] on one axis."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (cell - p0) / d
        b = (cell + 1.0 - p0) / d
    entry = np.minimum(a, b)
    # A ray parallel to the slab is inside it for all t (it reached the cell along the other axis).
    return np.where(d == 0, -np.inf, entry)
