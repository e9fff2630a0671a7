"""The costmap's layers, each one class with costmap_2d's `Layer` calls, inflation included.

The stack (wsnav.navigation.costmap.layered_costmap) holds them in a list and calls each in its order:
`update_bounds` (costmap_2d's updateBounds: given the windows the layers before it changed, the windows to
recompute after it; a layer adds the windows it changed itself, the inflation layer grows them by its reach),
`update_costs` (updateCosts: combine its costs into a master window, by one of the rules of
wsnav.navigation.costmap.merge), `clear` (clearArea, for the recoveries: a layer forgets what it holds in a
window, if it holds anything a recovery may clear) and `rebuild` (recompute its grid whole). The order is static,
obstacle, zone, robots, inflation. Adding a layer means writing one class with these calls and putting it in
the stack's list; nothing else changes.
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
from wsnav.navigation.costmap.merge import (
    update_with_max,
    update_with_max_without_unknown_overwrite,
    update_with_true_overwrite,
)
from wsnav.schemas.ros_map import OccupancyGrid
from wsnav.zones.cost_values import LETHAL_OBSTACLE, NO_INFORMATION, Costs
from wsnav.zones.geometry import Bounds, GridFrame
from wsnav.zones.zone_rule import BlockedArea, ZoneRule


class Layer(Protocol):
    """One layer of the stack: what changed, how its costs enter master, what a recovery may clear of it."""

    def update_bounds(self, bounds: list[Bounds]) -> list[Bounds]:
        """The windows to recompute, given those the layers before this one changed (costmap_2d's updateBounds):
        `bounds` plus the windows this layer changed since the last call, or `bounds` grown by its reach."""
        ...

    def update_costs(self, master: Costs, bounds: Bounds) -> None:
        """Combine this layer's costs into `master`, an array covering `bounds` (costmap_2d's updateCosts)."""
        ...

    def clear(self, window: Bounds, *, outside: bool = False) -> bool:
        """Forget what this layer holds in `window` (outside it, with `outside`), costmap_2d's clearArea; True if
        something went (its window is then pending). A layer holding nothing a recovery may clear returns False."""
        ...

    def rebuild(self) -> None:
        """Recompute this layer's grid whole and forget its pending windows (LayeredCostmap.rebuild)."""
        ...


class Stack(Protocol):
    """What a layer may ask of the stack holding it (costmap_2d's `layered_costmap_`)."""

    def merge_below(self, layer: Layer, bounds: Bounds) -> Costs:
        """The layers before `layer` merged in order inside `bounds`."""
        ...


class StaticLayer:
    """The site's map: walls lethal, unknown space unknown; never changes after start-up. The first layer: it
    overwrites master, unknown included (costmap_2d's updateWithTrueOverwrite, StaticLayer's default)."""

    def __init__(self, grid: OccupancyGrid) -> None:
        self.costs: Costs = static_layer(grid)

    def update_bounds(self, bounds: list[Bounds]) -> list[Bounds]:
        return bounds

    def update_costs(self, master: Costs, bounds: Bounds) -> None:
        update_with_true_overwrite(master, self.costs[bounds.rows, bounds.cols])

    def clear(self, window: Bounds, *, outside: bool = False) -> bool:
        """The map is not the robot's to forget (costmap_2d's StaticLayer is not clearable)."""
        return False

    def rebuild(self) -> None:
        """Nothing to recompute: the map never changes."""


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

    def update_bounds(self, bounds: list[Bounds]) -> list[Bounds]:
        out, self._pending = [*bounds, *self._pending], []
        return out

    def update_costs(self, master: Costs, bounds: Bounds) -> None:
        """`update_with_max` of LETHAL where marked and NO_INFORMATION (no opinion) elsewhere."""
        marks = np.where(
            self.marked[bounds.rows, bounds.cols], np.uint8(LETHAL_OBSTACLE), np.uint8(NO_INFORMATION)
        )
        update_with_max(master, marks)

    def rebuild(self) -> None:
        """The marks are this layer's own record of the scans: kept; only the pending windows go."""
        self._pending = []

    def move(self, frame: GridFrame) -> None:
        """Re-home the layer on `frame` (a rolling window: same resolution and size, its origin whole cells
        away): marks inside both windows stay, the rest are forgotten (costmap_2d's updateOrigin), and the last
        scan may be applied again, over the cells the window gained."""
        res = self.frame.resolution
        d_row = round((frame.origin_y - self.frame.origin_y) / res)
        d_col = round((frame.origin_x - self.frame.origin_x) / res)
        old = Bounds(d_row, d_col, d_row + frame.height, d_col + frame.width)
        kept = old.grow(0, self.frame)
        marked = np.zeros((frame.height, frame.width), dtype=bool)
        if not kept.empty:
            marked[kept.within(old)] = self.marked[kept.rows, kept.cols]
        self.marked, self.frame = marked, frame
        self._last_scan = None
        self._pending = []

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

    def clear(self, window: Bounds, *, outside: bool = False) -> bool:
        """Forget every mark in `window` (outside it, with `outside`: clear_costmap_recovery's clearMap on this
        layer); True if a mark went (the window of those marks is then pending)."""
        area = np.zeros(self.marked.shape, dtype=bool)
        inside = window.grow(0, self.frame)
        if not inside.empty:
            area[inside.rows, inside.cols] = True
        gone = self.marked & (~area if outside else area)
        rows, cols = np.nonzero(gone)
        if len(rows) == 0:
            return False
        self.marked[gone] = False
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
    the raytrace range for a beam with no return), and no further than the grid's edge (a local costmap's
    window is much smaller than the raytrace range). Marking: the cell of each `hit`. Compiled (numba): the
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
        inside = False
        for k in range(samples):
            s = k * step
            if not s < end:
                break
            col = math.floor((x + cos[i] * s - origin_x) / res)
            row = math.floor((y + sin[i] * s - origin_y) / res)
            if 0 <= row < height and 0 <= col < width:
                marked[row, col] = False
                inside = True
            elif inside:
                break  # a ray that left the grid (a rectangle) never comes back: the rest is off it
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

    def __init__(self, zone_layer: ZoneRule) -> None:
        self.zone_layer = zone_layer
        frame = zone_layer.frame
        self.costs: Costs = np.full((frame.height, frame.width), NO_INFORMATION, dtype=np.uint8)
        """NO_INFORMATION where no zone or operator block lies: the merge leaves master as it is there."""

    def update_bounds(self, bounds: list[Bounds]) -> list[Bounds]:
        """`bounds` plus the zone layer's changed windows whose cells really changed cost."""
        out = list(bounds)
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

    def clear(self, window: Bounds, *, outside: bool = False) -> bool:
        """Not clearable: the costs are the sensor network's and the operator's word, which a recovery must not
        overrule (it would drive the robot into a zone reported blocked; the next repaint would bring them back)."""
        return False

    def rebuild(self) -> None:
        """Forget what the zone layer changed and paint the whole map afresh."""
        self.zone_layer.take_changes()
        whole = Bounds(0, 0, *self.costs.shape)
        self.costs[...] = self.zone_layer.paint(whole, outside=NO_INFORMATION)


