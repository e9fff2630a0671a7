"""The layered costmap: bounded zone updates give exactly the whole-map result, the lidar marks and clears, and
the queries (goal check, zones at a point, rolling window, planner weights) read the merged, inflated map."""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import SITES
from tests.robot_agent_rig import scan_from
from tests.site_fixtures import tiny_site
from wsnav.navigation.behaviors.escape import ZoneEscape
from wsnav.navigation.costmap.inflation import InflationParams, cost_lut, inflate, static_layer
from wsnav.navigation.costmap.layered_costmap import CHANGE_LOG, Bounds, LayeredCostmap
from wsnav.navigation.costmap.layers import InflationLayer, Layer, RobotsLayer
from wsnav.navigation.costmap.merge import update_with_max, update_with_overwrite
from wsnav.navigation.planning.astar import PlannerParams, plan_path, weights_for
from wsnav.navigation.planning.global_planner import PlannerWeights
from wsnav.navigation.planning.offline_plan import zone_lethal
from wsnav.schemas.messages import NodeStatus, OperatorBlock, ZoneState
from wsnav.schemas.site import Site, load_site
from wsnav.schemas.site_file import ZonePolicy
from wsnav.zones.cost_values import FREE_SPACE, INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import GridFrame
from wsnav.zones.zone_rule import ZoneRule

MergeRule = Callable[[np.ndarray, np.ndarray], None]
INFLATION = InflationParams(inscribed_radius=0.105, inflation_radius=1.0, cost_scaling_factor=3.0)


@pytest.fixture
def tiny(tmp_path: Path) -> Site:
    return load_site(tiny_site(tmp_path / "tiny"))


def school_costmap(site: Site, policy: ZonePolicy | None = None) -> tuple[LayeredCostmap, ZoneRule]:
    layer = ZoneRule(site.spec, GridFrame.of_grid(site.grid), policy)
    return LayeredCostmap(site.grid, INFLATION, zone_layer=layer), layer


def zone_costs(costmap: LayeredCostmap) -> np.ndarray:
    assert costmap.zones is not None
    return costmap.zones.costs


def names_at(costmap: LayeredCostmap, x: float, y: float) -> list[str]:
    return [area.name for area in ZoneEscape(costmap).areas_at(x, y)]


def test_a_blocked_zone_gives_the_static_map_with_the_zone_lethal_inflated(school: Site) -> None:
    costmap, layer = school_costmap(school)
    empty = costmap.master.copy()
    assert layer.on_zone_state(ZoneState(zone="z1", node="n1", state="blocked", seq=1), 10.0)
    bounds = costmap.update_zones(10.0)
    assert bounds is not None
    # An independent reference: costmap_2d's static layer, the zone's cells lethal, the whole map inflated.
    reference = static_layer(school.grid)
    reference[zone_lethal(school, ["z1"])] = LETHAL_OBSTACLE
    reference = inflate(reference, school.grid.resolution, INFLATION)
    assert np.array_equal(costmap.master, reference)
    # The update stayed inside the bounds it reported, and those are the cells the zone made lethal (not the
    # walls it covers) grown by the inflation radius.
    outside = np.ones(empty.shape, dtype=bool)
    outside[bounds.rows, bounds.cols] = False
    assert np.array_equal(costmap.master[outside], empty[outside])
    rows, cols = np.nonzero(zone_lethal(school, ["z1"]) & (static_layer(school.grid) == FREE_SPACE))
    made_lethal = Bounds(int(rows.min()), int(cols.min()), int(rows.max()) + 1, int(cols.max()) + 1)
    reach = math.ceil(INFLATION.inflation_radius / school.grid.resolution) + 1
    assert bounds == made_lethal.grow(reach, costmap.frame)
    assert costmap.update_zones(10.5) is None, "nothing changed, nothing to do"


