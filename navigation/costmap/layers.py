"""The costmap's layers, each with its own grid and its own rule for entering master (costmap_2d's `Layer`).

A layer reports the windows it changed since it was last asked (costmap_2d's `updateBounds`) and combines its
costs into a master window (`updateCosts`). The stack (wsnav.navigation.costmap.layered_costmap) merges static, obstacle and
zone layers in that order, then hands the result to the inflation layer. The rules are costmap_2d's: the static
layer overwrites (StaticLayer without `use_maximum`), the others merge by `update_with_max`, in which a layer's
NO_INFORMATION never overrides what master knows. Adding a layer means writing one class
with these two methods and putting it in the stack's list; nothing else changes.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numba import njit
from numpy.typing import NDArray

from wsnav.navigation.backend import LaserScan, Pose
from wsnav.navigation.costmap.inflation import InflationParams, inflate, inflation_reach, static_layer
from wsnav.schemas.ros_map import OccupancyGrid
from wsnav.zones.cost_values import LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import Bounds, GridFrame
from wsnav.zones.zone_layer import BlockedArea, ZoneLayer

Costs = NDArray[np.uint8]


def update_with_max(master: Costs, costs: Costs) -> None:
    """costmap_2d's CostmapLayer::updateWithMax on a window: the layer's cost where master's is NO_INFORMATION or
    lower, and never the layer's NO_INFORMATION (so a stale zone read as unknown leaves walls lethal)."""
    take = (costs != NO_INFORMATION) & ((master == NO_INFORMATION) | (master < costs))
    np.copyto(master, costs, where=take)


class Layer(Protocol):
    """One layer of the stack: what it changed, and how its costs enter master."""

    def take_bounds(self) -> list[Bounds]:
        """The cell windows this layer changed since the last call (costmap_2d's updateBounds)."""
        ...

    def update_costs(self, master: Costs, bounds: Bounds) -> None:
        """Combine this layer's costs into `master`, an array covering `bounds` (costmap_2d's updateCosts)."""
        ...


class StaticLayer:
    """The site's map: walls lethal, unknown space unknown; never changes after start-up. The first layer: it
    overwrites master, unknown included (costmap_2d's updateWithTrueOverwrite, StaticLayer's default)."""

    def __init__(self, grid: OccupancyGrid) -> None:
        self.costs: Costs = static_layer(grid)

    def take_bounds(self) -> list[Bounds]:
        return []

    def update_costs(self, master: Costs, bounds: Bounds) -> None:
        master[...] = self.costs[bounds.rows, bounds.cols]


