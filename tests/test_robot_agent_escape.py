"""A robot standing in a zone that becomes blocked drives out of it by the shortest way, then on to its goal by a
route that avoids the zone (or waits outside it when there is none); walls and what the lidar sees stay lethal
all the while, and once out it never goes back in. The costmap's escape view, then the real agent on the school
site through the real broker with a simulated TurtleBot3."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tests.robot_agent_rig import SCHOOL, Rig, distance_to_polygon
from wsnav.navigation.backend import LaserScan
from wsnav.navigation.behaviors.escape import ESCAPE_COST, ZoneEscape, plan_escape
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.planning.astar import PlannerParams
from wsnav.navigation.planning.global_planner import GlobalPlanner
from wsnav.schemas import topics
from wsnav.schemas.messages import OperatorBlock, SimObstacle, SimWorld, ZoneState
from wsnav.schemas.site import Site, load_site
from wsnav.zones.cost_values import INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE
from wsnav.zones.geometry import GridFrame
from wsnav.zones.zone_rule import BlockedArea, ZoneRule

RADIUS = 0.105
INSIDE_Z1 = (17.5, 7.2)
"""Half a metre into z1 (x 17..19 across the south corridor) from its west end."""
Z1_EAST_END = [(18.4, 5.9), (19.0, 5.9), (19.0, 8.5), (18.4, 8.5)]
"""What the nodes of z1 saw: something across the corridor at the zone's east end."""


def scan_from(pose: tuple[float, float, float], ranges: dict[int, float], beams: int = 360) -> LaserScan:
    """An LDS-01-like sweep: beam i at yaw + i degrees; beams not given see nothing (+inf)."""
    r = np.full(beams, np.inf, dtype=np.float32)
    for i, value in ranges.items():
        r[i] = value
    return LaserScan(0.0, pose, 0.0, 2 * math.pi / beams, 0.12, 3.5, r)


def test_the_escape_view_lets_the_robot_out_of_its_zone_and_never_into_walls_or_what_the_lidar_sees(
    school: Site,
) -> None:
    layer = ZoneRule(school.spec, GridFrame.of_grid(school.grid))
    costmap = LayeredCostmap(school.grid, InflationParams(inscribed_radius=RADIUS), zone_layer=layer)
    for node in ("n1", "n2"):
        layer.on_zone_state(ZoneState(zone="z1", node=node, state="blocked", seq=1), 1.0)
    costmap.update_zones(1.0)
    x, y = INSIDE_Z1
    costmap.update_scan(scan_from((x, y, 0.0), {0: 1.0}))  # the lidar sees something 1 m east, in z1
    master = costmap.master.copy()
    escape = ZoneEscape(costmap)
    z1 = BlockedArea("zone", "z1")
    assert costmap.in_lethal(x, y) and escape.areas_at(x, y) == [z1]

    view = escape.view(escape.areas_at(x, y))
    assert view is not None and view.areas == (z1,)
    assert np.array_equal(costmap.master, master), "the costmap itself is untouched"
    b = view.bounds
    local = master[b.rows, b.cols]
    row, col = costmap.frame.world_to_cell(x, y)
    assert view.costs[row - b.row0, col - b.col0] < INSCRIBED_INFLATED_OBSTACLE  # the robot may move
    # Walls and the lidar's mark keep their cost (and the mark its inscribed ring); only the zone relaxes.
    walls = costmap.static.costs[b.rows, b.cols] == LETHAL_OBSTACLE
    assert walls.any() and (view.costs[walls] == LETHAL_OBSTACLE).all()
    mr, mc = costmap.frame.world_to_cell(x + 1.0, y)
    assert view.costs[mr - b.row0, mc - b.col0] == LETHAL_OBSTACLE
    assert view.costs[mr - b.row0, mc - 1 - b.col0] >= INSCRIBED_INFLATED_OBSTACLE
    changed = view.costs != local
    assert changed.any()
    assert (local[changed] >= INSCRIBED_INFLATED_OBSTACLE).all()
    assert (view.costs[changed] >= ESCAPE_COST).all() and (
        view.costs[changed] < INSCRIBED_INFLATED_OBSTACLE
    ).all()
    # Every exit is a place where the robot's footprint is clear of the zone.
    for r, c in np.argwhere(view.exits)[::7]:
        assert escape.areas_at(*costmap.frame.cell_to_world(int(r) + b.row0, int(c) + b.col0)) == []

    planner = GlobalPlanner(PlannerParams(), 3)
    plan = plan_escape(planner, costmap, view, INSIDE_Z1, school.point("B")[:2])
    assert plan.reaches_goal and plan.onward is not None
    ex, ey = plan.out.path[-1]
    assert ex < 17.0 - RADIUS, "out by the near (west) end"
    assert escape.areas_at(ex, ey) == []
    zone = layer.zone_window("z1")
    onward = [(int(r) - zone.row0, int(c) - zone.col0) for r, c in plan.onward.cells]
    assert not any(
        0 <= r < zone.mask.shape[0] and 0 <= c < zone.mask.shape[1] and zone.mask[r, c] for r, c in onward
    ), "the route on never goes back into the zone"


