"""The planner's coarse-to-fine search on big grids: as good a path as a whole-grid A*, a passage too narrow for
the block grid is still found (the search falls back to the whole grid), and the block grid the planner keeps
up to date between plans gives the plans a block grid made anew would."""

from __future__ import annotations

import math

import numpy as np

from wsnav.navigation.backend import LaserScan
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.planning.astar import PlannerParams, coarse_weights, plan_path, weights_for
from wsnav.navigation.planning.global_planner import GlobalPlanner, PlannerWeights
from wsnav.schemas.messages import ZoneState
from wsnav.schemas.site import Site
from wsnav.zones.cost_values import FREE_SPACE, LETHAL_OBSTACLE
from wsnav.zones.geometry import Bounds, GridFrame
from wsnav.zones.zone_rule import ZoneRule

WHOLE = PlannerParams(coarse_above_cells=0)
COARSE = PlannerParams(coarse_above_cells=100_000)
INFLATION = InflationParams(inscribed_radius=0.105, inflation_radius=1.0, cost_scaling_factor=3.0)


def scan(pose: tuple[float, float, float], ranges: dict[int, float], beams: int = 360) -> LaserScan:
    """A sweep with beam i at yaw + i degrees; beams not given see nothing (+inf)."""
    r = np.full(beams, np.inf, dtype=np.float32)
    for i, value in ranges.items():
        r[i] = value
    return LaserScan(0.0, pose, 0.0, 2 * math.pi / beams, 0.12, 3.5, r)


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


def test_a_block_grid_updated_where_weights_changed_equals_one_made_anew() -> None:
    rng = np.random.default_rng(7)
    costs = rng.integers(0, 256, size=(203, 157), dtype=np.uint8)  # edge blocks padded on both sides
    weights = weights_for(costs, COARSE)
    kept = coarse_weights(weights, 4)
    for changed in [
        Bounds(0, 0, 3, 5),
        Bounds(190, 140, 203, 157),
        Bounds(50, 61, 51, 62),
        Bounds(7, 0, 90, 157),
    ]:
        costs[changed.rows, changed.cols] = rng.integers(0, 256, size=changed.shape, dtype=np.uint8)
        weights[changed.rows, changed.cols] = weights_for(costs[changed.rows, changed.cols], COARSE)
        assert coarse_weights(weights, 4, kept, changed) is kept
        assert np.array_equal(kept, coarse_weights(weights, 4))


def test_the_planners_kept_block_grid_follows_costmap_changes_and_gives_the_plan_made_anew(
    school: Site,
) -> None:
    layer = ZoneRule(school.spec, GridFrame.of_grid(school.grid), None)
    costmap = LayeredCostmap(school.grid, INFLATION, zone_layer=layer)
    params = PlannerParams()
    planner = GlobalPlanner(params)
    kept = PlannerWeights(params)
    start, goal = school.point("A")[:2], school.point("B")[:2]
    grid = school.grid
    steps = [
        lambda: costmap.update_scan(scan((13.0, 7.2, 0.0), {0: 1.0, 10: 1.3, 350: 1.2})),
        lambda: (
            layer.on_zone_state(ZoneState(zone="z1", node="n1", state="blocked", seq=1), 1.0)
            and costmap.update_zones(1.0)
        ),
        lambda: costmap.update_scan(scan((13.0, 7.2, 0.0), {})),
        lambda: (
            layer.on_zone_state(ZoneState(zone="z1", node="n1", state="clear", seq=2), 2.0)
            and costmap.update_zones(2.0)
        ),
    ]
    kept.of(costmap)
    for step in steps:
        before = costmap.master.copy()
        assert step() is not None
        assert not np.array_equal(before, costmap.master), "each step changes the costmap"
        weights = kept.of(costmap)
        assert kept.coarse is not None
        assert np.array_equal(weights, weights_for(costmap.master, params))
        assert np.array_equal(kept.coarse, coarse_weights(weights_for(costmap.master, params), 4))
        anew = plan_path(costmap.master, grid.resolution, grid.origin, start, goal, params)
        assert np.array_equal(planner.plan(costmap, start, goal).cells, anew.cells)


def test_a_start_beside_a_wall_leaves_the_kept_block_grid_as_it_was() -> None:
    costs = corridor_grid()
    weights = weights_for(costs, COARSE)
    kept = coarse_weights(weights, 4)
    before = kept.copy()
    start, goal = (2.45, 1.0), (29.0, 29.0)  # cell (20, 49): its block holds wall cells of column 50
    assert not np.isfinite(kept[20 // 4, 49 // 4])
    plan = plan_path(costs, 0.05, (0.0, 0.0), start, goal, COARSE, weights, kept)
    assert plan.reachable
    assert np.array_equal(kept, before, equal_nan=True)
    assert np.array_equal(plan.cells, plan_path(costs, 0.05, (0.0, 0.0), start, goal, COARSE).cells)


def test_coarse_to_fine_reaches_the_last_partial_blocks_of_a_grid_not_a_multiple_of_the_block() -> None:
    costs = corridor_grid(600)[:599, :597]  # the last row and column of blocks are partial
    start, goal = (1.0, 1.0), (29.82, 29.93)  # the goal in the last, partial block of both axes
    whole = plan_path(costs, 0.05, (0.0, 0.0), start, goal, WHOLE)
    coarse = plan_path(costs, 0.05, (0.0, 0.0), start, goal, COARSE)
    assert coarse.reachable and tuple(coarse.cells[-1]) == (598, 596)
    assert coarse.length_m <= whole.length_m * 1.03
