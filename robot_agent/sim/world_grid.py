"""The simulated world as the robot's sensors and bumper see it: the site's static map, placed obstacles, and
the other robots of a simulated fleet (each a disk where it stands, for the others' lidars and bumpers).

The zone simulator publishes the obstacles it placed (schemas.messages.SimWorld, the whole set each time);
`apply` rasterises them onto a copy of the map's occupied cells, touching only the obstacles' windows.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt

from wsnav.navigation.costmap.inflation import static_layer
from wsnav.schemas.messages import SimWorld
from wsnav.schemas.ros_map import OccupancyGrid
from wsnav.zones.cost_values import LETHAL_OBSTACLE
from wsnav.zones.geometry import CellWindow, GridFrame, polygon_window


class SimWorldGrid:
    """Occupied cells (row 0 = map bottom) of the map plus the current obstacles."""

    def __init__(self, grid: OccupancyGrid) -> None:
        self.frame = GridFrame(grid.width, grid.height, grid.resolution, grid.origin[0], grid.origin[1])
        self._static: NDArray[np.bool_] = static_layer(grid) == LETHAL_OBSTACLE
        self.occupied: NDArray[np.bool_] = self._static.copy()
        self._windows: dict[str, CellWindow] = {}
        self.version = 0
        """Bumped on every change of `occupied`, so a reader can cache what it derives from it."""
        self._clearance: tuple[int, NDArray[np.float32]] | None = None
        self._robots: dict[str, tuple[float, float, float]] = {}
        """Robot id -> (x, y, radius) of each simulated robot in this world."""

    def place_robot(self, robot_id: str, x: float, y: float, radius: float) -> None:
        """Where a simulated robot of this world stands now (it registers and moves itself)."""
        self._robots[robot_id] = (x, y, radius)

    def occupied_seen_by(self, robot_id: str) -> NDArray[np.bool_]:
        """The occupied cells with every other robot's footprint painted in: what this robot's lidar sees.

        With no other robot in the world, `occupied` itself (no copy)."""
        others = [disk for r, disk in self._robots.items() if r != robot_id]
        if not others:
            return self.occupied
        out = self.occupied.copy()
        frame = self.frame
        res = frame.resolution
        for x, y, radius in others:
            row, col = frame.world_to_cell(x, y)
            reach = math.ceil(radius / res) + 1
            r0, r1 = max(row - reach, 0), min(row + reach + 1, frame.height)
            c0, c1 = max(col - reach, 0), min(col + reach + 1, frame.width)
            if r1 <= r0 or c1 <= c0:
                continue
            ys = frame.origin_y + (np.arange(r0, r1) + 0.5) * res
            xs = frame.origin_x + (np.arange(c0, c1) + 0.5) * res
            out[r0:r1, c0:c1] |= np.hypot(xs[None, :] - x, ys[:, None] - y) <= radius
        return out

    def robot_touching(self, robot_id: str, x: float, y: float, radius: float) -> str | None:
        """Another robot whose footprint the footprint of `robot_id` at (x, y) would overlap, or None."""
        for other, (ox, oy, r) in self._robots.items():
            if other != robot_id and math.hypot(ox - x, oy - y) < radius + r:
                return other
        return None

    @property
    def obstacle_ids(self) -> list[str]:
        return sorted(self._windows)

    def apply(self, world: SimWorld) -> None:
        """Replace the obstacle set with `world.obstacles` (an empty list clears them all)."""
        windows = {ob.id: polygon_window(ob.polygon, self.frame) for ob in world.obstacles}
        windows = {k: w for k, w in windows.items() if not w.empty}
        if windows.keys() == self._windows.keys() and all(
            _same(windows[k], self._windows[k]) for k in windows
        ):
            return
        for old in self._windows.values():
            self.occupied[old.rows, old.cols] = self._static[old.rows, old.cols]
        for new in windows.values():
            self.occupied[new.rows, new.cols] |= new.mask
        self._windows = windows
        self.version += 1

    def centre_clearance(self) -> NDArray[np.float32]:
        """Per cell, metres from its centre to the nearest occupied cell's centre (recomputed after a change).

        Lets the bumper skip its exact test wherever the robot is clearly far from everything, which is most of
        the way: the exact test runs at every physics substep.
        """
        if self._clearance is None or self._clearance[0] != self.version:
            dist = np.asarray(distance_transform_edt(~self.occupied), dtype=np.float32)
            self._clearance = (self.version, dist * np.float32(self.frame.resolution))
        return self._clearance[1]

    def is_occupied(self, x: float, y: float) -> bool:
        """Whether the cell holding world point (x, y) is occupied; outside the map counts as free."""
        row, col = self.frame.world_to_cell(x, y)
        return self.frame.contains_cell(row, col) and bool(self.occupied[row, col])


def _same(a: CellWindow, b: CellWindow) -> bool:
    return a.row0 == b.row0 and a.col0 == b.col0 and np.array_equal(a.mask, b.mask)
