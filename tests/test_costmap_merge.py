"""The merge rules (wsnav.navigation.costmap.merge) against costmap_2d's CostmapLayer::updateWith* cell by cell:
every pair of a master cost and a layer cost, and the cases the layers rely on written out."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from wsnav.navigation.costmap.merge import (
    update_with_addition,
    update_with_max,
    update_with_max_without_unknown_overwrite,
    update_with_overwrite,
    update_with_true_overwrite,
)
from wsnav.zones.cost_values import FREE_SPACE, INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE, NO_INFORMATION

UNKNOWN = NO_INFORMATION
VALUES = [FREE_SPACE, 1, 100, 200, 252, INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE, UNKNOWN]


def nav2_cell(rule: str, old: int, cost: int) -> int:
    """One cell as costmap_2d's loops compute it (costmap_layer.cpp), written from its C++ branch by branch."""
    if rule == "true_overwrite":
        return cost
    if cost == UNKNOWN:
        return old
    if rule == "overwrite":
        return cost
    if rule == "max":
        return cost if old == UNKNOWN or old < cost else old
    if rule == "max_without_unknown_overwrite":
        return cost if old != UNKNOWN and old < cost else old
    assert rule == "addition"
    if old == UNKNOWN:
        return cost
    return min(old + cost, INSCRIBED_INFLATED_OBSTACLE - 1)


RULES: dict[str, Callable[[np.ndarray, np.ndarray], None]] = {
    "true_overwrite": update_with_true_overwrite,
    "overwrite": update_with_overwrite,
    "max": update_with_max,
    "max_without_unknown_overwrite": update_with_max_without_unknown_overwrite,
    "addition": update_with_addition,
}


@pytest.mark.parametrize("rule", list(RULES))
def test_each_rule_gives_costmap_2d_cost_for_every_pair_of_costs(rule: str) -> None:
    old, cost = np.meshgrid(np.array(VALUES, dtype=np.uint8), np.array(VALUES, dtype=np.uint8))
    master = old.copy()
    RULES[rule](master, cost)
    expected = np.vectorize(lambda o, c: nav2_cell(rule, int(o), int(c)))(old, cost).astype(np.uint8)
    np.testing.assert_array_equal(master, expected)
    assert master.dtype == np.uint8


def test_the_cases_the_layers_rely_on() -> None:
    def merged(rule: Callable[[np.ndarray, np.ndarray], None], old: int, cost: int) -> int:
        master = np.array([old], dtype=np.uint8)
        rule(master, np.array([cost], dtype=np.uint8))
        return int(master[0])

    # the static layer: the map as it is, unknown included
    assert merged(update_with_true_overwrite, LETHAL_OBSTACLE, UNKNOWN) == UNKNOWN
    # a stale zone read as unknown leaves a wall lethal; a caution cost never lowers it; unknown space takes
    # a zone's cost; a plain numeric maximum would keep 255 over 254
    assert merged(update_with_max, LETHAL_OBSTACLE, UNKNOWN) == LETHAL_OBSTACLE
    assert merged(update_with_max, LETHAL_OBSTACLE, 150) == LETHAL_OBSTACLE
    assert merged(update_with_max, UNKNOWN, LETHAL_OBSTACLE) == LETHAL_OBSTACLE
    assert merged(update_with_max, UNKNOWN, FREE_SPACE) == FREE_SPACE
    # another robot's disk never fills in unknown space, and its free cells never lower master
    assert merged(update_with_max_without_unknown_overwrite, UNKNOWN, LETHAL_OBSTACLE) == UNKNOWN
    assert merged(update_with_max_without_unknown_overwrite, 100, FREE_SPACE) == 100
    assert merged(update_with_max_without_unknown_overwrite, 100, LETHAL_OBSTACLE) == LETHAL_OBSTACLE
    # overwrite lowers; addition never reaches INSCRIBED (no uint8 wrap-around: 200 + 200 is not 144)
    assert merged(update_with_overwrite, LETHAL_OBSTACLE, FREE_SPACE) == FREE_SPACE
    assert merged(update_with_addition, 200, 200) == INSCRIBED_INFLATED_OBSTACLE - 1
    assert merged(update_with_addition, 100, 50) == 150


def test_a_rule_changes_only_the_window_it_is_given() -> None:
    grid = np.full((6, 6), 7, dtype=np.uint8)
    update_with_max(grid[2:4, 1:5], np.full((2, 4), 90, dtype=np.uint8))
    assert (grid[2:4, 1:5] == 90).all()
    grid[2:4, 1:5] = 7
    assert (grid == 7).all()
