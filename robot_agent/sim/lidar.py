"""A simulated 2-D lidar (LDS-01-like: 360 beams, 3.5 m) cast against an occupancy grid (a numba kernel).

Beams are traced exactly (Amanatides-Woo grid traversal): every cell a ray enters, it enters across a
vertical or a horizontal grid line, and the crossings of each family are evenly spaced along the ray, so
both families are walked in closed form, each up to its first occupied cell; the range is the smaller of
the two. No corner is skipped and ranges are exact to the grid. Ranges follow REP 117: +inf when nothing lies
within `range_max`, -inf when something is closer than `range_min` (too close to measure).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numba import njit
from numpy.typing import NDArray

from wsnav.navigation.backend import LaserScan, Pose
from wsnav.zones.geometry import GridFrame


@dataclass(frozen=True)
class LidarParams:
    """The sensor; defaults are the TurtleBot3's LDS-01 (ROBOTIS: 360 samples per turn, 0.12-3.5 m, 5 Hz)."""

    beams: int = 360
    range_min: float = 0.12
    range_max: float = 3.5
    rate_hz: float = 5.0
    noise_std: float = 0.0
    """Standard deviation (m) of Gaussian noise added to each valid range; 0 for an exact sensor."""
    noise_fraction: float = 0.0
    """More standard deviation, as a fraction of the range (the LDS-01's precision is +-3.5% beyond 0.5 m)."""

    def __post_init__(self) -> None:
        if self.beams < 1:
            raise ValueError("a lidar needs at least one beam")
        if not 0 <= self.range_min < self.range_max:
            raise ValueError("need 0 <= range_min < range_max")
        if self.rate_hz <= 0 or self.noise_std < 0 or self.noise_fraction < 0:
            raise ValueError("rate_hz must be > 0 and noise_std, noise_fraction >= 0")

    @property
    def angle_increment(self) -> float:
        return 2.0 * math.pi / self.beams

    @property
    def angle_min(self) -> float:
        return 0.0


@lru_cache(maxsize=16)
def _samples(params: LidarParams, resolution: float) -> tuple[int, NDArray[np.float64]]:
    """How many grid lines a ray may cross on one axis within range, and the beams' relative angles."""
    angles = params.angle_min + np.arange(params.beams, dtype=np.float64) * params.angle_increment
    return math.ceil(params.range_max / resolution) + 2, angles


def cast_scan(
    occupied: NDArray[np.bool_],
    frame: GridFrame,
    pose: Pose,
    params: LidarParams,
    stamp: float,
    rng: np.random.Generator | None = None,
) -> LaserScan:
    """One sweep from `pose` (the sensor at the robot's centre) against `occupied` (row 0 = map bottom).

    Cells outside the grid count as free. With `rng` and noise in `params`, valid ranges get Gaussian noise.
    """
    ranges = cast_ranges(occupied, frame, pose, params)
    if rng is not None and (params.noise_std > 0 or params.noise_fraction > 0):
        valid = np.isfinite(ranges)
        sigma = params.noise_std + params.noise_fraction * ranges[valid].astype(np.float64)
        noisy = ranges[valid] + (rng.standard_normal(int(valid.sum())) * sigma).astype(np.float32)
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
    res = frame.resolution
    ranges = np.full(params.beams, np.inf, dtype=np.float32)
    x, y, yaw = pose
    u0 = (x - frame.origin_x) / res
    v0 = (y - frame.origin_y) / res
    height, width = occupied.shape
    if not (0 <= u0 < width and 0 <= v0 < height):
        return ranges  # a sensor off the map sees nothing it could be told about
    if occupied[math.floor(v0), math.floor(u0)]:
        ranges[:] = -np.inf  # the sensor sits inside an obstacle
        return ranges
    crossings, rel = _samples(params, res)
    angles = rel + yaw
    return _cast(
        occupied.ravel(),
        width,
        height,
        u0,
        v0,
        np.cos(angles),
        np.sin(angles),
        crossings,
        params.range_max / res,
        res,
        params.range_min,
    )


@njit(error_model="numpy")
def _cast(
    flat: NDArray[np.bool_],
    width: int,
    height: int,
    u0: float,
    v0: float,
    dx: NDArray[np.float64],
    dy: NDArray[np.float64],
    crossings: int,
    range_max_cells: float,
    res: float,
    range_min: float,
) -> NDArray[np.float32]:
    """Each ray's range (metres, REP 117's -inf under range_min) from (u0, v0) in cells, along (dx, dy).

    Compiled (numba), with the same float32/float64 operations in the same order as the array form it
    replaced, so scans are bit for bit what they were.
    """
    ranges = np.empty(dx.shape[0], dtype=np.float32)
    for i in range(dx.shape[0]):
        # Rays leave the grid (and with it every occupied cell) at t_exit; look no further than it or range_max.
        limit = min(min(_exit(u0, dx[i], width), _exit(v0, dy[i], height)), range_max_cells)
        # Every cell a ray enters, it enters across a vertical or a horizontal grid line: take both families.
        t_x = _first_hit(flat, width, u0, v0, dx[i], dy[i], crossings, limit, True)
        t_y = _first_hit(flat, width, v0, u0, dy[i], dx[i], crossings, limit, False)
        first = min(t_x, t_y) * res
        ranges[i] = -np.inf if first < range_min else first
    return ranges


@njit(error_model="numpy")
def _exit(a0: float, da: float, size: int) -> float:
    """Ray parameter (cells) at which a ray from a0 leaves [0, size) on one axis."""
    if da > 0:
        return (size - a0) / da
    if da < 0:
        return -a0 / da
    return np.inf


@njit(error_model="numpy")
def _first_hit(
    flat: NDArray[np.bool_],
    width: int,
    a0: float,
    b0: float,
    da: float,
    db: float,
    crossings: int,
    limit: float,
    vertical: bool,
) -> float:
    """Smallest ray parameter (cells) at which the ray enters an occupied cell across a line of axis a.

    Lines of axis a are crossed evenly, every 1/|da| along the ray, the first at floor(a0) + 1 going up
    (floor(a0) going down); the cell entered there is the line's neighbour on axis a and floor(b0 + t db) on
    axis b. `vertical`: axis a is x (columns), else y (rows). inf where no occupied cell is entered in range.
    The walk stops at the first hit. Crossing parameters are float32 (ranges stay well under a millimetre).
    """
    base = math.floor(a0)
    up = da > 0
    first_line = base + 1.0 if up else float(base)
    first_cell = base + 1 if up else base - 1
    step = 1 if up else -1
    # A ray parallel to these lines never crosses one: its t is inf or nan, and fails `t < lim`.
    t0 = np.float32((first_line - a0) / da)
    delta = np.float32(abs(1.0 / da))
    lim = np.float32(limit)
    b0_32 = np.float32(b0)
    db_32 = np.float32(db)
    last = flat.shape[0] - 1
    for k in range(crossings):
        t = t0 + np.float32(k) * delta
        if not t < lim:
            break
        cell_b = np.int32(b0_32 + t * db_32)
        cell_a = first_cell + k * step
        index = cell_b * width + cell_a if vertical else cell_a * width + cell_b
        if flat[min(max(index, 0), last)]:
            return np.float64(t)
    return np.inf