def test_incremental_updates_equal_whole_map_recomputation_after_random_zone_changes(school: Site) -> None:
    policy = ZonePolicy(stale="unknown", caution_cost=180)
    costmap, layer = school_costmap(school, policy)
    rng = random.Random(6)
    nodes = [(n.id, n.zone) for n in school.spec.nodes]
    seq = dict.fromkeys((n for n, _ in nodes), 0)
    now = 0.0
    updates = 0
    seen: set[int] = set()
    for step in range(60):
        now += rng.choice([0.5, 1.0, 4.0, 16.0])
        kind = rng.random()
        if kind < 0.6:
            node, zone = rng.choice(nodes)
            seq[node] += 1
            state = rng.choice(["blocked", "clear", "caution"])
            msg = ZoneState.model_validate({"zone": zone, "node": node, "state": state, "seq": seq[node]})
            layer.on_zone_state(msg, now)
        elif kind < 0.7:
            node, _ = rng.choice(nodes)
            layer.on_node_status(NodeStatus(node=node, status=rng.choice(["online", "offline"])), now)
        elif kind < 0.85:
            x, y = rng.uniform(2, 45), rng.uniform(2, 25)
            square = [(x, y), (x + 1.5, y), (x + 1.5, y + 1.5), (x, y + 1.5)]
            block = OperatorBlock(polygon=square, expires_at=now + rng.choice([1.0, 30.0]))
            layer.on_operator_block(f"b{step % 3}", block, now)
        else:
            zone = rng.choice([z.id for z in school.spec.zones])
            layer.on_operator_block("zone-block", OperatorBlock(zone=zone, expires_at=now + 5.0), now)
        if costmap.update_zones(now) is not None:
            updates += 1
        seen |= set(layer.zone_costs().values())
        incremental = costmap.master.copy()
        costmap.rebuild()
        assert np.array_equal(incremental, costmap.master), (
            f"step {step}: bounded update differs from whole map"
        )
    assert updates >= 30, "the sequence must actually change the map"
    assert {FREE_SPACE, 180, LETHAL_OBSTACLE, NO_INFORMATION} <= seen, "every kind of zone cost was exercised"


def test_a_zone_merges_like_costmap_2d_update_with_max_so_unknown_never_hides_walls(school: Site) -> None:
    """costmap_2d's updateWithMax: a layer's NO_INFORMATION is skipped and a lower cost never lowers master.

    Stale zones read as unknown must leave master exactly as the map alone makes it (the walls inside z1 stay
    lethal and keep seeding inflation); a caution zone keeps its walls lethal; blocked is lethal throughout.
    An overwriting merge (or a plain numeric maximum, where 255 beats 254) fails here.
    """
    costmap, layer = school_costmap(school, ZonePolicy(stale="unknown", caution_cost=150))
    map_only = LayeredCostmap(school.grid, INFLATION, obstacle_layer=False)
    walls = static_layer(school.grid) == LETHAL_OBSTACLE
    window = layer.zone_window("z1")
    z1_walls = np.zeros(walls.shape, dtype=bool)
    z1_walls[window.rows, window.cols] = window.mask & walls[window.rows, window.cols]
    assert z1_walls.sum() > 100, "z1 covers walls: the case the merge must get right"

    layer.on_zone_state(ZoneState(zone="z1", node="n1", state="clear", seq=1), 1.0)
    costmap.update_zones(1.0)
    assert np.array_equal(costmap.master, map_only.master), "a clear zone changes nothing"
    costmap.update_zones(100.0)  # every node silent for far more than 3 heartbeats: stale, read as unknown
    assert set(layer.zone_costs().values()) == {NO_INFORMATION}
    assert np.array_equal(costmap.master, map_only.master), "an unknown zone changes nothing in master"
    assert (costmap.master[z1_walls] == LETHAL_OBSTACLE).all()

    layer.on_zone_state(ZoneState(zone="z1", node="n1", state="caution", seq=2), 101.0)
    layer.on_zone_state(ZoneState(zone="z1", node="n2", state="caution", seq=1), 101.0)
    costmap.update_zones(101.0)
    z1_cells = np.zeros(walls.shape, dtype=bool)
    z1_cells[window.rows, window.cols] = window.mask
    assert (costmap.master[z1_walls] == LETHAL_OBSTACLE).all(), "a caution cost never lowers a wall"
    assert (costmap.master[z1_cells & ~walls] >= 150).all()
    incremental = costmap.master.copy()
    costmap.rebuild()
    assert np.array_equal(incremental, costmap.master)


