"""The global planner as the agent runs it: A* over the costmap's master grid, optionally on a coarser grid.

Planning on a grid `downsample` times coarser, each coarse cell taking the highest cost of the cells it
covers, keeps every path at least as far from walls and zones as at full resolution while A* expands
`downsample**2` times fewer cells: what keeps a zone message's replan within the latency budget on big maps.

A robot standing in a blocked zone is planned in two legs (`plan_escape`): the shortest way out over an escape
view of the costmap (the zone passable, walls and lidar marks not), then on from the exit over the costmap as it
is, so the rest of the route never goes back through the zone.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from robot_agent.global_planner import XY, Plan, PlannerParams, plan_exit, plan_path
from robot_agent.inflation import NO_INFORMATION
from robot_agent.layered_costmap import EscapeView
from robot_agent.zone_geometry import GridFrame


def pool_max(costs: NDArray[np.uint8], factor: int) -> NDArray[np.uint8]:
    """Each `factor` x `factor` block's highest cost; a partial block at the edge is padded with unknown."""
    if factor == 1:
        return costs
    h, w = costs.shape
    ph, pw = -h % factor, -w % factor
    if ph or pw:
        costs = np.pad(costs, ((0, ph), (0, pw)), constant_values=NO_INFORMATION)
    out = costs[0::factor, 0::factor].copy()
    for dr in range(factor):
        for dc in range(factor):
            if dr or dc:
                np.maximum(out, costs[dr::factor, dc::factor], out=out)
    return out


class PlanningCostmap(Protocol):
    """What the planner reads of robot_agent.layered_costmap.LayeredCostmap."""

    @property
    def frame(self) -> GridFrame: ...
    @property
    def master(self) -> NDArray[np.uint8]: ...
    @property
    def version(self) -> int:
        """Changes whenever master does."""
        ...

    def planner_weights(self, params: PlannerParams | None = None) -> NDArray[np.float32]: ...


@dataclass(frozen=True)
class EscapePlan:
    """The way out of blocked zones and, when there is one, the route on to the goal from its end."""

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


@dataclass
class GlobalPlanner:
    params: PlannerParams
    downsample: int = 1
    _pooled: tuple[int, NDArray[np.uint8]] | None = field(default=None, init=False, repr=False)
    """(costmap version, coarse grid): replanning on an unchanged costmap does not pool it again."""

    def plan(self, costmap: PlanningCostmap, start: XY, goal: XY) -> Plan:
        """A path from `start` to `goal` (world metres) over the costmap; never raises for unreachable goals.

        At full resolution the A* weights come from the costmap, which keeps them up to date in the bounds that
        changed: a planner replanning at 5 Hz does not convert the whole map each time.
        """
        frame = costmap.frame
        origin = (frame.origin_x, frame.origin_y)
        if self.downsample == 1:
            weights = costmap.planner_weights(self.params)
            return plan_path(costmap.master, frame.resolution, origin, start, goal, self.params, weights)
        if self._pooled is None or self._pooled[0] != costmap.version:
            self._pooled = (costmap.version, pool_max(costmap.master, self.downsample))
        grid = self._pooled[1]
        return plan_path(grid, frame.resolution * self.downsample, origin, start, goal, self.params)

    def plan_escape(self, costmap: PlanningCostmap, view: EscapeView, start: XY, goal: XY) -> EscapePlan:
        """The shortest way out of the view's zones from `start`, then a plan from its end to `goal` over master.

        The way out is searched at full resolution in the view's bounds only; the onward leg is an ordinary
        `plan`, so the zones are lethal again for it (no route back through them).
        """
        t0 = time.perf_counter()
        frame = costmap.frame
        b = view.bounds
        row, col = frame.world_to_cell(*start)
        cell = (row - b.row0, col - b.col0)
        inside = 0 <= cell[0] < view.costs.shape[0] and 0 <= cell[1] < view.costs.shape[1]
        cells = plan_exit(view.costs, view.exits, cell, frame.resolution, self.params) if inside else None
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
        return EscapePlan(out, self.plan(costmap, exit_xy, goal))
