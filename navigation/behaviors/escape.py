"""Leaving a blocked zone: a robot standing in a zone that becomes blocked must be able to drive out of it.

Everything about it lives here: which blocked areas the robot's footprint touches (`ZoneEscape.areas_at`), the
escape view (master around those areas with their own cost passable, walls and the lidar's marks unchanged,
computed in the areas' neighbourhood only and only while the footprint touches one), and the two-leg plan
(`plan_escape`: the shortest way out over the view, then on from the exit over master, so the route never goes
back through the zone). The navigator holds the state (`Leaving`) and decides when to use them. A navigator
without wsnav's costmap (move_base, supervised by the ROS bridge) finds its exit with `exit_beside`, by the same
search (`plan_exit`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt

from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.planning.astar import XY, Plan, PlannerParams, plan_exit
from wsnav.navigation.planning.global_planner import GlobalPlanner, PlanningCostmap
from wsnav.zones.cost_values import FREE_SPACE, INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE
from wsnav.zones.geometry import Bounds, CellWindow, GridFrame
from wsnav.zones.zone_rule import BlockedArea

ESCAPE_COST = 200
"""What a cell made lethal or inscribed only by a zone the robot stands in costs in an escape view: passable, but
dear enough that the controller creeps (its speed falls with cost) while it leaves."""
EXIT_MARGIN_CELLS = 2
"""An exit lies this many cells beyond where the footprint stops touching the zones: a robot that stopped near
an exit (within the controller's goal tolerance) is out, not on the edge."""


@dataclass(frozen=True)
class Leaving:
    """The navigator's escape state: the areas the robot is driving out of, and whether a route goes on."""

    areas: tuple[BlockedArea, ...]
    onward: bool
    """A route on to the goal follows the way out; False: the path is the way out alone (then wait)."""

    @property
    def names(self) -> str:
        return ", ".join(a.name for a in self.areas)


@dataclass(frozen=True)
class EscapeView:
    """Master around some blocked areas with their zone cost relaxed, for leaving them.

    Inside `bounds` (the areas grown by the inflation's reach), `costs` is master where every cell that only those
    areas made lethal or inscribed costs `ESCAPE_COST` (or its inflation from what remains, if higher); walls,
    the lidar's marks, other areas and everything outside `bounds` keep master's cost. `exits` marks the cells of
    `bounds` where the robot's footprint is clear of the areas (by `areas_at`'s rule, plus a margin).
    """

    areas: tuple[BlockedArea, ...]
    version: int
    """Master's version it was computed from."""
    bounds: Bounds
    costs: NDArray[np.uint8]
    exits: NDArray[np.bool_]

    @property
    def overlay(self) -> tuple[Bounds, NDArray[np.uint8]]:
        """What the local costmap shows instead of master (LayeredCostmap.local_window's `overlay`)."""
        return self.bounds, self.costs


class ZoneEscape:
    """Which blocked areas a footprint touches, and the escape view around them, over one layered costmap."""

    def __init__(self, costmap: LayeredCostmap) -> None:
        self.costmap = costmap
        frame = costmap.frame
        self._touch = math.ceil(costmap.inflation.params.inscribed_radius / frame.resolution)
        """`areas_at`'s radius in cells: an area's cell this near the robot's cell touches its footprint."""
        self._cached: EscapeView | None = None

    def areas_at(self, x: float, y: float) -> list[BlockedArea]:
        """Blocked zones and operator polygon blocks within the robot's radius of a point."""
        layer = self.costmap.zone_layer
        if layer is None:
            return []
        row, col = self.costmap.frame.world_to_cell(x, y)
        r = self._touch
        rows, cols = np.ogrid[-r : r + 1, -r : r + 1]
        disk = rows * rows + cols * cols <= r * r
        here = Bounds(row - r, col - r, row + r + 1, col + r + 1)
        return [area for area, window in layer.blocked_areas() if _touches(window, here, disk)]

    def view(self, areas: Sequence[BlockedArea]) -> EscapeView | None:
        """Master with `areas` passable, around them only; None if none of them is blocked now.

        The areas' neighbourhood is merged again without them and re-inflated there, so walls and what the lidar
        sees stay lethal and inscribed; kept until master or the areas change (the controller asks every tick).
        """
        key = tuple(sorted(set(areas)))
        cached = self._cached
        costmap = self.costmap
        if cached is not None and cached.areas == key and cached.version == costmap.version:
            return cached
        layer, zones = costmap.zone_layer, costmap.zones
        if layer is None or zones is None:
            return None
        windows = [w for a, w in layer.blocked_areas() if a in key and not w.empty]
        if not windows:
            return None
        frame = costmap.frame
        reach = costmap.inflation.reach
        area: Bounds | None = None
        for w in windows:
            area = Bounds.of_window(w).union(area)
        assert area is not None
        bounds = area.grow(max(reach, self._touch + EXIT_MARGIN_CELLS + 2), frame)
        source = bounds.grow(reach, frame)
        inflation = costmap.inflation
        below = [layer_ for layer_ in costmap.layers_below(inflation) if layer_ is not zones]
        merged = costmap.merge(source, below)
        zones.update_costs_without(merged, source, key)
        without = inflation.inflate(merged, bounds.within(source))
        costs = costmap.master[bounds.rows, bounds.cols].copy()
        relax = (costs >= INSCRIBED_INFLATED_OBSTACLE) & (without < INSCRIBED_INFLATED_OBSTACLE)
        costs[relax] = np.maximum(without[relax], np.uint8(ESCAPE_COST))
        inside = np.zeros(bounds.shape, dtype=bool)
        for w in windows:
            common = Bounds.of_window(w).intersection(bounds)
            inside[common.within(bounds)] |= w.mask[common.within(Bounds.of_window(w))]
        dist = np.asarray(distance_transform_edt(~inside), dtype=np.float64)
        exits = (dist > self._touch + EXIT_MARGIN_CELLS) & (costs < INSCRIBED_INFLATED_OBSTACLE)
        self._cached = EscapeView(key, costmap.version, bounds, costs, exits)
        return self._cached


@dataclass(frozen=True)
class EscapePlan:
    """The way out of blocked areas and, when there is one, the route on to the goal from its end."""

    out: Plan
    """Start to the nearest exit over the escape view; not reachable when the robot is shut in."""
    onward: Plan | None
    """Exit to goal over the costmap as it is (None without a way out)."""

    @property
    def reaches_goal(self) -> bool:
        return self.out.reachable and self.onward is not None and self.onward.reachable

    @property
    def path(self) -> NDArray[np.float64]:
        """The whole route when it reaches the goal, else the way out alone."""
        if not self.reaches_goal:
            return self.out.path
        assert self.onward is not None
        return np.vstack([self.out.path, self.onward.path[1:]])

    @property
    def length_m(self) -> float:
        onward = self.onward.length_m if self.reaches_goal and self.onward is not None else 0.0
        return self.out.length_m + onward

    @property
    def plan_ms(self) -> float:
        return self.out.plan_ms + (self.onward.plan_ms if self.onward is not None else 0.0)


def plan_escape(
    planner: GlobalPlanner, costmap: PlanningCostmap, view: EscapeView, start: XY, goal: XY
) -> EscapePlan:
    """The shortest way out of the view's areas from `start`, then a plan from its end to `goal` over master.

    The way out is searched at full resolution in the view's bounds only; the onward leg is the planner's
    ordinary `plan`, so the areas are lethal again for it (no route back through them).
    """
    t0 = time.perf_counter()
    frame = costmap.frame
    b = view.bounds
    row, col = frame.world_to_cell(*start)
    cell = (row - b.row0, col - b.col0)
    inside = 0 <= cell[0] < view.costs.shape[0] and 0 <= cell[1] < view.costs.shape[1]
    cells = plan_exit(view.costs, view.exits, cell, frame.resolution, planner.params) if inside else None
    ms = (time.perf_counter() - t0) * 1000.0
    if cells is None:
        return EscapePlan(Plan(False, "start_blocked", plan_ms=ms), None)
    # The first cell is the start's own: the robot leaves from where it stands, not from its cell's centre.
    path = np.empty((len(cells), 2), dtype=np.float64)
    path[0] = start
    path[1:, 0] = frame.origin_x + (cells[1:, 1] + b.col0 + 0.5) * frame.resolution
    path[1:, 1] = frame.origin_y + (cells[1:, 0] + b.row0 + 0.5) * frame.resolution
    length = float(np.hypot(*np.diff(path, axis=0).T).sum()) if len(path) > 1 else 0.0
    out = Plan(True, "ok", path, cells + np.array([b.row0, b.col0], dtype=np.intp), length, ms)
    exit_xy = (float(path[-1, 0]), float(path[-1, 1]))
    return EscapePlan(out, planner.plan(costmap, exit_xy, goal))


def exit_beside(
    frame: GridFrame,
    walls: NDArray[np.bool_],
    blocked: NDArray[np.bool_],
    start: XY,
    clear_m: float = 0.35,
    search_m: float = 6.0,
    params: PlannerParams | None = None,
) -> XY | None:
    """The nearest place by the way there (not as the crow flies: a room behind the corridor's wall is not an exit)
    at least `clear_m` from every `blocked` cell and on no wall, within `search_m` of `start`; None if there is
    none. For a navigator without wsnav's costmap (move_base): walls lethal, the blocked cells at ESCAPE_COST,
    searched by `plan_exit` as the navigator's own way out is. `walls` and `blocked` are whole-map masks."""
    row, col = frame.world_to_cell(*start)
    if not frame.contains_cell(row, col):
        return None
    reach = int(search_m / frame.resolution)
    b = Bounds(
        max(0, row - reach),
        max(0, col - reach),
        min(frame.height, row + reach + 1),
        min(frame.width, col + reach + 1),
    )
    wall, inside = walls[b.rows, b.cols], blocked[b.rows, b.cols]
    costs = np.where(wall, LETHAL_OBSTACLE, np.where(inside, ESCAPE_COST, FREE_SPACE)).astype(np.uint8)
    away = np.asarray(distance_transform_edt(~inside), dtype=np.float64) * frame.resolution >= clear_m
    cells = plan_exit(costs, away & ~wall, (row - b.row0, col - b.col0), frame.resolution, params)
    if cells is None:
        return None
    return frame.cell_to_world(int(cells[-1, 0]) + b.row0, int(cells[-1, 1]) + b.col0)


def _touches(window: CellWindow, here: Bounds, disk: NDArray[np.bool_]) -> bool:
    """True if any cell of `window` lies in the disk that fills `here`."""
    if window.empty:
        return False
    area = Bounds.of_window(window)
    common = area.intersection(here)
    if common.empty:
        return False
    return bool((window.mask[common.within(area)] & disk[common.within(here)]).any())