def test_an_operator_polygon_block_is_left_like_a_zone(school: Site) -> None:
    layer = ZoneRule(school.spec, GridFrame.of_grid(school.grid))
    costmap = LayeredCostmap(school.grid, InflationParams(inscribed_radius=RADIUS), zone_layer=layer)
    spill = [(30.0, 22.0), (31.0, 22.0), (31.0, 23.5), (30.0, 23.5)]
    layer.on_operator_block("spill", OperatorBlock(polygon=spill), 0.0)
    costmap.update_zones(0.0)
    escape = ZoneEscape(costmap)
    here = (30.5, 22.8)
    assert costmap.in_lethal(*here) and escape.areas_at(*here) == [BlockedArea("block", "spill")]
    view = escape.view(escape.areas_at(*here))
    assert view is not None
    row, col = costmap.frame.world_to_cell(*here)
    assert view.costs[row - view.bounds.row0, col - view.bounds.col0] < INSCRIBED_INFLATED_OBSTACLE
    plan = plan_escape(GlobalPlanner(PlannerParams(), 3), costmap, view, here, school.point("B")[:2])
    assert plan.out.reachable and escape.areas_at(*plan.out.path[-1]) == []
    # Once the block is removed, there is nothing to leave.
    layer.on_operator_block("spill", None, 1.0)
    costmap.update_zones(1.0)
    assert escape.areas_at(*here) == [] and escape.view([BlockedArea("block", "spill")]) is None


def set_world(rig: Rig, obstacles: dict[str, list[tuple[float, float]]]) -> None:
    """The simulated world's obstacles (what the lidar and the bumper meet), taken in by the agent."""
    world = SimWorld(
        t=rig.clock.now(), obstacles=[SimObstacle(id=k, polygon=list(p)) for k, p in obstacles.items()]
    )
    target = rig.agent.stats.sim_worlds + 1
    rig.operator.publish(topics.sim_world(rig.site.name), world.to_payload(), qos=1, retain=True)
    rig.settle(lambda: rig.agent.stats.sim_worlds >= target, "the simulated world")


def z1_gap(rig: Rig, x: float, y: float) -> float:
    return distance_to_polygon(list(rig.site.spec.zone("z1").polygon), x, y)


def drive_into_z1_on_the_way_to_b(rig: Rig) -> None:
    rig.send_goal("B")
    first = rig.agent.navigator.plan_length_m
    assert first is not None and first < 35.0  # east through z1, up the middle corridor
    rig.drive(lambda: rig.robot.pose()[0] >= INSIDE_Z1[0])
    assert z1_gap(rig, *rig.robot.pose()[:2]) == 0.0


