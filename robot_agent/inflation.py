"""costmap_2d's cost values, its static layer from a ROS map, and its inflation formula.

Users of ROS read costs as costmap_2d defines them, so we keep its numbers and its rule exactly:
0 free, 253 inscribed (the robot's centre here means a collision), 254 lethal, 255 unknown, and between
the inscribed radius and the inflation radius `252 * exp(-k * (d - r_inscribed))`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt

from schemas.ros_map import OCCUPIED, UNKNOWN, OccupancyGrid

FREE_SPACE = 0
INSCRIBED_INFLATED_OBSTACLE = 253
LETHAL_OBSTACLE = 254
NO_INFORMATION = 255

Costs = NDArray[np.uint8]


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


def cost_lut(resolution: float, params: InflationParams) -> NDArray[np.uint8]:
    """Cost by squared cell distance to the nearest lethal cell (costmap_2d caches costs the same way).

    The last entry stands for every distance beyond the inflation radius (cost FREE).
    """
    max_cells = int(np.ceil(params.inflation_radius / resolution)) + 1
    d2 = np.arange(max_cells * max_cells + 1, dtype=np.float64)
    d = np.sqrt(d2) * resolution
    factor = np.exp(-params.cost_scaling_factor * (d - params.inscribed_radius))
    lut = np.floor((INSCRIBED_INFLATED_OBSTACLE - 1) * factor).clip(0, 252).astype(np.uint8)
    lut[d <= params.inscribed_radius] = INSCRIBED_INFLATED_OBSTACLE
    lut[d > params.inflation_radius] = FREE_SPACE
    lut[-1] = FREE_SPACE
    lut[0] = LETHAL_OBSTACLE
    return lut


def inflation_costs(lethal: NDArray[np.bool_], resolution: float, params: InflationParams) -> Costs:
    """The inflation layer alone: each cell's cost from its distance to the nearest lethal cell.

    Distances are exact Euclidean distances between cell centres (scipy's EDT), as costmap_2d measures them.
    """
    if not bool(lethal.any()):
        return np.zeros(lethal.shape, dtype=np.uint8)
    lut = cost_lut(resolution, params)
    dist = np.asarray(distance_transform_edt(~lethal), dtype=np.float64)
    d2 = np.minimum(np.rint(dist * dist), len(lut) - 1).astype(np.intp)
    return lut[d2]


def inflate(master: Costs, resolution: float, params: InflationParams) -> Costs:
    """Merge the inflation of `master`'s lethal cells into a copy of it (costmap_2d's updateCosts rule).

    Known cells take the maximum of their cost and the inflated cost; unknown cells stay unknown unless the
    inflated cost is inscribed or lethal (or any positive cost with inflate_unknown), as in costmap_2d.
    """
    inflated = inflation_costs(master == LETHAL_OBSTACLE, resolution, params)
    out = np.maximum(master, inflated)
    unknown = master == NO_INFORMATION
    if bool(unknown.any()):
        threshold = FREE_SPACE + 1 if params.inflate_unknown else INSCRIBED_INFLATED_OBSTACLE
        take = unknown & (inflated >= threshold)
        out[unknown] = NO_INFORMATION
        out[take] = inflated[take]
    return out