class ObstacleLayer:
    """What the lidar sees: each scan clears the cells along its beams and marks the cells of its hits lethal.

    Beams with no return (+inf) clear up to the raytrace range (costmap_2d's `inf_is_valid`); hits are marked up
    to the obstacle range. Only the scan's window is touched. It enters master by `update_with_max` with its
    marks only (a cell it never marked is NO_INFORMATION to the merge): clearing removes its own marks and never
    opens the static map's unknown space. The costmap's rate may be above the lidar's:
    applying the sweep already applied again would change nothing (each cell it touches ends cleared or marked
    whatever it was), so it is skipped.
    """

    def __init__(
        self, frame: GridFrame, obstacle_range_m: float = 3.0, raytrace_range_m: float = 3.5
    ) -> None:
        self.frame = frame
        self.obstacle_range_m = obstacle_range_m
        self.raytrace_range_m = raytrace_range_m
        self.marked: NDArray[np.bool_] = np.zeros((frame.height, frame.width), dtype=bool)
        self._last_scan: LaserScan | None = None
        self._pending: list[Bounds] = []
        # numba compiles the kernel on its first call: make that call now, with no beams, so the robot's first
        # scan does not wait for it (and the experiment's agent CPU of a worker's first run does not carry it).
        no_beams, no_flags = np.zeros(0), np.zeros(0, dtype=bool)
        _trace_beams(
            self.marked,
            (frame.origin_x, frame.origin_y, frame.resolution),
            (0.0, 0.0),
            (no_beams, no_beams),
            no_beams,
            no_flags,
            no_flags,
            raytrace_range_m,
        )

    def take_bounds(self) -> list[Bounds]:
        out, self._pending = self._pending, []
        return out

    def update_costs(self, master: Costs, bounds: Bounds) -> None:
        """`update_with_max` of LETHAL where marked and NO_INFORMATION elsewhere, which comes down to writing
        LETHAL into the marked cells (nothing in master is above it but NO_INFORMATION, which it overrides)."""
        np.copyto(master, np.uint8(LETHAL_OBSTACLE), where=self.marked[bounds.rows, bounds.cols])

    def add_scan(self, scan: LaserScan, known: Sequence[tuple[float, float, float]] = ()) -> bool:
        """Clear and mark along the scan's beams; True if a cell changed (its window is then pending).

        Hits inside a `known` disc (x, y, radius: another robot, which the robots layer holds) clear but are not
        marked: a robot that drove on would otherwise leave its mark wherever this robot's lidar last saw it."""
        if scan is self._last_scan:
            return False
        self._last_scan = scan
        frame = self.frame
        res = frame.resolution
        x, y, yaw = scan.pose
        ranges = np.asarray(scan.ranges, dtype=np.float64)
        angles = yaw + scan.angle_min + scan.angle_increment * np.arange(len(ranges))
        usable = ~np.isnan(ranges) & (ranges >= scan.range_min)
        hit = usable & np.isfinite(ranges) & (ranges < scan.range_max) & (ranges <= self.obstacle_range_m)
        near = [
            (kx, ky, kr) for kx, ky, kr in known if math.hypot(kx - x, ky - y) <= self.obstacle_range_m + kr
        ]
        if near:
            reach = np.where(hit, ranges, 0.0)
            hx, hy = x + np.cos(angles) * reach, y + np.sin(angles) * reach
            for kx, ky, kr in near:
                hit &= np.hypot(hx - kx, hy - ky) > kr
        reach = math.ceil(max(self.raytrace_range_m, self.obstacle_range_m) / res) + 2
        row, col = frame.world_to_cell(x, y)
        window = Bounds(row - reach, col - reach, row + reach + 1, col + reach + 1).grow(0, frame)
        if window.empty:
            return False
        before = self.marked[window.rows, window.cols].copy()
        _trace_beams(
            self.marked,
            (frame.origin_x, frame.origin_y, res),
            (x, y),
            (np.cos(angles), np.sin(angles)),
            ranges,
            usable,
            hit,
            self.raytrace_range_m,
        )
        if np.array_equal(before, self.marked[window.rows, window.cols]):
            return False
        self._pending.append(window)
        return True

    def clear_outside(self, inside: Bounds) -> bool:
        """Forget every mark outside the cell window `inside` (clear_costmap_recovery's clearMap on this layer);
        True if a mark went (the window of those marks is then pending)."""
        keep = inside.grow(0, self.frame)
        before = self.marked.copy()
        self.marked[...] = False
        if not keep.empty:
            self.marked[keep.rows, keep.cols] = before[keep.rows, keep.cols]
        rows, cols = np.nonzero(before & ~self.marked)
        if len(rows) == 0:
            return False
        self._last_scan = None
        self._pending.append(
            Bounds(int(rows.min()), int(cols.min()), int(rows.max()) + 1, int(cols.max()) + 1)
        )
        return True


