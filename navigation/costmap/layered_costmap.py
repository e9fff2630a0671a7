"""The robot's layered costmap, with costmap_2d's semantics: static -> obstacle -> zone -> robots, then inflation.

The layers (wsnav.navigation.costmap.layers) are merged in order, each by its own rule (costmap_2d's: the static
layer overwrites, the others by updateWithMax, where a layer's NO_INFORMATION never hides a known cost), then
inflated with costmap_2d's formula (wsnav.navigation.costmap.inflation). Every
update touches only the bounds that changed: the cells whose merged cost a layer changed are merged again, and
the inflation layer's reach around them re-inflated from the merged cells within reach of them (a lethal
cell farther than the radius cannot change a cell's cost), so the result is cell for cell what a whole-map
recomputation gives (`rebuild`), at a fraction of the cost on big maps.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from wsnav.navigation.backend import LaserScan, Pose
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layers import (
    InflationLayer,
    Layer,
    ObstacleLayer,
    RobotsLayer,
    StaticLayer,
    ZoneCostLayer,
)
from wsnav.schemas.ros_map import OccupancyGrid
from wsnav.zones.cost_values import FREE_SPACE, INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import Bounds, GridFrame
from wsnav.zones.zone_layer import ZoneLayer

__all__ = ["Bounds", "LayeredCostmap"]

CHANGE_LOG = 64
"""Updates remembered for `changes_since`; a reader further behind recomputes from master whole."""


class LayeredCostmap:
    """Static, obstacle (lidar), zone (WSN) and, in a fleet, robots layers merged in order, then inflated."""

    def __init__(
        self,
        grid: OccupancyGrid,
        inflation: InflationParams,
        *,
        zone_layer: ZoneLayer | None = None,
        obstacle_layer: bool = True,
        obstacle_range_m: float = 3.0,
        raytrace_range_m: float = 3.5,
        robots_layer: RobotsLayer | None = None,
    ) -> None:
        """`robots_layer`: the other robots' footprints (a fleet), merged after the zone layer."""
        self.frame = GridFrame.of_grid(grid)
        if zone_layer is not None and zone_layer.frame != self.frame:
            raise ValueError("the zone layer was built for another grid frame")
        self.static = StaticLayer(grid)
        self.obstacles = (
            ObstacleLayer(self.frame, obstacle_range_m, raytrace_range_m) if obstacle_layer else None
        )
        self.zones = ZoneCostLayer(zone_layer) if zone_layer is not None else None
        self.layers: list[Layer] = [self.static]
        """The layers merged into master, in order (inflation comes after them)."""
        if self.obstacles is not None:
            self.layers.append(self.obstacles)
        if self.zones is not None:
            self.layers.append(self.zones)
        self.robots = robots_layer
        if robots_layer is not None:
            if robots_layer.frame != self.frame:
                raise ValueError("the robots layer was built for another grid frame")
            self.layers.append(robots_layer)
        self.inflation = InflationLayer(inflation, grid.resolution)
        self.merged: NDArray[np.uint8] = self.static.costs.copy()
        """The layers merged, before inflation."""
        self.master: NDArray[np.uint8] = self.static.costs.copy()
        self.version = 0
        self._log: deque[tuple[int, Bounds]] = deque(maxlen=CHANGE_LOG)
        self.rebuild()

    @property
    def zone_layer(self) -> ZoneLayer | None:
        return self.zones.zone_layer if self.zones is not None else None

    @property
    def whole(self) -> Bounds:
        return Bounds(0, 0, self.frame.height, self.frame.width)

    # -- updates --------------------------------------------------------------------------------------------

    def rebuild(self) -> None:
        """Recompute every layer and the inflation over the whole map (start-up, and the reference for tests)."""
        whole = self.whole
        if self.zones is not None:
            self.zones.repaint(whole)
        for layer in self.layers:
            layer.take_bounds()
        self.merged = self.merge(whole)
        self.master = np.empty_like(self.merged)
        self.inflation.update_costs(self.master, whole, self.merged)
        self._changed(whole)

    def update_zones(self, now: float) -> Bounds | None:
        """Apply what changed in the zone layer (after ageing it to `now`); None if no cost changed."""
        if self.zones is None:
            return None
        self.zones.zone_layer.refresh(now)
        return self.update()

    def update_scan(self, scan: LaserScan) -> Bounds | None:
        """Feed a scan to the obstacle layer and apply it; None if no cost changed. Other robots the robots layer
        knows are left to it (not marked by the lidar)."""
        known = self.robots.known_discs() if self.robots is not None else []
        if self.obstacles is None or not self.obstacles.add_scan(scan, known):
            return None
        return self.update()

    def clear_obstacles_outside(self, x: float, y: float, size_m: float) -> Bounds | None:
        """Forget the lidar's marks outside a square of side `size_m` centred on (x, y) (move_base's
        clear_costmap_recovery on the obstacle layer); None if nothing changed."""
        if self.obstacles is None:
            return None
        row0, col0 = self.frame.world_to_cell(x - size_m / 2.0, y - size_m / 2.0)
        n = math.ceil(size_m / self.frame.resolution)
        if not self.obstacles.clear_outside(Bounds(row0, col0, row0 + n, col0 + n)):
            return None
        return self.update()

    def update(self) -> Bounds | None:
        """costmap_2d's updateMap: ask each layer what it changed, merge there, re-inflate around it.

        Only the cells whose merged cost really changed are re-inflated: most scans re-mark walls the static layer
        already holds and clear what they cleared before, and cost nothing.
        """
        changed = [
            b for b in (self._merge_changes(w) for layer in self.layers for w in layer.take_bounds()) if b
        ]
        if not changed:
            return None
        out: Bounds | None = None
        for w in changed:
            touched = self.inflation.grow(w, self.frame)
            self.inflation.update_costs(self.master, touched, self.merged)
            out = touched.union(out)
        assert out is not None
        self._changed(out)
        return out

    def merge(self, bounds: Bounds, layers: Sequence[Layer] | None = None) -> NDArray[np.uint8]:
        """The layers (all by default) merged in order inside `bounds`, before inflation."""
        out = np.full(bounds.shape, FREE_SPACE, dtype=np.uint8)
        for layer in self.layers if layers is None else layers:
            layer.update_costs(out, bounds)
        return out

    # -- queries --------------------------------------------------------------------------------------------

    def cost_at(self, x: float, y: float) -> int:
        """Master cost of the cell holding a world point; NO_INFORMATION outside the map."""
        row, col = self.frame.world_to_cell(x, y)
        if not self.frame.contains_cell(row, col):
            return NO_INFORMATION
        return int(self.master[row, col])

    def in_lethal(self, x: float, y: float) -> bool:
        """True when the robot's centre there would touch an obstacle (inscribed or lethal, not unknown)."""
        return INSCRIBED_INFLATED_OBSTACLE <= self.cost_at(x, y) <= LETHAL_OBSTACLE

    def changes_since(self, version: int) -> list[Bounds] | None:
        """The bounds master changed in after `version`, or None when they are no longer remembered."""
        if version == self.version:
            return []
        if not self._log or self._log[0][0] > version + 1:
            return None
        return [b for v, b in self._log if v > version]

    def local_window(
        self, pose: Pose, size_m: float, overlay: tuple[Bounds, NDArray[np.uint8]] | None = None
    ) -> tuple[NDArray[np.uint8], GridFrame]:
        """The rolling local costmap: a square of master centred on the robot, unknown beyond the map.

        `overlay` (bounds, costs) replaces master's costs in those bounds (the way out of a blocked zone)."""
        frame = self.frame
        n = max(math.ceil(size_m / frame.resolution), 1)
        row, col = frame.world_to_cell(pose[0], pose[1])
        r0, c0 = row - n // 2, col - n // 2
        out = np.full((n, n), NO_INFORMATION, dtype=np.uint8)
        here = Bounds(r0, c0, r0 + n, c0 + n)
        src = here.grow(0, frame)
        if not src.empty:
            out[src.within(here)] = self.master[src.rows, src.cols]
        if overlay is not None:
            bounds, costs = overlay
            common = bounds.intersection(src)
            if not common.empty:
                out[common.within(here)] = costs[common.within(bounds)]
        local = GridFrame(
            n,
            n,
            frame.resolution,
            frame.origin_x + c0 * frame.resolution,
            frame.origin_y + r0 * frame.resolution,
        )
        return out, local

    # -- internals ------------------------------------------------------------------------------------------

    def _merge_changes(self, window: Bounds) -> Bounds | None:
        """Merge the layers again in `window`; the bounds of the cells whose merged cost changed, or None."""
        window = window.grow(0, self.frame)
        if window.empty:
            return None
        new = self.merge(window)
        diff = new != self.merged[window.rows, window.cols]
        rows = np.flatnonzero(diff.any(axis=1))
        if len(rows) == 0:
            return None
        self.merged[window.rows, window.cols] = new
        cols = np.flatnonzero(diff.any(axis=0))
        return Bounds(
            window.row0 + int(rows[0]),
            window.col0 + int(cols[0]),
            window.row0 + int(rows[-1]) + 1,
            window.col0 + int(cols[-1]) + 1,
        )

    def _changed(self, b: Bounds) -> None:
        self.version += 1
        self._log.append((self.version, b))
