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

from wsnav.navigation.planning.astar import (
    XY,
    Plan,
    PlannerParams,
    coarse_weights,
    plan_path,
    searched_coarse,
    weight_lut,
)
from wsnav.zones.cost_values import NO_INFORMATION
from wsnav.zones.geometry import Bounds, GridFrame


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
    """What the planner reads of wsnav.navigation.costmap.layered_costmap.LayeredCostmap."""

    @property
    def frame(self) -> GridFrame: ...
    @property
    def master(self) -> NDArray[np.uint8]: ...
    @property
    def version(self) -> int:
        """Changes whenever master does."""
        ...

    def changes_since(self, version: int) -> list[Bounds] | None:
        """The bounds master changed in after `version`, or None when they are no longer known."""
        ...


class PlannerWeights:
    """A* weights of a costmap's master, and their block grid on big maps, kept up to date in the bounds that
    changed since the last plan.

    A planner replanning at 5 Hz must not convert (nor average, for the coarse search) the whole map each
    time; the costmap tells which bounds changed (`changes_since`), and only those are converted again.
    """

    def __init__(self, params: PlannerParams) -> None:
        self._params = params
        self._lut = weight_lut(params)
        self._weights: NDArray[np.float32] | None = None
        self._coarse: NDArray[np.float32] | None = None
        self._source: PlanningCostmap | None = None
        self._version = -1

    def of(self, costmap: PlanningCostmap) -> NDArray[np.float32]:
        """The weights of `costmap`'s master now (the array is reused and updated in place)."""
        changes = costmap.changes_since(self._version) if costmap is self._source else None
        self._source = costmap
        coarse = searched_coarse(costmap.master.shape, self._params)
        f = self._params.coarse_factor
        if changes is None or self._weights is None:
            self._weights = self._lut[costmap.master]
            self._coarse = coarse_weights(self._weights, f) if coarse else None
        else:
            for b in changes:
                self._weights[b.rows, b.cols] = self._lut[costmap.master[b.rows, b.cols]]
                if self._coarse is not None:
                    coarse_weights(self._weights, f, self._coarse, b)
        self._version = costmap.version
        return self._weights

    @property
    def coarse(self) -> NDArray[np.float32] | None:
        """The block grid (`coarse_weights`) of the weights `of` last returned; None on a grid searched whole."""
        return self._coarse


@dataclass
class GlobalPlanner:
    params: PlannerParams
    downsample: int = 1
    _pooled: tuple[int, NDArray[np.uint8]] | None = field(default=None, init=False, repr=False)
    """(costmap version, coarse grid): replanning on an unchanged costmap does not pool it again."""
    _weights: PlannerWeights | None = field(default=None, init=False, repr=False)

    def plan(self, costmap: PlanningCostmap, start: XY, goal: XY) -> Plan:
        """A path from `start` to `goal` (world metres) over the costmap; never raises for unreachable goals.

        At full resolution the A* weights (and their block grid) are kept up to date in the bounds that changed
        (PlannerWeights).
        """
        frame = costmap.frame
        origin = (frame.origin_x, frame.origin_y)
        if self.downsample == 1:
            if self._weights is None:
                self._weights = PlannerWeights(self.params)
            weights = self._weights.of(costmap)
            return plan_path(
                costmap.master,
                frame.resolution,
                origin,
                start,
                goal,
                self.params,
                weights,
                self._weights.coarse,
            )
        if self._pooled is None or self._pooled[0] != costmap.version:
            self._pooled = (costmap.version, pool_max(costmap.master, self.downsample))
        grid = self._pooled[1]
        return plan_path(grid, frame.resolution * self.downsample, origin, start, goal, self.params)