@njit
def _trace_beams(
    marked: NDArray[np.bool_],
    frame_at: tuple[float, float, float],
    at: tuple[float, float],
    direction: tuple[NDArray[np.float64], NDArray[np.float64]],
    ranges: NDArray[np.float64],
    usable: NDArray[np.bool_],
    hit: NDArray[np.bool_],
    raytrace_range: float,
) -> None:
    """Clear, then mark, the obstacle layer's cells along a scan's beams from `at`, heading along `direction`.

    Clearing: each usable beam's points every half cell, while short of a cell before its end (its range, or
    the raytrace range for a beam with no return). Marking: the cell of each `hit`. Compiled (numba): the
    (beams, samples) points this replaced were mostly beyond their beam's end; each point is computed with the
    same float64 operations in the same order, so the same cells change."""
    origin_x, origin_y, res = frame_at
    x, y = at
    cos, sin = direction
    height, width = marked.shape
    step = res / 2.0
    samples = math.ceil(raytrace_range / step) + 1
    for i in range(cos.shape[0]):
        clear_len = min(ranges[i] if math.isfinite(ranges[i]) else np.inf, raytrace_range)
        end = (clear_len if usable[i] else 0.0) - res
        for k in range(samples):
            s = k * step
            if not s < end:
                break
            col = math.floor((x + cos[i] * s - origin_x) / res)
            row = math.floor((y + sin[i] * s - origin_y) / res)
            if 0 <= row < height and 0 <= col < width:
                marked[row, col] = False
    for i in range(cos.shape[0]):
        if hit[i]:
            col = math.floor((x + cos[i] * ranges[i] - origin_x) / res)
            row = math.floor((y + sin[i] * ranges[i] - origin_y) / res)
            if 0 <= row < height and 0 <= col < width:
                marked[row, col] = True


class ZoneCostLayer:
    """The WSN zone layer's costs on the costmap's grid, repainted in the windows the zone layer changed.

    Merged by `update_with_max`, as the ROS bridge's grid is by a StaticLayer with `use_maximum`: a clear zone
    (0) changes nothing known, an unknown (stale) zone changes nothing at all, and walls stay walls. Cells outside
    every zone and block are NO_INFORMATION here, so the layer never opens the map's unknown space."""

    def __init__(self, zone_layer: ZoneLayer) -> None:
        self.zone_layer = zone_layer
        frame = zone_layer.frame
        self.costs: Costs = np.full((frame.height, frame.width), NO_INFORMATION, dtype=np.uint8)
        """NO_INFORMATION where no zone or operator block lies: the merge leaves master as it is there."""

    def repaint(self, bounds: Bounds) -> None:
        """Forget what the zone layer changed and paint it afresh in `bounds` (start-up, rebuild)."""
        self.zone_layer.take_changes()
        self.costs[bounds.rows, bounds.cols] = self.zone_layer.paint(bounds, outside=NO_INFORMATION)

    def take_bounds(self) -> list[Bounds]:
        """The zone layer's changed windows whose cells really changed cost."""
        out = []
        for w in self.zone_layer.take_changes():
            new = self.zone_layer.paint(w, outside=NO_INFORMATION)
            if not np.array_equal(new, self.costs[w.rows, w.cols]):
                self.costs[w.rows, w.cols] = new
                out.append(w)
        return out

    def update_costs(self, master: Costs, bounds: Bounds) -> None:
        update_with_max(master, self.costs[bounds.rows, bounds.cols])

    def update_costs_without(self, master: Costs, bounds: Bounds, exclude: Collection[BlockedArea]) -> None:
        """As `update_costs`, with some blocked areas left out (for letting a robot out of them)."""
        update_with_max(master, self.zone_layer.paint(bounds, exclude=exclude, outside=NO_INFORMATION))


class InflationLayer:
    """costmap_2d's inflation: master's lethal cells spread their cost over the robot's inflation radius.

    It holds no grid of its own; `grow` says how far a change in the merged layers reaches (its updateBounds),
    and `update_costs` recomputes master in a window from the merged layers around it.
    """

    def __init__(self, params: InflationParams, resolution: float) -> None:
        self.params = params
        self.resolution = resolution
        self.reach = inflation_reach(resolution, params)
        """Cells beyond which a lethal cell cannot change a cell's inflated cost."""

    def take_bounds(self) -> list[Bounds]:
        return []

    def grow(self, bounds: Bounds, frame: GridFrame) -> Bounds:
        return bounds.grow(self.reach, frame)

    def update_costs(self, master: Costs, bounds: Bounds, merged: Costs) -> None:
        """Set `master`'s cells in `bounds` to `merged` (the layers merged, whole map) with its inflation."""
        master[bounds.rows, bounds.cols] = inflate(
            merged, self.resolution, self.params, (bounds.rows, bounds.cols)
        )