def test_zone_costs_are_painted_by_policy(school: Site) -> None:
    costmap, layer = school_costmap(school, ZonePolicy(caution_cost=150))
    layer.on_zone_state(ZoneState(zone="z4", node="n5", state="caution", seq=1), 1.0)
    costmap.update_zones(1.0)
    window = layer.zone_window("z4")
    zone_cells = zone_costs(costmap)[window.rows, window.cols][window.mask]
    assert set(np.unique(zone_cells).tolist()) == {150}
    x, y = 25.0, 15.0  # the middle of z4, the middle corridor
    assert costmap.cost_at(x, y) == 150
    assert not costmap.in_lethal(x, y)
    assert names_at(costmap, x, y) == []
    layer.on_zone_state(ZoneState(zone="z4", node="n5", state="blocked", seq=2), 2.0)
    costmap.update_zones(2.0)
    assert costmap.cost_at(x, y) == LETHAL_OBSTACLE
    assert costmap.in_lethal(x, y)
    assert names_at(costmap, x, y) == ["z4"]
    assert costmap.cost_at(-100.0, -100.0) == NO_INFORMATION


def test_areas_at_names_a_zone_the_robot_would_touch_and_operator_polygons(school: Site) -> None:
    costmap, layer = school_costmap(school)
    layer.on_operator_block("spill", OperatorBlock(polygon=[(30, 22), (31, 22), (31, 23.5), (30, 23.5)]), 0.0)
    layer.on_zone_state(ZoneState(zone="z1", node="n2", state="blocked", seq=7), 0.0)
    costmap.update_zones(0.0)
    assert names_at(costmap, 30.5, 22.8) == ["operator/spill"]
    # just outside z1's west edge (x 17.0), within the robot's radius: the goal is lethal because of z1
    assert costmap.in_lethal(16.95, 7.2)
    assert names_at(costmap, 16.95, 7.2) == ["z1"]
    assert names_at(costmap, 12.0, 7.2) == []


def test_local_window_is_master_around_the_robot_and_unknown_beyond_the_map(school: Site) -> None:
    costmap, _ = school_costmap(school)
    local, frame = costmap.local_window((12.0, 7.2, 0.0), 3.0)
    assert local.shape == (60, 60)
    row, col = costmap.frame.world_to_cell(frame.origin_x + 0.01, frame.origin_y + 0.01)
    assert np.array_equal(local, costmap.master[row : row + 60, col : col + 60])
    assert frame.cell_to_world(30, 30) == pytest.approx(
        costmap.frame.cell_to_world(*costmap.frame.world_to_cell(12.0, 7.2))
    )
    corner, _ = costmap.local_window((-1.0, -1.0, 0.0), 3.0)  # the map's bottom-left corner
    assert (corner[:30, :] == NO_INFORMATION).all() and (corner[:, :30] == NO_INFORMATION).all()


def test_planner_weights_follow_the_updates_and_plans_avoid_a_blocked_zone(school: Site) -> None:
    costmap, layer = school_costmap(school)
    params = PlannerParams()
    grid = school.grid
    start, goal = school.point("A")[:2], school.point("B")[:2]
    cache = PlannerWeights(params)
    free = plan_path(costmap.master, grid.resolution, grid.origin, start, goal, params, cache.of(costmap))
    layer.on_zone_state(ZoneState(zone="z1", node="n1", state="blocked", seq=1), 1.0)
    costmap.update_zones(1.0)
    weights = cache.of(costmap)
    assert np.array_equal(weights, weights_for(costmap.master, params))
    around = plan_path(costmap.master, grid.resolution, grid.origin, start, goal, params, weights)
    assert free.reachable and around.reachable
    assert around.length_m > free.length_m + 5.0
    crossed = [zone_costs(costmap)[r, c] for r, c in around.cells]
    assert LETHAL_OBSTACLE not in crossed


def test_planner_weights_of_a_planner_left_far_behind_are_recomputed_whole(school: Site) -> None:
    costmap, layer = school_costmap(school, ZonePolicy(caution_cost=150))
    params = PlannerParams()
    cache = PlannerWeights(params)
    cache.of(costmap)
    for i in range(CHANGE_LOG + 2):  # more updates than the costmap remembers
        state = "caution" if i % 2 == 0 else "clear"
        layer.on_zone_state(ZoneState(zone="z4", node="n5", state=state, seq=i + 1), float(i))
        assert costmap.update_zones(float(i)) is not None
    assert costmap.changes_since(0) is None
    assert np.array_equal(cache.of(costmap), weights_for(costmap.master, params))


