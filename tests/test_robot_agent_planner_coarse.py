"""The planner's coarse-to-fine search on big grids: as good a path as a whole-grid A*, and a passage too narrow
for the block grid is still found (the search falls back to the whole grid)."""

from __future__ import annotations

import numpy as np

from robot_agent.global_planner import PlannerParams, plan_path
from robot_agent.inflation import FREE_SPACE, LETHAL_OBSTACLE

WHOLE = PlannerParams(coarse_above_cells=0)
COARSE = PlannerParams(coarse_above_cells=100_000)


def corridor_grid(n: int = 600) -> np.ndarray:
    """Rooms on a grid of corridors, a door in every wall: the map shape that makes a plain A* slow."""
    costs = np.zeros((n, n), dtype=np.uint8)
    for k in range(50, n, 100):
        costs[k, :] = LETHAL_OBSTACLE
        costs[:, k] = LETHAL_OBSTACLE
    for k in range(50, n, 100):
        for d in range(0, n, 100):
            costs[k, d + 20 : d + 30] = FREE_SPACE
            costs[d + 70 : d + 80, k] = FREE_SPACE
    return costs


def test_coarse_to_fine_finds_a_path_as_short_as_the_whole_grid_search() -> None:
    costs = corridor_grid()
    for start, goal in [((1.0, 1.0), (29.0, 29.0)), ((1.0, 28.0), (28.0, 5.0)), ((12.0, 3.0), (12.0, 27.0))]:
        whole = plan_path(costs, 0.05, (0.0, 0.0), start, goal, WHOLE)
        coarse = plan_path(costs, 0.05, (0.0, 0.0), start, goal, COARSE)
        assert whole.reachable and coarse.reachable
        assert coarse.length_m <= whole.length_m * 1.03
        assert (costs[coarse.cells[:, 0], coarse.cells[:, 1]] < LETHAL_OBSTACLE).all()


def test_a_passage_the_block_grid_cannot_see_is_still_used() -> None:
    costs = np.zeros((500, 500), dtype=np.uint8)
    costs[:, 250] = LETHAL_OBSTACLE
    costs[301:303, 250] = (
        FREE_SPACE  # two cells, straddling two 4 x 4 blocks: every block there is impassable
    )
    plan = plan_path(costs, 0.05, (0.0, 0.0), (2.0, 15.0), (23.0, 15.0), COARSE)
    assert plan.reachable
    assert any(r in (301, 302) and c == 250 for r, c in plan.cells)
    walled = costs.copy()
    walled[301:303, 250] = LETHAL_OBSTACLE
    assert plan_path(walled, 0.05, (0.0, 0.0), (2.0, 15.0), (23.0, 15.0), COARSE).reason == "no_path"
