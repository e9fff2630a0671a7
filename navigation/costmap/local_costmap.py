"""The local costmap the controller reads: costmap_2d's rolling-window costmap, with its own layers, size and rate.

move_base (and Nav2) run two costmaps: the global one the planner reads and a local one the controller reads, a
square window that moves with the robot (`rolling_window`), built from its own `plugins` list and updated at its
own `update_frequency` (ROBOTIS' TurtleBot3: obstacle and inflation layers, 3 x 3 m, 10 Hz). Its size and rate are
what the paper reduces in `full`, so the work here scales with them: every update re-homes the window on the
robot, feeds the newest scan to its own obstacle layer (marked and cleared inside the window only; marks that
leave the window are forgotten, as costmap_2d's updateOrigin forgets them) and merges and inflates the window
whole. `static_layer` and `robots_layer` read the global costmap's layers inside the window (the same map and the
same robot statuses both of move_base's costmaps subscribe to). The zone layer is not offered: a blocked zone
reaches the controller through the global plan (as with the ROS bridge, docs/ros.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from wsnav.navigation.backend import LaserScan, Pose
from wsnav.navigation.costmap.inflation import InflationParams, inflate
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap, check_plugins
from wsnav.navigation.costmap.layers import ObstacleLayer
from wsnav.zones.cost_values import FREE_SPACE, NO_INFORMATION
from wsnav.zones.geometry import Bounds, GridFrame

LOCAL_PLUGINS = ("static_layer", "obstacle_layer", "robots_layer", "inflation_layer")
"""The layers a local costmap's `plugins` list may name, each at most once, in the order they are called;
`inflation_layer` is required."""


def check_local_plugins(plugins: Sequence[str]) -> None:
    """Refuse, in one line, a local `plugins` list that names an unknown layer (the zone layer among them), one
    twice, or lacks the inflation layer."""
    if "zone_layer" in plugins:
        raise ValueError(
            "the local costmap takes no zone_layer: a blocked zone reaches the controller through the global plan"
        )
    check_plugins(plugins, LOCAL_PLUGINS, ("inflation_layer",), "local costmap")


class LocalCostmap:
    """A rolling window of `size_m` centred on the robot at its last `update`, its layers named by `plugins`."""

    def __init__(
        self,
        global_costmap: LayeredCostmap,
        size_m: float,
        inflation: InflationParams,
        plugins: Sequence[str],
        *,
        obstacle_range_m: float = 3.0,
        raytrace_range_m: float = 3.5,
    ) -> None:
        check_local_plugins(plugins)
        self.plugins = list(plugins)
        self.map_frame = global_costmap.frame
        self.inflation = inflation
        self.size = max(math.ceil(size_m / self.map_frame.resolution), 1)
        """Cells on a side."""
        self._static = global_costmap.static if "static_layer" in plugins else None
        self._robots = global_costmap.robots if "robots_layer" in plugins else None
        self._corner: tuple[int, int] | None = None
        """The window's first (row, col) in the map's cells; None before the first update."""
        self.frame = self._frame_at(0, 0)
        self.obstacles = (
            ObstacleLayer(self.frame, obstacle_range_m, raytrace_range_m)
            if "obstacle_layer" in plugins
            else None
        )
        self.costs: NDArray[np.uint8] = np.full((self.size, self.size), FREE_SPACE, dtype=np.uint8)
        """The window's merged, inflated costs (what the controller reads)."""
        self.updates = 0

    def _frame_at(self, row0: int, col0: int) -> GridFrame:
        f = self.map_frame
        return GridFrame(
            self.size,
            self.size,
            f.resolution,
            f.origin_x + col0 * f.resolution,
            f.origin_y + row0 * f.resolution,
        )

    def update(self, pose: Pose, scan: LaserScan | None) -> None:
        """One update cycle: the window re-homed on `pose`, the newest scan marked and cleared in it, the layers
        merged and inflated over it."""
        row, col = self.map_frame.world_to_cell(pose[0], pose[1])
        corner = (row - self.size // 2, col - self.size // 2)
        if corner != self._corner:
            self._corner = corner
            self.frame = self._frame_at(*corner)
            if self.obstacles is not None:
                self.obstacles.move(self.frame)
        if self.obstacles is not None and scan is not None:
            known = self._robots.known_discs() if self._robots is not None else []
            self.obstacles.add_scan(scan, known)
        self._compose()
        self.updates += 1

    def window(self) -> tuple[NDArray[np.uint8], GridFrame]:
        """The costs and where they lie (what the navigator hands the controller)."""
        return self.costs, self.frame

    def clear_except_region(self, x: float, y: float, size_m: float) -> None:
        """Forget the obstacle marks outside a square of side `size_m` centred on (x, y) (clear_costmap_recovery,
        which clears move_base's local costmap as well as its global one)."""
        if self.obstacles is None or self._corner is None:
            return
        row0, col0 = self.frame.world_to_cell(x - size_m / 2.0, y - size_m / 2.0)
        n = math.ceil(size_m / self.frame.resolution)
        if self.obstacles.clear(Bounds(row0, col0, row0 + n, col0 + n), outside=True):
            self._compose()

    def _compose(self) -> None:
        """The layers in their order over the window, each by its own merge rule; inflation over the whole window
        from the layers before it."""
        assert self._corner is not None
        r0, c0 = self._corner
        here = Bounds(r0, c0, r0 + self.size, c0 + self.size)
        on_map = here.grow(0, self.map_frame)
        inner = on_map.within(here) if not on_map.empty else None
        out = np.full((self.size, self.size), FREE_SPACE, dtype=np.uint8)
        for name in self.plugins:
            if name == "static_layer" and self._static is not None:
                out[...] = NO_INFORMATION  # beyond the map, as the global costmap's window had it
                if inner is not None:
                    self._static.update_costs(out[inner], on_map)
            elif name == "robots_layer" and self._robots is not None and inner is not None:
                self._robots.update_costs(out[inner], on_map)
            elif name == "obstacle_layer" and self.obstacles is not None:
                self.obstacles.update_costs(out, Bounds(0, 0, self.size, self.size))
            elif name == "inflation_layer":
                out = inflate(out, self.map_frame.resolution, self.inflation)
        self.costs = out