class Puddle:
    """A layer written against the Layer protocol alone: a square of one cost, merged by `rule`; clearable."""

    def __init__(self, bounds: Bounds, cost: int, rule: MergeRule = update_with_max) -> None:
        self.bounds, self.rule, self._pending = bounds, rule, [bounds]
        self.costs = np.full(bounds.shape, cost, dtype=np.uint8)

    def update_bounds(self, bounds: list[Bounds]) -> list[Bounds]:
        out, self._pending = [*bounds, *self._pending], []
        return out

    def update_costs(self, master: np.ndarray, bounds: Bounds) -> None:
        common = self.bounds.intersection(bounds)
        if not common.empty:
            self.rule(master[common.within(bounds)], self.costs[common.within(self.bounds)])

    def clear(self, window: Bounds, *, outside: bool = False) -> bool:
        common = self.bounds.intersection(window)
        if outside or common.empty or (self.costs[common.within(self.bounds)] == NO_INFORMATION).all():
            return False
        self.costs[common.within(self.bounds)] = NO_INFORMATION
        self._pending.append(common)
        return True

    def rebuild(self) -> None:
        self._pending = []


def before_inflation(costmap: LayeredCostmap, layer: Layer) -> None:
    costmap.layers.insert(costmap.layers.index(costmap.inflation), layer)


def test_a_new_layer_is_one_class_in_the_stack_and_updates_only_its_bounds(school: Site) -> None:
    costmap, _ = school_costmap(school)
    before = costmap.master.copy()
    puddle = Puddle(Bounds(100, 300, 110, 320), 120)
    before_inflation(costmap, puddle)
    changed = costmap.update()
    assert changed is not None
    assert (costmap.master[puddle.bounds.rows, puddle.bounds.cols] >= 120).all()
    outside = np.ones(before.shape, dtype=bool)
    outside[changed.rows, changed.cols] = False
    assert np.array_equal(costmap.master[outside], before[outside]), (
        "nothing beyond the reported bounds moved"
    )
    bounded = costmap.master.copy()
    costmap.rebuild()
    assert np.array_equal(bounded, costmap.master), "the bounded update equals the whole-map recomputation"
    assert costmap.update() is None, "a layer with nothing new costs nothing"


def test_inflation_is_the_last_layer_of_the_list_called_like_the_others(school: Site) -> None:
    layer = ZoneRule(school.spec, GridFrame.of_grid(school.grid))
    robots = RobotsLayer(GridFrame.of_grid(school.grid))
    costmap = LayeredCostmap(school.grid, INFLATION, zone_layer=layer, robots_layer=robots)
    assert costmap.layers == [costmap.static, costmap.obstacles, costmap.zones, robots, costmap.inflation]
    assert isinstance(costmap.inflation, InflationLayer)
    # master is the list applied in order and nothing else: no inflation step beside it
    assert np.array_equal(costmap.merge(costmap.whole), costmap.master)
    assert np.array_equal(costmap.merge(costmap.whole, costmap.layers[:-1]), costmap.inflation.costs)