def test_a_robot_in_a_zone_that_becomes_blocked_leaves_it_by_the_near_end_and_goes_round_to_its_goal(
    tmp_path: Path,
) -> None:
    with Rig(tmp_path) as rig:
        drive_into_z1_on_the_way_to_b(rig)
        x0 = rig.robot.pose()[0]
        mark = len(rig.trajectory)
        set_world(rig, {"ob-z1": Z1_EAST_END})
        rig.set_zone("z1", "blocked")
        nav = rig.agent.navigator
        assert nav.state == "navigating" and nav.leaving is not None and nav.leaving.names == "z1"
        assert nav.reason == "leaving blocked zone z1"
        rig.drive(rig.finished, max_sim_s=700.0)
        statuses = rig.collect_statuses()
    assert rig.state() == "arrived"
    assert rig.robot.collisions == 0
    gaps = [z1_gap(rig, x, y) for x, y, _ in rig.trajectory[mark:]]
    out = next(i for i, g in enumerate(gaps) if g > RADIUS)
    assert all(g > RADIUS for g in gaps[out:]), "once out, the footprint never touches z1 again"
    assert max(x for x, _, _ in rig.trajectory[mark : mark + out + 1]) < x0 + 0.05, "out the west end"
    assert out * 0.05 < 20.0  # simulated seconds to get out of half a metre of zone
    assert rig.robot.distance_m > 55.0  # round by the west corridor, not 20 m on through z1
    kinds = [e.kind for e in nav.events]
    assert kinds.index("leaving") < kinds.index("left") < kinds.index("arrived")
    leaving = [s for s in statuses if s.reason == "leaving blocked zone z1"]
    assert leaving and all(s.state == "navigating" and s.blocked_zones == ["z1"] for s in leaving)
    assert statuses[-1].state == "arrived" and statuses[-1].goal == "B"


def test_with_the_only_way_on_through_the_zone_the_robot_leaves_it_and_waits_outside_until_it_clears(
    tmp_path: Path,
) -> None:
    z3 = list(load_site(SCHOOL).spec.zone("z3").polygon)
    with Rig(tmp_path) as rig:
        set_world(rig, {"ob-z3": z3})
        rig.set_zone("z3", "blocked")  # west of z1 the south corridor leads nowhere else now
        drive_into_z1_on_the_way_to_b(rig)
        set_world(rig, {"ob-z3": z3, "ob-z1": Z1_EAST_END})
        rig.set_zone("z1", "blocked")
        nav = rig.agent.navigator
        assert nav.state == "navigating" and nav.reason is not None
        assert nav.reason.startswith("leaving blocked zone z1; then waiting: no path to the goal")
        rig.drive(lambda: rig.state() != "navigating", max_sim_s=30.0)
        assert rig.state() == "waiting"
        assert nav.reason is not None and "z1" in nav.reason and "z3" in nav.reason
        x, y, _ = where = rig.robot.pose()
        assert RADIUS < z1_gap(rig, x, y) < 0.5, "stopped just outside the zone"
        assert x < 17.0
        rig.drive(lambda: rig.clock.now() > 60.0)
        assert rig.state() == "waiting"
        assert math.hypot(rig.robot.pose()[0] - where[0], rig.robot.pose()[1] - where[1]) < 0.02
        # The zone clears: the robot goes on by itself (once its lidar no longer sees the obstacle), through z1.
        set_world(rig, {"ob-z3": z3})
        rig.set_zone("z1", "clear")
        rig.drive(lambda: rig.state() != "waiting", max_sim_s=5.0)
        assert rig.state() == "navigating"
        rig.drive(rig.finished)
        statuses = rig.collect_statuses()
    assert rig.state() == "arrived"
    assert rig.robot.collisions == 0
    states = [s.state for s in statuses if s.state != "idle"]
    assert [a for a, b in zip(states, [None, *states], strict=False) if a != b] == [
        "navigating",
        "waiting",
        "navigating",
        "arrived",
    ]
