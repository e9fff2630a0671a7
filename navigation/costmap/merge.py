"""costmap_2d's rules for combining a layer's costs into master (CostmapLayer's updateWith* methods), in one place.

Every layer enters master through one of these, so a rule means the same in every layer and reads as its
costmap_2d name. Each takes `master`, a window of the master grid, and `costs`, the layer's costs over the same
cells, and changes `master` in place. In all but the true overwrite a layer's NO_INFORMATION is "no opinion":
it leaves master's cell as it is.
"""

from __future__ import annotations

import numpy as np

from wsnav.zones.cost_values import INSCRIBED_INFLATED_OBSTACLE, NO_INFORMATION, Costs

__all__ = [
    "update_with_addition",
    "update_with_max",
    "update_with_max_without_unknown_overwrite",
    "update_with_overwrite",
    "update_with_true_overwrite",
]


def update_with_true_overwrite(master: Costs, costs: Costs) -> None:
    """updateWithTrueOverwrite: every cell takes the layer's cost, NO_INFORMATION included (the static map)."""
    master[...] = costs


def update_with_overwrite(master: Costs, costs: Costs) -> None:
    """updateWithOverwrite: the layer's cost wherever it has one, lower or higher than master's."""
    np.copyto(master, costs, where=costs != NO_INFORMATION)


def update_with_max(master: Costs, costs: Costs) -> None:
    """updateWithMax: the layer's cost where master's is NO_INFORMATION or lower, so a known cost replaces
    unknown and never lowers master (a stale zone read as unknown leaves the walls lethal)."""
    take = (costs != NO_INFORMATION) & ((master == NO_INFORMATION) | (master < costs))
    np.copyto(master, costs, where=take)


def update_with_max_without_unknown_overwrite(master: Costs, costs: Costs) -> None:
    """updateWithMaxWithoutUnknownOverwrite: as `update_with_max`, but master's NO_INFORMATION stays (a layer
    that only raises known costs, such as the other robots' footprints, never fills in unknown space)."""
    take = (costs != NO_INFORMATION) & (master != NO_INFORMATION) & (master < costs)
    np.copyto(master, costs, where=take)


def update_with_addition(master: Costs, costs: Costs) -> None:
    """updateWithAddition: master's cost plus the layer's, capped just below INSCRIBED (a sum never makes a cell
    an obstacle); where master is NO_INFORMATION the layer's cost alone."""
    total = np.minimum(master.astype(np.uint16) + costs, INSCRIBED_INFLATED_OBSTACLE - 1).astype(np.uint8)
    added = np.where(master == NO_INFORMATION, costs, total)
    np.copyto(master, added, where=costs != NO_INFORMATION)