def test_the_layers_apply_in_the_order_of_the_list(school: Site) -> None:
    """A lethal square before inflation is inflated around; after it, it is lethal alone. An overwriting
    layer after the zone layer hides a blocked zone; before it, the zone's max merge wins over it."""
    costmap, layer = school_costmap(school)
    square = Bounds(370, 409, 374, 413)  # a hall, over 1.5 m from any wall
    next_to = (372, 414)  # two cells east of the square: within the robot's radius
    assert costmap.master[next_to] == FREE_SPACE
    lethal = Puddle(square, LETHAL_OBSTACLE)
    before_inflation(costmap, lethal)
    costmap.update()
    assert costmap.master[next_to] == INSCRIBED_INFLATED_OBSTACLE
    costmap.layers.remove(lethal)
    costmap.layers.append(Puddle(square, LETHAL_OBSTACLE))
    costmap.rebuild()
    assert (costmap.master[square.rows, square.cols] == LETHAL_OBSTACLE).all()
    assert costmap.master[next_to] == FREE_SPACE, "a layer after inflation is not inflated"

    costmap, layer = school_costmap(school)
    layer.on_operator_block("z4", OperatorBlock(zone="z4"), 0.0)
    costmap.update_zones(0.0)
    row, col = costmap.frame.world_to_cell(25.0, 15.0)  # the middle of z4
    assert costmap.inflation.costs[row, col] == LETHAL_OBSTACLE
    assert costmap.zones is not None
    zones_at = costmap.layers.index(costmap.zones)
    mop = Puddle(Bounds(row - 2, col - 2, row + 3, col + 3), FREE_SPACE, update_with_overwrite)
    costmap.layers.insert(zones_at + 1, mop)
    costmap.rebuild()
    assert costmap.inflation.costs[row, col] == FREE_SPACE, "after the zone layer, the overwrite wins"
    costmap.layers.remove(mop)
    costmap.layers.insert(zones_at, mop)
    costmap.rebuild()
    assert costmap.inflation.costs[row, col] == LETHAL_OBSTACLE, "before it, the zone's max merge wins"


def test_inflation_after_the_zone_layer_inflates_a_blocked_zone_and_not_a_caution_cost(school: Site) -> None:
    costmap, layer = school_costmap(school, ZonePolicy(caution_cost=150))
    window = layer.zone_window("z4")
    edge = Bounds.of_window(window)
    row, col = edge.row1 + 2, (edge.col0 + edge.col1) // 2  # 3 cells north of z4, mid-corridor
    free = int(costmap.master[row, col])
    layer.on_zone_state(ZoneState(zone="z4", node="n5", state="caution", seq=1), 1.0)
    costmap.update_zones(1.0)
    assert costmap.master[row, col] == free, "a caution cost is not lethal: nothing to inflate"
    layer.on_zone_state(ZoneState(zone="z4", node="n5", state="blocked", seq=2), 2.0)
    costmap.update_zones(2.0)
    lut = cost_lut(school.grid.resolution, INFLATION)
    assert costmap.master[row, col] == max(free, lut[3 * 3]), "the zone's edge spreads its cost 3 cells out"
    assert costmap.master[row, col] > free


def test_clear_empties_the_clearable_layers_in_a_window_and_master_is_inflated_again(tiny: Site) -> None:
    """Every layer is asked: the lidar's marks and a clearable extra layer go in the window only; the map and
    the blocked zone stay (a recovery must not drive the robot into a zone the network reports blocked)."""
    layer = ZoneRule(tiny.spec, GridFrame.of_grid(tiny.grid))
    costmap = LayeredCostmap(tiny.grid, INFLATION, zone_layer=layer)
    zone = tiny.spec.zones[1].id
    layer.on_operator_block("spill", OperatorBlock(zone=zone), 0.0)
    costmap.update_zones(0.0)
    with_zone = costmap.master.copy()
    assert (
        costmap.update_scan(scan_from((2.0, 1.25, 0.0), {0: 1.0, 180: 1.0})) is not None
    )  # hits at x 3 and 1
    puddle = Puddle(Bounds(20, 60, 30, 70), 120)
    before_inflation(costmap, puddle)
    costmap.update()
    assert costmap.cost_at(3.0, 1.25) == LETHAL_OBSTACLE and costmap.cost_at(1.0, 1.25) == LETHAL_OBSTACLE
    frame = costmap.frame
    _, col = frame.world_to_cell(3.0, 1.25)
    east = Bounds(0, col - 5, frame.height, frame.width)  # the map east of x 2.75: x 3's mark and the puddle
    version = costmap.version
    assert costmap.clear(east) is not None and costmap.version == version + 1
    assert costmap.cost_at(3.0, 1.25) < INSCRIBED_INFLATED_OBSTACLE, "cleared, and its inflation gone"
    assert costmap.cost_at(1.0, 1.25) == LETHAL_OBSTACLE, "a mark outside the window stays"
    assert costmap.cost_at(7.0, 1.5) == LETHAL_OBSTACLE, "the blocked zone in the window stays"
    assert (puddle.costs == NO_INFORMATION).all()
    cleared = costmap.master.copy()
    costmap.rebuild()
    assert np.array_equal(cleared, costmap.master), "re-inflated as the whole map would be"
    assert costmap.clear(east) is None, "nothing left to clear there"
    assert costmap.clear_except_region(3.0, 1.25, 1.0) is not None  # the mark at x 1 is outside that square
    costmap.layers.remove(puddle)
    costmap.rebuild()
    assert np.array_equal(costmap.master, with_zone), "the map and the blocked zone survive every clear"


