"""The robot's layered costmap, with costmap_2d's semantics: a list of layers named by a `plugins` list as in
Nav2 (by default static -> obstacle -> zone -> robots -> inflation), each called the same way.

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
from typing import TypeVar

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
from wsnav.zones.zone_rule import ZoneRule

__all__ = ["LAYER_PLUGINS", "Bounds", "LayeredCostmap", "check_plugins"]

L = TypeVar("L", bound=Layer)

CHANGE_LOG = 64
"""Updates remembered for `changes_since`; a reader further behind recomputes from master whole."""


LAYER_PLUGINS = ("static_layer", "obstacle_layer", "zone_layer", "robots_layer", "inflation_layer")
"""The layers a configuration may name in its `plugins` list (Nav2's costmap `plugins` parameter), each at most
once, in the order they are called; `static_layer` and `inflation_layer` are required."""


class LayeredCostmap:
    """One list of layers, built from a `plugins` list of names (by default static, obstacle (lidar), zone (WSN)
    and, in a fleet, robots, then inflation), each called the same way."""

    def __init__(
        self,
        grid: OccupancyGrid,
        inflation: InflationParams,
        *,
        zone_layer: ZoneRule | None = None,
        obstacle_layer: bool = True,
        obstacle_range_m: float = 3.0,
        raytrace_range_m: float = 3.5,
        robots_layer: RobotsLayer | None = None,
        plugins: Sequence[str] | None = None,
    ) -> None:
        """`robots_layer`: the other robots' footprints (a fleet). `plugins`: the layers by name, in order
        (LAYER_PLUGINS); by default every layer given: static, obstacle (unless `obstacle_layer` is false), zone (if
        `zone_layer`), robots (if `robots_layer`), inflation. A named `robots_layer` with no robots to follow (a
        site with one robot) is left out."""
        self.frame = GridFrame.of_grid(grid)
        if zone_layer is not None and zone_layer.frame != self.frame:
            raise ValueError("the zone layer was built for another grid frame")
        if robots_layer is not None and robots_layer.frame != self.frame:
            raise ValueError("the robots layer was built for another grid frame")
        if plugins is None:
            plugins = [
                name
                for name, present in zip(
                    LAYER_PLUGINS,
                    (True, obstacle_layer, zone_layer is not None, robots_layer is not None, True),
                    strict=True,
                )
                if present
            ]
        check_plugins(plugins)
        if "zone_layer" in plugins and zone_layer is None:
            raise ValueError("plugins name zone_layer, but no zone layer was given")
        self.plugins: list[str] = list(plugins)
        """The names of the layers, in order (what built `layers`)."""
        self.layers: list[Layer] = []
        """The layers, in the order they are called."""
        for name in plugins:
            match name:
                case "static_layer":
                    self.layers.append(StaticLayer(grid))
                case "obstacle_layer":
                    self.layers.append(ObstacleLayer(self.frame, obstacle_range_m, raytrace_range_m))
                case "zone_layer":
                    assert zone_layer is not None
                    self.layers.append(ZoneCostLayer(zone_layer))
                case "robots_layer":
                    if robots_layer is not None:
                        self.layers.append(robots_layer)
                case "inflation_layer":
                    self.layers.append(InflationLayer(inflation, self.frame, self))
        self.master: NDArray[np.uint8] = self.static.costs.copy()
        self.version = 0
        self._log: deque[tuple[int, Bounds]] = deque(maxlen=CHANGE_LOG)
        self.rebuild()

    def _layer(self, kind: type[L]) -> L | None:
        return next((layer for layer in self.layers if isinstance(layer, kind)), None)

    @property
    def static(self) -> StaticLayer:
        """The map's layer (always in the list)."""
        layer = self._layer(StaticLayer)
        assert layer is not None
        return layer

    @property
    def obstacles(self) -> ObstacleLayer | None:
        """The lidar's layer, if in the list."""
        return self._layer(ObstacleLayer)

    @property
    def zones(self) -> ZoneCostLayer | None:
        """The WSN zone layer's costs, if in the list."""
        return self._layer(ZoneCostLayer)

    @property
    def robots(self) -> RobotsLayer | None:
        """The other robots' footprints, if in the list."""
        return self._layer(RobotsLayer)

    @property
    def inflation(self) -> InflationLayer:
        """The inflation layer (always in the list)."""
        layer = self._layer(InflationLayer)
        assert layer is not None
        return layer

    @property
    def zone_layer(self) -> ZoneRule | None:
        zones = self.zones
        return zones.zone_layer if zones is not None else None

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
        zone_layer = self.zone_layer
        if zone_layer is None:
            return None
        zone_layer.refresh(now)
        return self.update()

    def update_scan(self, scan: LaserScan) -> Bounds | None:
        """Feed a scan to the obstacle layer and apply it; None if no cost changed. Other robots the robots layer
        knows are left to it (not marked by the lidar)."""
        robots, obstacles = self.robots, self.obstacles
        known = robots.known_discs() if robots is not None else []
        if obstacles is None or not obstacles.add_scan(scan, known):
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


def check_plugins(
    plugins: Sequence[str],
    known: Sequence[str] = LAYER_PLUGINS,
    required: Sequence[str] = ("static_layer", "inflation_layer"),
    what: str = "costmap",
) -> None:
    """Refuse, in one line, a `plugins` list that names an unknown layer, one twice, or lacks a required one (the
    global costmap's by default; the local costmap passes its own)."""
    unknown = [p for p in plugins if p not in known]
    if unknown:
        raise ValueError(f"unknown {what} plugin {unknown[0]!r} (known: {', '.join(known)})")
    twice = [p for p in known if list(plugins).count(p) > 1]
    if twice:
        raise ValueError(f"{what} plugin {twice[0]!r} named twice")
    for layer in required:
        if layer not in plugins:
            raise ValueError(f"{what} plugins lack {layer!r}")
