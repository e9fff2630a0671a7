"""costmap_2d's static layer from a ROS map, and its inflation formula.

Users of ROS read costs as costmap_2d defines them, so we keep its values (wsnav.zones.cost_values) and its rule
exactly: between the inscribed radius and the inflation radius `252 * exp(-k * (d - r_inscribed))`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numba import njit
from numpy.typing import NDArray

from wsnav.schemas.ros_map import OCCUPIED, UNKNOWN, OccupancyGrid
from wsnav.zones.cost_values import (
    FREE_SPACE,
    INSCRIBED_INFLATED_OBSTACLE,
    LETHAL_OBSTACLE,
    NO_INFORMATION,
    Costs,
)


@dataclass(frozen=True)
class InflationParams:
    """costmap_2d's inflation_layer parameters; defaults are TurtleBot3 Burger's navigation config."""

    inscribed_radius: float = 0.105
    inflation_radius: float = 1.0
    cost_scaling_factor: float = 3.0
    inflate_unknown: bool = False

    def __post_init__(self) -> None:
        if self.inscribed_radius < 0 or self.inflation_radius < 0 or self.cost_scaling_factor < 0:
            raise ValueError("inflation radii and cost_scaling_factor must not be negative")


def static_layer(grid: OccupancyGrid, *, lethal_threshold: int = 100, track_unknown: bool = True) -> Costs:
    """The static layer of a map, as costmap_2d's static_layer makes it from an OccupancyGrid.

    Occupied (>= lethal_threshold) -> LETHAL, unknown (-1) -> NO_INFORMATION (or FREE when not tracking
    unknown space), everything else FREE; row 0 stays the map's bottom row.
    """
    data = grid.data.astype(np.int16)
    costs = np.zeros(data.shape, dtype=np.uint8)
    costs[data >= min(lethal_threshold, OCCUPIED)] = LETHAL_OBSTACLE
    if track_unknown:
        costs[data == UNKNOWN] = NO_INFORMATION
    return costs


@lru_cache(maxsize=16)
def cost_lut(resolution: float, params: InflationParams) -> NDArray[np.uint8]:
    """Cost by squared cell distance to the nearest lethal cell (costmap_2d caches costs the same way).

    The last entry stands for every distance beyond the inflation radius (cost FREE). Cached: read only.
    """
    max_cells = inflation_reach(resolution, params)
    d2 = np.arange(max_cells * max_cells + 1, dtype=np.float64)
    d = np.sqrt(d2) * resolution
    factor = np.exp(-params.cost_scaling_factor * (d - params.inscribed_radius))
    lut = np.floor((INSCRIBED_INFLATED_OBSTACLE - 1) * factor).clip(0, 252).astype(np.uint8)
    lut[d <= params.inscribed_radius] = INSCRIBED_INFLATED_OBSTACLE
    lut[d > params.inflation_radius] = FREE_SPACE
    lut[-1] = FREE_SPACE
    lut[0] = LETHAL_OBSTACLE
    lut.setflags(write=False)
    return lut


def inflation_reach(resolution: float, params: InflationParams) -> int:
    """Cells beyond which a lethal cell cannot change a cell's inflated cost."""
    return math.ceil(params.inflation_radius / resolution) + 1


def inflate(
    master: Costs,
    resolution: float,
    params: InflationParams,
    inner: tuple[slice, slice] | None = None,
) -> Costs:
    """Merge the inflation of `master`'s lethal cells into a copy of it (costmap_2d's updateCosts rule).

    Known cells take the maximum of their cost and the inflated cost; unknown cells stay unknown unless the
    inflated cost is inscribed or lethal (or any positive cost with inflate_unknown), as in costmap_2d.
    Distances are exact Euclidean distances between cell centres, as costmap_2d measures them. `inner`
    (slices with bounds, as Bounds.within gives): only that part of master, computed from the lethal cells
    of all of it; exact when master reaches `inflation_reach` cells beyond it (or the map's edge).
    """
    height, width = master.shape
    rows, cols = inner if inner is not None else (slice(0, height), slice(0, width))
    row0, row1, _ = rows.indices(height)
    col0, col1, _ = cols.indices(width)
    out = np.empty((max(row1 - row0, 0), max(col1 - col0, 0)), dtype=np.uint8)
    threshold = FREE_SPACE + 1 if params.inflate_unknown else INSCRIBED_INFLATED_OBSTACLE
    reach = inflation_reach(resolution, params)
    _inflate(master, cost_lut(resolution, params), reach, row0, col0, threshold, out)
    return out


@njit(error_model="numpy")
def _inflate(
    master: Costs,
    lut: NDArray[np.uint8],
    reach: int,
    row0: int,
    col0: int,
    threshold: int,
    out: Costs,
) -> None:
    """`out` = master's window at (row0, col0) merged with its inflation (the rule of `inflate`).

    Squared distances to the nearest lethal cell, cut off at reach squared (lut's last entry: everything
    farther costs the same), by the two passes of an exact Euclidean distance transform: per column the
    distance to the nearest lethal cell of that column (capped at reach), then per row the lower envelope of the
    parabolas (c - c')^2 + g(c')^2 (Felzenszwalb and Huttenlocher). Compiled (numba): only the window's
    rows and the columns within reach of it are visited, and a capped distance cannot hide a nearer one.
    """
    height, width = master.shape
    rows, cols = out.shape
    if rows == 0 or cols == 0:
        return
    big = reach * reach
    lo_row, hi_row = max(row0 - reach, 0), min(row0 + rows + reach, height)
    lo_col, hi_col = max(col0 - reach, 0), min(col0 + cols + reach, width)
    n = hi_col - lo_col
    # g2[r, c]: squared distance along column lo_col + c from row row0 + r to its nearest lethal cell, capped at
    # reach; swept down, then up, a row at a time (master is row-major).
    g2 = np.empty((rows, n), dtype=np.int32)
    d = np.full(n, reach, dtype=np.int32)
    for r in range(lo_row, hi_row):
        for c in range(n):
            d[c] = 0 if master[r, lo_col + c] == 254 else min(d[c] + 1, reach)
            if row0 <= r < row0 + rows:
                g2[r - row0, c] = d[c]
    d = np.full(n, reach, dtype=np.int32)
    for r in range(hi_row - 1, lo_row - 1, -1):
        for c in range(n):
            d[c] = 0 if master[r, lo_col + c] == 254 else min(d[c] + 1, reach)
            if row0 <= r < row0 + rows:
                g = min(g2[r - row0, c], d[c])
                g2[r - row0, c] = g * g
    v = np.empty(n, dtype=np.int64)
    z = np.empty(n + 1, dtype=np.float64)
    for r in range(rows):
        f = g2[r]
        k = 0
        v[0] = 0
        z[0] = -np.inf
        z[1] = np.inf
        for q in range(1, n):
            p = v[k]
            s = ((f[q] + q * q) - (f[p] + p * p)) / (2.0 * (q - p))
            while s <= z[k]:
                k -= 1
                p = v[k]
                s = ((f[q] + q * q) - (f[p] + p * p)) / (2.0 * (q - p))
            k += 1
            v[k] = q
            z[k] = s
            z[k + 1] = np.inf
        k = 0
        for c in range(cols):
            q = col0 + c - lo_col
            while z[k + 1] < q:
                k += 1
            p = v[k]
            d2 = min((q - p) * (q - p) + f[p], big)
            inflated = lut[d2]
            cost = master[row0 + r, col0 + c]
            if cost == 255:
                out[r, c] = inflated if inflated >= threshold else cost
            else:
                out[r, c] = max(cost, inflated)