class InflationLayer:
    """costmap_2d's inflation: the lethal cells of the layers before it spread their cost over the inflation radius.

    The last layer of the list. Its grid is a copy of the layers before it merged (what it inflates): its
    `update_bounds` merges them again in the windows they changed, keeps only the cells whose merged cost really
    changed (most scans re-mark walls the static layer already holds, and cost nothing), and grows those by its
    reach; `update_costs` writes the inflated costs of a window, from the lethal cells within reach of it, so a
    bounded update gives cell for cell what inflating the whole map gives.
    """

    def __init__(self, params: InflationParams, frame: GridFrame, stack: Stack) -> None:
        self.params = params
        self.frame = frame
        self.reach = inflation_reach(frame.resolution, params)
        """Cells beyond which a lethal cell cannot change a cell's inflated cost."""
        self.costs: Costs = np.full((frame.height, frame.width), NO_INFORMATION, dtype=np.uint8)
        """The layers before this one merged: what it inflates."""
        self._stack = stack

    def update_bounds(self, bounds: list[Bounds]) -> list[Bounds]:
        out = []
        for w in bounds:
            changed = self._merge_changes(w)
            if changed is not None:
                out.append(changed.grow(self.reach, self.frame))
        return out

    def update_costs(self, master: Costs, bounds: Bounds) -> None:
        """`master`'s window, inflated from this layer's copy of the costs below it (it reaches beyond `bounds`):
        the inflated costs already hold those below, so they overwrite master."""
        update_with_true_overwrite(master, self.inflate(self.costs, (bounds.rows, bounds.cols)))

    def clear(self, window: Bounds, *, outside: bool = False) -> bool:
        """Holds nothing of its own to clear: it re-inflates what the layers before it cleared."""
        return False

    def rebuild(self) -> None:
        self.costs = self._stack.merge_below(self, Bounds(0, 0, self.frame.height, self.frame.width))

    def inflate(self, below: Costs, inner: tuple[slice, slice]) -> Costs:
        """The cells `inner` of `below` (merged costs reaching `reach` cells beyond them, or the map's edge) with
        their inflation: this layer's rule, for master and for views beside it (the escape view)."""
        return inflate(below, self.frame.resolution, self.params, inner)

    def _merge_changes(self, window: Bounds) -> Bounds | None:
        """Merge the layers below again in `window`; the bounds of the cells whose merged cost changed, or None."""
        window = window.grow(0, self.frame)
        if window.empty:
            return None
        new = self._stack.merge_below(self, window)
        diff = new != self.costs[window.rows, window.cols]
        rows = np.flatnonzero(diff.any(axis=1))
        if len(rows) == 0:
            return None
        self.costs[window.rows, window.cols] = new
        cols = np.flatnonzero(diff.any(axis=0))
        return Bounds(
            window.row0 + int(rows[0]),
            window.col0 + int(cols[0]),
            window.row0 + int(rows[-1]) + 1,
            window.col0 + int(cols[-1]) + 1,
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

    def update_bounds(self, bounds: list[Bounds]) -> list[Bounds]:
        out, self._pending = [*bounds, *self._pending], []
        return out

    def update_costs(self, master: Costs, bounds: Bounds) -> None:
        """Raises known costs only: a disk never fills in the map's unknown space."""
        update_with_max_without_unknown_overwrite(master, self.costs[bounds.rows, bounds.cols])

    def clear(self, window: Bounds, *, outside: bool = False) -> bool:
        """Not clearable: the other robots stand where their statuses say until those go stale (`expire`)."""
        return False

    def rebuild(self) -> None:
        """The disks are painted as statuses come: only the pending windows go."""
        self._pending = []

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