def test_a_scan_marks_an_obstacle_and_a_later_scan_through_it_clears_it(tiny: Site) -> None:
    costmap = LayeredCostmap(tiny.grid, INFLATION)
    before = costmap.master.copy()
    pose = (2.0, 1.25, 0.0)
    assert costmap.update_scan(scan_from(pose, {0: 1.0})) is not None
    assert costmap.cost_at(3.0, 1.25) == LETHAL_OBSTACLE
    assert costmap.cost_at(2.95, 1.25) == INSCRIBED_INFLATED_OBSTACLE  # next cell: within the robot radius
    assert costmap.in_lethal(3.0, 1.25)
    marked = costmap.master.copy()
    costmap.rebuild()
    assert np.array_equal(marked, costmap.master)
    # The obstacle went away: the same beam now reaches 2.5 m, and nothing sees the old spot.
    bounds = costmap.update_scan(scan_from(pose, {0: 2.5}))
    assert bounds is not None
    assert costmap.cost_at(3.0, 1.25) < INSCRIBED_INFLATED_OBSTACLE
    assert costmap.cost_at(4.5, 1.25) == LETHAL_OBSTACLE, "the new hit is marked"
    costmap.update_scan(scan_from(pose, {}))
    assert np.array_equal(costmap.master, before), "a clear sweep leaves exactly the static map"
    assert costmap.update_scan(scan_from(pose, {})) is None


def test_a_beam_clears_up_to_a_cell_short_of_its_hit_and_leaves_marks_beyond_it(tiny: Site) -> None:
    costmap = LayeredCostmap(tiny.grid, INFLATION)
    layer = costmap.obstacles
    assert layer is not None
    frame = costmap.frame
    row, first = frame.world_to_cell(2.0, 1.25)
    _, last = frame.world_to_cell(4.0, 1.25)
    layer.marked[row, first : last + 1] = True  # marks left along the beam by earlier scans
    # Beam 0 from x 2.0 returns at 1.5 m (the others read nothing usable): points every half cell along it
    # are cleared while short of 1.45 m.
    assert layer.add_scan(scan_from((2.0, 1.25, 0.0), {0: 1.5} | {i: math.nan for i in range(1, 360)}))

    def marked(x: float) -> bool:
        r, c = frame.world_to_cell(x, 1.25)
        return bool(layer.marked[r, c])

    assert not any(marked(x) for x in np.arange(2.0, 3.425, 0.025)), "cleared along the beam"
    assert marked(3.47), "the last cell before the hit is not cleared"
    assert marked(3.5), "the hit is marked"
    assert marked(3.6) and marked(4.0), "nothing beyond the hit is cleared"
    assert not layer.marked[row + 1].any() and not layer.marked[row - 1].any()


def test_clearing_never_erases_the_static_map_and_far_hits_are_not_marked(tiny: Site) -> None:
    costmap = LayeredCostmap(tiny.grid, INFLATION, obstacle_range_m=2.0)
    static = costmap.master.copy()
    # From just above the bottom wall, beams pointing down pass through it with no return.
    costmap.update_scan(scan_from((3.0, 0.3, 0.0), {}))
    assert np.array_equal(costmap.master, static)
    assert costmap.cost_at(3.0, 0.02) == LETHAL_OBSTACLE
    assert costmap.update_scan(scan_from((2.0, 1.25, 0.0), {0: 2.5})) is None, (
        "beyond obstacle_range: no mark"
    )
    assert costmap.cost_at(4.5, 1.25) == FREE_SPACE


