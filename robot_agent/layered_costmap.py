"""The robot's layered costmap, with costmap_2d's semantics: static -> obstacle -> zone -> inflation.

Layers are merged by numeric maximum (so NO_INFORMATION, 255, stays unknown) and then inflated with
costmap_2d's formula (robot_agent.inflation). Every update touches only the bounds that changed: a zone change
repaints the zone's window, and re-inflates that window grown by the inflation radius, computing distances on
a window grown once more (a lethal cell farther than the radius cannot change a cell's cost), so the result is
cell for cell what a whole-map recomputation gives (`rebuild`), at a fraction of the cost on big maps.

A robot that stands in a zone which becomes blocked must be able to drive out of it: `escape_view` gives master
around those zones with their own cost passable (high), walls and the lidar's marks unchanged; it is computed in
the zones' neighbourhood only, and only while the robot's footprint touches one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt

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

__all__ = ["ESCAPE_COST", "Bounds", "EscapeView", "LayeredCostmap"]

ESCAPE_COST = 200
"""What a cell made lethal or inscribed only by a zone the robot stands in costs in an escape view: passable, but
dear enough that the controller creeps (its speed falls with cost) while it leaves."""
EXIT_MARGIN_CELLS = 2
"""An exit lies this many cells beyond where the footprint stops touching the zones: a robot that stopped near
an exit (within the controller's goal tolerance) is out, not on the edge."""


@dataclass(frozen=True)
class EscapeView:
    """Master around some blocked zones with their zone cost relaxed, for leaving them.

    Inside `bounds` (the zones grown by the inflation's reach), `costs` is master where every cell that only those
    zones made lethal or inscribed costs `ESCAPE_COST` (or its inflation from what remains, if higher); walls,
    the lidar's marks, other zones and everything outside `bounds` keep master's cost. `exits` marks the cells of
    `bounds` where the robot's footprint is clear of the zones (by `zones_at`'s rule, plus a margin).
    """

    zones: tuple[str, ...]
    version: int
    """Master's version it was computed from."""
    bounds: Bounds
    costs: NDArray[np.uint8]
    exits: NDArray[np.bool_]


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
        self._touch = math.ceil(inflation.inscribed_radius / grid.resolution)
        """`zones_at`'s radius in cells: a zone cell this near the robot's cell touches its footprint."""
        self._escape: EscapeView | None = None
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
        r = self._touch
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

    def local_window(
        self, pose: Pose, size_m: float, view: EscapeView | None = None
    ) -> tuple[NDArray[np.uint8], GridFrame]:
        """The rolling local costmap: a square of master (or of an escape view) centred on the robot, unknown
        beyond the map."""
        frame = self.frame
        n = max(math.ceil(size_m / frame.resolution), 1)
        row, col = frame.world_to_cell(pose[0], pose[1])
        r0, c0 = row - n // 2, col - n // 2
        out = np.full((n, n), NO_INFORMATION, dtype=np.uint8)
        here = Bounds(r0, c0, r0 + n, c0 + n)
        src = here.grow(0, frame)
        if not src.empty:
            out[src.within(here)] = self.master[src.rows, src.cols]
        if view is not None:
            common = view.bounds.intersection(src)
            if not common.empty:
                out[common.within(here)] = view.costs[common.within(view.bounds)]
        local = GridFrame(
            n,
            n,
            frame.resolution,
            frame.origin_x + c0 * frame.resolution,
            frame.origin_y + r0 * frame.resolution,
        )
        return out, local

    def escape_view(self, zones: Sequence[str]) -> EscapeView | None:
        """Master with `zones` (names as `zones_at` gives them) passable, around them only; None if none is known.

        The zones' neighbourhood is merged again without them and re-inflated there, so walls and what the lidar
        sees stay lethal and inscribed; kept until master or the zones change (the controller asks every tick).
        """
        key = tuple(sorted(set(zones)))
        cached = self._escape
        if cached is not None and cached.zones == key and cached.version == self.version:
            return cached
        windows = [w for w in (self._area(z) for z in key) if w is not None and not w.empty]
        if self.zone_layer is None or not windows:
            return None
        frame = self.frame
        area: Bounds | None = None
        for w in windows:
            area = Bounds.of_window(w).union(area)
        assert area is not None
        bounds = area.grow(max(self._reach, self._touch + EXIT_MARGIN_CELLS + 2), frame)
        source = bounds.grow(self._reach, frame)
        merged = self._merged(source, self.zone_layer.paint(source, exclude=key))
        without = inflate(merged, frame.resolution, self.inflation)[bounds.within(source)]
        costs = self.master[bounds.rows, bounds.cols].copy()
        relax = (costs >= INSCRIBED_INFLATED_OBSTACLE) & (without < INSCRIBED_INFLATED_OBSTACLE)
        costs[relax] = np.maximum(without[relax], np.uint8(ESCAPE_COST))
        inside = np.zeros(bounds.shape, dtype=bool)
        for w in windows:
            common = Bounds.of_window(w).intersection(bounds)
            inside[common.within(bounds)] |= w.mask[common.within(Bounds.of_window(w))]
        dist = np.asarray(distance_transform_edt(~inside), dtype=np.float64)
        exits = (dist > self._touch + EXIT_MARGIN_CELLS) & (costs < INSCRIBED_INFLATED_OBSTACLE)
        self._escape = EscapeView(key, self.version, bounds, costs, exits)
        return self._escape

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

    def _area(self, name: str) -> CellWindow | None:
        """The cells of a blocked zone, or of an operator polygon block named `operator/<id>`."""
        layer = self.zone_layer
        if layer is None:
            return None
        if name.startswith("operator/"):
            return layer.block_window(name.removeprefix("operator/"))
        if name in layer.zone_costs():
            return layer.zone_window(name)
        return None

    def _set_cells(self, xs: NDArray[np.float64], ys: NDArray[np.float64], value: bool) -> None:
        assert self.obstacles is not None
        frame = self.frame
        cols = np.floor((xs - frame.origin_x) / frame.resolution).astype(np.intp)
        rows = np.floor((ys - frame.origin_y) / frame.resolution).astype(np.intp)
        inside = (rows >= 0) & (rows < frame.height) & (cols >= 0) & (cols < frame.width)
        self.obstacles[rows[inside], cols[inside]] = value

    def _merged(self, b: Bounds, zones: NDArray[np.uint8] | None = None) -> NDArray[np.uint8]:
        """The layers merged by maximum in `b`; `zones` replaces the zone layer's costs there if given."""
        zone_costs = self.zones[b.rows, b.cols] if zones is None else zones
        merged = np.maximum(self.static[b.rows, b.cols], zone_costs)
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
