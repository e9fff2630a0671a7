"""The robot's layered costmap, with costmap_2d's semantics: a list of layers, static -> obstacle -> zone ->
robots -> inflation, each called the same way.

The layers (wsnav.navigation.costmap.layers) are called in their order: `update_bounds` gathers the windows to
recompute (each layer adds what it changed; the inflation layer keeps the cells whose merged cost really changed
and grows them by its reach), then `update_costs` writes each window of master, each layer by its rule
(wsnav.navigation.costmap.merge). Every update touches only those windows, so the result is cell for cell what
a whole-map recomputation gives (`rebuild`), at a fraction of the cost on big maps. `clear` asks every layer to
forget what it holds in a window, for the recoveries.
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
    """Static, obstacle (lidar), zone (WSN) and, in a fleet, robots layers, then inflation: one list of layers."""

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
        if robots_layer is not None and robots_layer.frame != self.frame:
            raise ValueError("the robots layer was built for another grid frame")
        self.static = StaticLayer(grid)
        self.obstacles = (
            ObstacleLayer(self.frame, obstacle_range_m, raytrace_range_m) if obstacle_layer else None
        )
        self.zones = ZoneCostLayer(zone_layer) if zone_layer is not None else None
        self.robots = robots_layer
        self.inflation = InflationLayer(inflation, self.frame, self)
        self.layers: list[Layer] = [
            layer
            for layer in (self.static, self.obstacles, self.zones, self.robots, self.inflation)
            if layer is not None
        ]
        """The layers, in the order they are called; the named ones above are handles into it."""
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
        """Recompute every layer and master over the whole map (start-up, and the reference for tests)."""
        for layer in self.layers:
            layer.rebuild()
        self.master = self.merge(self.whole)
        self._changed(self.whole)

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

    def clear(self, window: Bounds, *, outside: bool = False) -> Bounds | None:
        """Every layer forgets what it holds in the cell window (outside it, with `outside`), if it holds
        anything a recovery may clear, and master follows (costmap_2d's clearArea over the layers); None if
        nothing changed."""
        cleared = [layer.clear(window, outside=outside) for layer in self.layers]
        if not any(cleared):
            return None
        return self.update()

    def clear_except_region(self, x: float, y: float, size_m: float) -> Bounds | None:
        """`clear` outside a square of side `size_m` centred on (x, y) (move_base's clear_costmap_recovery,
        Nav2's clearExceptRegion); None if nothing changed."""
        row0, col0 = self.frame.world_to_cell(x - size_m / 2.0, y - size_m / 2.0)
        n = math.ceil(size_m / self.frame.resolution)
        return self.clear(Bounds(row0, col0, row0 + n, col0 + n), outside=True)

    def update(self) -> Bounds | None:
        """costmap_2d's updateMap: ask each layer in turn for the windows to recompute, then write master there.

        None (and no new version) when no window is left: a change the merge hides costs nothing downstream.
        """
        windows: list[Bounds] = []
        for layer in self.layers:
            windows = layer.update_bounds(windows)
        windows = [w for w in (w.grow(0, self.frame) for w in windows) if not w.empty]
        if not windows:
            return None
        out: Bounds | None = None
        for w in windows:
            self.master[w.rows, w.cols] = self.merge(w)
            out = w.union(out)
        assert out is not None
        self._changed(out)
        return out

    def merge(self, bounds: Bounds, layers: Sequence[Layer] | None = None) -> NDArray[np.uint8]:
        """The layers (all by default) applied in order inside `bounds`, each by its rule, from free space."""
        out = np.full(bounds.shape, FREE_SPACE, dtype=np.uint8)
        for layer in self.layers if layers is None else layers:
            layer.update_costs(out, bounds)
        return out

    def layers_below(self, layer: Layer) -> list[Layer]:
        """The layers before `layer` in the list."""
        return self.layers[: self.layers.index(layer)]

    def merge_below(self, layer: Layer, bounds: Bounds) -> NDArray[np.uint8]:
        """The layers before `layer` merged inside `bounds` (what the inflation layer inflates)."""
        return self.merge(bounds, self.layers_below(layer))

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

    def _changed(self, b: Bounds) -> None:
        self.version += 1
        self._log.append((self.version, b))
