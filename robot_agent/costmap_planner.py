"""The global planner as the agent runs it: A* over the costmap's master grid, optionally on a coarser grid.

Planning on a grid `downsample` times coarser, each coarse cell taking the highest cost of the cells it
covers, keeps every path at least as far from walls and zones as at full resolution while A* expands
`downsample**2` times fewer cells: what keeps a zone message's replan within the latency budget on big maps.
"""

from __future__ import annotations

from dataclasses import dataclass

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


@dataclass
class GlobalPlanner:
    params: PlannerParams
    downsample: int = 1

    def plan(self, costs: NDArray[np.uint8], frame: GridFrame, start: XY, goal: XY) -> Plan:
        """A path from `start` to `goal` (world metres) over `costs`; never raises for unreachable goals."""
        grid = pool_max(costs, self.downsample)
        return plan_path(
            grid,
            frame.resolution * self.downsample,
            (frame.origin_x, frame.origin_y),
            start,
            goal,
            self.params,
        )