@dataclass(frozen=True)
class OtherRobot:
    """Another robot of the fleet as its last status told it: where it stands, how big it is, what it does."""

    robot: str
    pose: Pose
    radius: float
    state: str
    priority: int
    """Its place in the site's robot list: 0 has right of way over everyone (wsnav.navigation.behaviors.right_of_way)."""
    expires_at: float
    """Clock time after which its pose is too old to keep (it went silent, or its status was an old retained one)."""


KNOWN_ROBOT_MARGIN_M = 0.2
"""Lidar hits this far beyond a known robot's footprint are its (it drives 0.11 m between two 2 Hz statuses)."""


class RobotsLayer:
    """The other robots' footprints (from `robots/<id>/status`): each a lethal disk until its pose goes stale.

    The inflation layer then adds this robot's own radius around them, so the planner keeps the two footprints
    apart as it keeps the robot off walls. Only the windows of disks that moved, appeared or expired are repainted.
    """

    def __init__(self, frame: GridFrame) -> None:
        self.frame = frame
        self.costs: Costs = np.zeros((frame.height, frame.width), dtype=np.uint8)
        self.robots: dict[str, OtherRobot] = {}
        self._windows: dict[str, Bounds] = {}
        self._pending: list[Bounds] = []

    def put(self, other: OtherRobot) -> None:
        """Place (or move) a robot's disk; a robot that did not move changes nothing."""
        old = self.robots.get(other.robot)
        self.robots[other.robot] = other
        if old is not None and (old.pose[:2], old.radius) == (other.pose[:2], other.radius):
            return
        before = self._windows.get(other.robot)
        self._windows[other.robot] = self._disk_window(other)
        self._repaint([self._windows[other.robot], *([before] if before is not None else [])])

    def expire(self, now: float) -> list[str]:
        """Forget the robots whose pose is older than allowed; returns their ids."""
        gone = [r for r, o in self.robots.items() if o.expires_at <= now]
        for robot in gone:
            del self.robots[robot]
            self._repaint([self._windows.pop(robot)])
        return gone

    def known_discs(self) -> list[tuple[float, float, float]]:
        """Each robot's footprint grown by KNOWN_ROBOT_MARGIN_M: lidar hits there are that robot, not an obstacle."""
        return [(o.pose[0], o.pose[1], o.radius + KNOWN_ROBOT_MARGIN_M) for o in self.robots.values()]

    @property
    def changed(self) -> bool:
        """Whether a disk moved, appeared or went since the stack last asked."""
        return bool(self._pending)

    def take_bounds(self) -> list[Bounds]:
        out, self._pending = self._pending, []
        return out

    def update_costs(self, master: Costs, bounds: Bounds) -> None:
        np.maximum(master, self.costs[bounds.rows, bounds.cols], out=master)

    def _disk_window(self, other: OtherRobot) -> Bounds:
        row, col = self.frame.world_to_cell(other.pose[0], other.pose[1])
        reach = math.ceil(other.radius / self.frame.resolution) + 1
        return Bounds(row - reach, col - reach, row + reach + 1, col + reach + 1).grow(0, self.frame)

    def _repaint(self, windows: list[Bounds]) -> None:
        """Paint every robot's disk afresh in `windows` (disks may overlap, so a window is redrawn whole)."""
        frame = self.frame
        res = frame.resolution
        for w in windows:
            if w.empty:
                continue
            ys = frame.origin_y + (np.arange(w.row0, w.row1) + 0.5) * res
            xs = frame.origin_x + (np.arange(w.col0, w.col1) + 0.5) * res
            painted = np.zeros(w.shape, dtype=bool)
            for other in self.robots.values():
                # A cell is covered when its centre lies within the radius grown by half a cell.
                d = np.hypot(xs[None, :] - other.pose[0], ys[:, None] - other.pose[1])
                painted |= d <= other.radius + res / 2
            self.costs[w.rows, w.cols] = np.where(painted, np.uint8(LETHAL_OBSTACLE), np.uint8(0))
            self._pending.append(w)
