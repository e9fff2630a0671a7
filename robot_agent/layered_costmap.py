"""The robot's layered costmap, with costmap_2d's semantics: static -> obstacle -> zone -> inflation.

Layers are merged by numeric maximum (so NO_INFORMATION, 255, stays unknown) and then inflated with
costmap_2d's formula (robot_agent.inflation). Every update touches only the bounds that changed: a zone change
repaints the zone's window, and re-inflates that window grown by the inflation radius, computing distances on
a window grown once more (a lethal cell farther than the radius cannot change a cell's cost), so the result is
cell for cell what a whole-map recomputation gives (`rebuild`), at a fraction of the cost on big maps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from robot_agent.backend import LaserScan, Pose
from robot_agent.global_planner import PlannerParams, weight_lut
from robot_agent.inflation import (
    INSCRIBED_INFLATED_OBSTACLE,
    LETHAL_OBSTACLE,
    NO_INFORMATION,
    InflationParams,
    inflate,
    static_layer,
)
from robot_agent.zone_geometry import Bounds, CellWindow, GridFrame
from robot_agent.zone_layer import ZoneLayer
from schemas.ros_map import OccupancyGrid

__all__ = ["Bounds", "LayeredCostmap"]


class LayeredCostmap:
    """Static, obstacle (lidar) and zone (WSN) layers merged by maximum, then inflated; updated in bounds."""

    def __init__(
        self,
        grid: OccupancyGrid,
        inflation: InflationParams,
        *,
        zone_layer: ZoneLayer | None = None,
        obstacle_layer: bool = True,
        obstacle_range_m: float = 3.0,
        raytrace_range_m: float = 3.5,
    ) -> None:
        self.frame = GridFrame(grid.width, grid.height, grid.resolution, grid.origin[0], grid.origin[1])
        if zone_layer is not None and zone_layer.frame != self.frame:
            raise ValueError("the zone layer was built for another grid frame")
        self.inflation = inflation
        self.zone_layer = zone_layer
        self.obstacle_range_m = obstacle_range_m
        self.raytrace_range_m = raytrace_range_m
        self.static: NDArray[np.uint8] = static_layer(grid)
        self.obstacles: NDArray[np.bool_] | None = (
            np.zeros(self.static.shape, dtype=bool) if obstacle_layer else None
        )
        self.zones: NDArray[np.uint8] = np.zeros(self.static.shape, dtype=np.uint8)
        self.merged: NDArray[np.uint8] = self.static.copy()
        """The layers merged by maximum, before inflation."""
        self.master: NDArray[np.uint8] = self.static.copy()
        self.version = 0
        self._reach = math.ceil(inflation.inflation_radius / grid.resolution) + 1
        """Cells beyond which a lethal cell cannot change a cell's inflated cost."""
        self._weights: dict[PlannerParams, NDArray[np.float32]] = {}
        self._weights_dirty: dict[PlannerParams, list[Bounds]] = {}
        self._last_scan: LaserScan | None = None
        self.rebuild()

    @property
    def whole(self) -> Bounds:
        return Bounds(0, 0, self.frame.height, self.frame.width)

    # -- updates --------------------------------------------------------------------------------------------

    def rebuild(self) -> None:
        """Recompute every layer and the inflation over the whole map (start-up, and the reference for tests)."""
        whole = self.whole
        if self.zone_layer is not None:
            self.zone_layer.take_changes()
            self.zones = self.zone_layer.paint(whole)
        self._merge(whole)
        self.master = inflate(self.merged, self.frame.resolution, self.inflation)
        self._changed(whole)

    def update_zones(self, now: float) -> Bounds | None:
        """Apply what changed in the zone layer (after ageing it to `now`); None if no cost changed."""
        if self.zone_layer is None:
            return None
        self.zone_layer.refresh(now)
        windows = self.zone_layer.take_changes()
        if not windows:
            return None
        before = [self.zones[w.rows, w.cols].copy() for w in windows]
        for w in windows:
            self.zones[w.rows, w.cols] = self.zone_layer.paint(w)
        touched = [
            w
            for w, old in zip(windows, before, strict=True)
            if not np.array_equal(old, self.zones[w.rows, w.cols])
        ]
        return self._apply(touched)

    def update_scan(self, scan: LaserScan) -> Bounds | None:
        """Obstacle layer: clear cells along each beam, then mark its hit; None if no cell changed.

        Beams with no return (+inf) clear up to the raytrace range (costmap_2d's `inf_is_valid`); hits are
        marked up to the obstacle range. Only the scan's window is touched. The costmap's rate may be above the
        lidar's: applying the sweep already applied again would change nothing (each cell it touches ends cleared
        or marked whatever it was), so it is skipped.
        """
        if self.obstacles is None or scan is self._last_scan:
            return None
        self._last_scan = scan
        frame = self.frame
        res = frame.resolution
        x, y, yaw = scan.pose
        ranges = np.asarray(scan.ranges, dtype=np.float64)
        angles = yaw + scan.angle_min + scan.angle_increment * np.arange(len(ranges))
        usable = ~np.isnan(ranges) & (ranges >= scan.range_min)
        hit = usable & np.isfinite(ranges) & (ranges < scan.range_max) & (ranges <= self.obstacle_range_m)
        clear_len = np.minimum(np.where(np.isfinite(ranges), ranges, np.inf), self.raytrace_range_m)
        clear_len = np.where(usable, clear_len, 0.0)
        reach = math.ceil(max(self.raytrace_range_m, self.obstacle_range_m) / res) + 2
        row, col = frame.world_to_cell(x, y)
        window = Bounds(row - reach, col - reach, row + reach + 1, col + reach + 1).grow(0, frame)
        if window.empty:
            return None
        obstacles = self.obstacles
        before = obstacles[window.rows, window.cols].copy()
        # Clearing: sample each beam every half cell, stopping a cell short of its end.
        step = res / 2.0
        n = math.ceil(self.raytrace_range_m / step) + 1
        s = np.arange(n, dtype=np.float64) * step
        cos, sin = np.cos(angles), np.sin(angles)
        along = s[None, :] < (clear_len[:, None] - res)
        px = x + cos[:, None] * s[None, :]
        py = y + sin[:, None] * s[None, :]
        self._set_cells(px[along], py[along], False)
        # Marking: the cell of each hit within the obstacle range.
        hx = x + cos[hit] * ranges[hit]
        hy = y + sin[hit] * ranges[hit]
        self._set_cells(hx, hy, True)
        if np.array_equal(before, obstacles[window.rows, window.cols]):
            return None
        changed = self._merged_changes(window)
        return self._apply([changed]) if changed is not None else None

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

    def zones_at(self, x: float, y: float) -> list[str]:
        """Blocked zones (and operator polygon blocks, as `operator/<id>`) within the robot's radius of a point."""
        if self.zone_layer is None:
            return []
        frame = self.frame
        row, col = frame.world_to_cell(x, y)
        r = math.ceil(self.inflation.inscribed_radius / frame.resolution)
        rows, cols = np.ogrid[-r : r + 1, -r : r + 1]
        disk = rows * rows + cols * cols <= r * r
        here = Bounds(row - r, col - r, row + r + 1, col + r + 1)
        out = [
            z for z in self.zone_layer.blocked_zones() if _touches(self.zone_layer.zone_window(z), here, disk)
        ]
        for block_id in self.zone_layer.active_blocks():
            window = self.zone_layer.block_window(block_id)
            if window is not None and _touches(window, here, disk):
                out.append(f"operator/{block_id}")
        return out

    def local_window(self, pose: Pose, size_m: float) -> tuple[NDArray[np.uint8], GridFrame]:
        """The rolling local costmap: a square of master centred on the robot, unknown beyond the map."""
        frame = self.frame
        n = max(math.ceil(size_m / frame.resolution), 1)
        row, col = frame.world_to_cell(pose[0], pose[1])
        r0, c0 = row - n // 2, col - n // 2
        out = np.full((n, n), NO_INFORMATION, dtype=np.uint8)
        src = Bounds(r0, c0, r0 + n, c0 + n).grow(0, frame)
        if not src.empty:
            out[src.row0 - r0 : src.row1 - r0, src.col0 - c0 : src.col1 - c0] = self.master[
                src.rows, src.cols
            ]
        local = GridFrame(
            n,
            n,
            frame.resolution,
            frame.origin_x + c0 * frame.resolution,
            frame.origin_y + r0 * frame.resolution,
        )
        return out, local

    def planner_weights(self, params: PlannerParams | None = None) -> NDArray[np.float32]:
        """A* weights of master, kept up to date in the changed bounds only (pass to plan_path's `weights`)."""
        p = params or PlannerParams()
        lut = weight_lut(p)
        cached = self._weights.get(p)
        if cached is None:
            cached = lut[self.master]
            self._weights[p] = cached
        else:
            for b in self._weights_dirty.get(p, []):
                cached[b.rows, b.cols] = lut[self.master[b.rows, b.cols]]
        self._weights_dirty[p] = []
        return cached

    # -- internals ------------------------------------------------------------------------------------------

    def _set_cells(self, xs: NDArray[np.float64], ys: NDArray[np.float64], value: bool) -> None:
        assert self.obstacles is not None
        frame = self.frame
        cols = np.floor((xs - frame.origin_x) / frame.resolution).astype(np.intp)
        rows = np.floor((ys - frame.origin_y) / frame.resolution).astype(np.intp)
        inside = (rows >= 0) & (rows < frame.height) & (cols >= 0) & (cols < frame.width)
        self.obstacles[rows[inside], cols[inside]] = value

    def _merged(self, b: Bounds) -> NDArray[np.uint8]:
        merged = np.maximum(self.static[b.rows, b.cols], self.zones[b.rows, b.cols])
        if self.obstacles is not None:
            np.maximum(
                merged,
                np.where(self.obstacles[b.rows, b.cols], np.uint8(LETHAL_OBSTACLE), np.uint8(0)),
                out=merged,
            )
        return merged

    def _merge(self, b: Bounds) -> None:
        self.merged[b.rows, b.cols] = self._merged(b)

    def _merged_changes(self, window: Bounds) -> Bounds | None:
        """The bounds of the cells in `window` whose merged cost the layers now change, or None.

        Most scans only re-mark walls the static layer already holds and clear what they cleared before, so
        most of them change nothing and cost no re-inflation; the rest re-inflate around what changed only.
        """
        diff = self._merged(window) != self.merged[window.rows, window.cols]
        rows = np.flatnonzero(diff.any(axis=1))
        if len(rows) == 0:
            return None
        cols = np.flatnonzero(diff.any(axis=0))
        return Bounds(
            window.row0 + int(rows[0]),
            window.col0 + int(cols[0]),
            window.row0 + int(rows[-1]) + 1,
            window.col0 + int(cols[-1]) + 1,
        )

    def _apply(self, windows: Sequence[Bounds]) -> Bounds | None:
        """Merge the layers in each changed window, then re-inflate the window's neighbourhood."""
        if not windows:
            return None
        for w in windows:
            self._merge(w)
        out: Bounds | None = None
        for w in windows:
            touched = w.grow(self._reach, self.frame)
            source = touched.grow(self._reach, self.frame)
            inflated = inflate(self.merged[source.rows, source.cols], self.frame.resolution, self.inflation)
            self.master[touched.rows, touched.cols] = inflated[touched.within(source)]
            out = touched.union(out)
        assert out is not None
        self._changed(out)
        return out

    def _changed(self, b: Bounds) -> None:
        self.version += 1
        for dirty in self._weights_dirty.values():
            dirty.append(b)


def _touches(window: CellWindow, here: Bounds, disk: NDArray[np.bool_]) -> bool:
    """True if any cell of `window` lies in the disk that fills `here`."""
    if window.empty:
        return False
    area = Bounds.of_window(window)
    common = area.intersection(here)
    if common.empty:
        return False
    return bool((window.mask[common.within(area)] & disk[common.within(here)]).any())