def test_a_scan_that_only_sees_the_static_walls_changes_nothing_and_costs_no_replanning(tiny: Site) -> None:
    costmap = LayeredCostmap(tiny.grid, INFLATION)
    static = costmap.master.copy()
    version = costmap.version
    # Straight down (beam 270) from 0.28 m above the bottom wall: the hit lands on a wall cell.
    assert costmap.update_scan(scan_from((3.0, 0.3, 0.0), {270: 0.28})) is None
    assert costmap.version == version, "an unchanged costmap keeps the planner's cached weights valid"
    assert np.array_equal(costmap.master, static)
    # A hit in free space still changes the map, and only around itself.
    bounds = costmap.update_scan(scan_from((3.0, 0.3, 0.0), {90: 0.8}))
    assert bounds is not None and costmap.version == version + 1
    assert bounds.shape[0] < costmap.frame.height and bounds.shape[1] < costmap.frame.width
    assert costmap.cost_at(3.0, 1.1) == LETHAL_OBSTACLE
    incremental = costmap.master.copy()
    costmap.rebuild()
    assert np.array_equal(incremental, costmap.master)


def test_without_obstacle_layer_scans_are_ignored(tiny: Site) -> None:
    costmap = LayeredCostmap(tiny.grid, INFLATION, obstacle_layer=False)
    assert costmap.update_scan(scan_from((2.0, 1.25, 0.0), {0: 1.0})) is None
    assert costmap.cost_at(3.0, 1.25) == FREE_SPACE
    assert costmap.update_zones(0.0) is None


@pytest.mark.parametrize("name", ["depot", "depot_keepout", "warehouse", "warehouse_keepout", "tb3_sandbox"])
def test_real_maps_block_each_zone_incrementally_as_the_whole_map_would(name: str) -> None:
    site = load_site(SITES / name)
    costmap, layer = school_costmap(site)
    for i, zone in enumerate(site.spec.zones):
        layer.on_operator_block(f"b{i}", OperatorBlock(zone=zone.id), float(i))
        assert costmap.update_zones(float(i)) is not None
        assert zone.id in layer.blocked_zones()
    incremental = costmap.master.copy()
    costmap.rebuild()
    assert np.array_equal(incremental, costmap.master)


def test_the_builtin_configs_name_todays_layers_and_a_config_may_name_others(
    school: Site, tmp_path: Path
) -> None:
    """Nav2's `plugins`: the list of layers is the configuration's. The built-in ones give exactly the lists
    the layer switches gave before; a config naming fewer layers builds only those, in its order."""
    from wsnav.robot_agent.agent_config import AgentConfig, AgentConfigError, load_agent_config

    fleet = ["static_layer", "obstacle_layer", "zone_layer", "robots_layer", "inflation_layer"]
    assert load_agent_config("default").layer_plugins() == [p for p in fleet if p != "zone_layer"]
    assert load_agent_config("zones").layer_plugins() == fleet
    assert load_agent_config("full").layer_plugins() == fleet
    for name in ("default", "zones", "full"):  # the switches, unset plugins: the same list as before
        switches = load_agent_config(name).model_copy(update={"plugins": None})
        assert switches.layer_plugins() == load_agent_config(name).layer_plugins()
    layer = ZoneRule(school.spec, GridFrame.of_grid(school.grid))
    plugins = AgentConfig(plugins=["static_layer", "zone_layer", "inflation_layer"]).layer_plugins()
    costmap = LayeredCostmap(school.grid, INFLATION, zone_layer=layer, plugins=plugins)
    assert [type(x).__name__ for x in costmap.layers] == ["StaticLayer", "ZoneCostLayer", "InflationLayer"]
    assert costmap.obstacles is None and costmap.robots is None
    assert AgentConfig(plugins=plugins).obstacle_layer is False
    for bad, says in [
        ("plugins: [static_layer, lidar, inflation_layer]\n", "unknown costmap plugin 'lidar'"),
        ("plugins: [static_layer, inflation_layer, inflation_layer]\n", "'inflation_layer' named twice"),
        ("plugins: [static_layer, zone_layer]\n", "lack 'inflation_layer'"),
        (
            "zone_layer: true\nplugins: [static_layer, inflation_layer]\n",
            "zone_layer: True but plugins leave out",
        ),
    ]:
        path = tmp_path / "agent.yaml"
        path.write_text(bad)
        with pytest.raises(AgentConfigError, match=says):
            load_agent_config(path)
