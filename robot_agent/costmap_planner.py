"""The global planner as the agent runs it: A* over the costmap's master grid, optionally on a coarser grid.

Planning on a grid `downsample` times coarser, each coarse cell taking the highest cost of the cells it
covers, keeps every path at least as far from walls and zones as at full resolution while A* expands
`downsample**2` times fewer cells: what keeps a zone message's replan within the latency budget on big maps.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from robot_agent.global_planner import XY, Plan, PlannerParams, plan_path
from robot_agent.inflation import NO_INFORMATION
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
