"""Stock move_base's oscillation detection and recovery behaviours, as the `default` robot now runs them: a robot
that gets nowhere for 10 s runs conservative reset, rotation, aggressive reset, rotation, then aborts; moving
0.2 m starts the sequence afresh; the resets clear the lidar's marks outside their square and keep the rest."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.robot_agent_rig import scan_from
from tests.site_fixtures import tiny_site
from wsnav.navigation.backend import Pose, Velocity
from wsnav.navigation.behaviors.recovery import MoveBaseRecovery, RecoveryParams
from wsnav.navigation.control.controller import ControlResult
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.navigator import Mode, Navigator, NavigatorParams
from wsnav.navigation.planning.astar import PlannerParams
from wsnav.navigation.planning.global_planner import GlobalPlanner
from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.schemas.site import Site, load_site
from wsnav.zones.cost_values import LETHAL_OBSTACLE
from wsnav.zones.geometry import GridFrame

INFLATION = InflationParams(inscribed_radius=0.105, inflation_radius=1.0, cost_scaling_factor=3.0)
DT = 0.05


@pytest.fixture
def tiny(tmp_path: Path) -> Site:
    return load_site(tiny_site(tmp_path / "tiny"))


class Dithering:
    """A local planner caught between two global plans: it turns left, then right, and never gets anywhere."""

    def __init__(self) -> None:
        self.calls = 0

    def set_path(self, path: np.ndarray, goal_yaw: float | None = None) -> None:
        pass

    def clear(self) -> None:
        pass

    def compute(self, pose: Pose, odom: Velocity, costs: np.ndarray, frame: GridFrame) -> ControlResult:
        self.calls += 1
        return ControlResult(Velocity(0.0, 0.5 if (self.calls // 10) % 2 else -0.5), "following")


def test_a_robot_that_gets_nowhere_runs_move_bases_recoveries_in_order_then_aborts(tiny: Site) -> None:
    costmap = LayeredCostmap(tiny.grid, INFLATION)
    robot = SimTurtleBot3("robot1", SimWorldGrid(tiny.grid), (1.0, 4.0, 0.0))
    nav = Navigator(
        costmap,
        GlobalPlanner(PlannerParams()),
        Dithering(),
        robot,
        NavigatorParams(replan_rate_hz=5.0, recovery=RecoveryParams()),
    )
    nav.set_goal((9.0, 4.0, 0.0), "B", 0.0)
    yaws: list[float] = []
    t = 0.0
    while t < 120.0 and nav.state == "navigating":
        nav.step(t)
        robot.step(DT, t + DT)
        t += DT
        yaws.append(robot.pose()[2])
    recoveries = [(e.t, e.detail) for e in nav.events if e.kind == "recovery"]
    assert [d for _, d in recoveries] == [
        "conservative_reset (oscillation)",
        "rotate_recovery (oscillation)",
        "aggressive_reset (oscillation)",
        "rotate_recovery (oscillation)",
    ]
    assert recoveries[0][0] == pytest.approx(10.0, abs=0.2), "oscillation_timeout: 10 s without 0.2 m"
    assert recoveries[1][0] - recoveries[0][0] == pytest.approx(10.0, abs=0.2)
    assert nav.state == "cancelled"
    assert nav.reason == "aborted: the robot appears to be oscillating even after all recovery behaviours"
    assert nav.recovery is not None and nav.recovery.run == 4
    # Each rotate_recovery turned the robot a full turn in place (its heading unwrapped over the run).
    turned = np.abs(np.diff(np.unwrap(np.asarray(yaws))))
    assert turned.sum() > 2 * (2 * math.pi - 0.2)
    assert math.hypot(robot.pose()[0] - 1.0, robot.pose()[1] - 4.0) < 0.05


def test_moving_0_2_m_starts_the_recovery_sequence_afresh() -> None:
    rec = MoveBaseRecovery(RecoveryParams())
    rec.start_goal(0.0, (0.0, 0.0, 0.0))
    assert not rec.control_cycle(5.0, (0.1, 0.0, 0.0))
    assert rec.control_cycle(10.1, (0.19, 0.0, 0.0)), "0.19 m in 10 s is oscillating"
    assert rec.next_behaviour("oscillation") == "conservative_reset"
    rec.behaviour_done(10.1)
    assert rec.control_cycle(20.2, (0.1, 0.0, 0.0))
    assert rec.next_behaviour("oscillation") == "rotate_recovery"
    rec.behaviour_done(20.2)
    assert not rec.control_cycle(21.0, (0.5, 0.0, 0.0)), "0.2 m made: the timeout restarts"
    assert rec.control_cycle(31.1, (0.5, 0.0, 0.0))
    assert rec.next_behaviour("oscillation") == "conservative_reset", "and the sequence with it"


def test_planner_patience_applies_to_stock_move_base_and_not_to_algorithm_3() -> None:
    stock, waits = MoveBaseRecovery(RecoveryParams()), MoveBaseRecovery(RecoveryParams(on_no_path=False))
    for rec in (stock, waits):
        rec.start_goal(0.0, (0.0, 0.0, 0.0))
        assert not rec.plan_failed(1.0)
    assert stock.plan_failed(6.1) and not waits.plan_failed(6.1)


def test_a_reset_clears_the_lidar_marks_outside_its_square_and_keeps_the_walls(tiny: Site) -> None:
    costmap = LayeredCostmap(tiny.grid, INFLATION)
    walls = costmap.master.copy()
    pose = (5.0, 1.25, 0.0)
    costmap.update_scan(scan_from(pose, {0: 1.0, 180: 2.5}))  # marks at 1.0 m ahead and 2.5 m behind
    assert costmap.cost_at(6.0, 1.25) == LETHAL_OBSTACLE
    assert costmap.cost_at(2.5, 1.25) == LETHAL_OBSTACLE
    assert costmap.clear_except_region(5.0, 1.25, 3.0) is not None  # conservative_reset_dist 3
    assert costmap.cost_at(6.0, 1.25) == LETHAL_OBSTACLE, "inside the square: kept"
    assert costmap.cost_at(2.5, 1.25) < LETHAL_OBSTACLE, "outside: cleared"
    assert costmap.clear_except_region(5.0, 1.25, 0.59) is not None  # aggressive: 4 circumscribed radii
    assert np.array_equal(costmap.master, walls), "only the static map is left"
    assert costmap.clear_except_region(5.0, 1.25, 0.59) is None
    # The next costmap update takes the newest sweep in again, as costmap_2d's observation buffer does.
    assert costmap.update_scan(scan_from(pose, {0: 1.0})) is not None
    assert costmap.cost_at(6.0, 1.25) == LETHAL_OBSTACLE


def test_a_robot_held_for_another_robot_runs_no_recovery_when_released(tiny: Site) -> None:
    """Yielding to a robot with right of way is a wait on purpose: released after 20 s, the robot drives on
    instead of taking the wait for an oscillation (move_base's rule would fire at once: 10 s without 0.2 m)."""
    costmap = LayeredCostmap(tiny.grid, INFLATION)
    robot = SimTurtleBot3("robot1", SimWorldGrid(tiny.grid), (1.0, 4.0, 0.0))
    planner = GlobalPlanner(PlannerParams())
    nav = Navigator(costmap, planner, Dithering(), robot, NavigatorParams(recovery=RecoveryParams()))
    nav.set_goal((9.0, 4.0, 0.0), "B", 0.0)
    nav.hold(0.5, "yielding to robot2")
    t = 0.5
    while t < 20.5:
        nav.step(t)
        robot.step(DT, t + DT)
        t += DT
    assert nav.state == "waiting"
    nav.release(t)
    for _ in range(20):  # a second of control cycles
        nav.step(t)
        robot.step(DT, t + DT)
        t += DT
    assert nav.state == "navigating"
    assert not [e for e in nav.events if e.kind == "recovery"]


def test_a_robot_held_during_a_recovery_rotation_stops_turning_and_follows_its_plan_when_released(
    tiny: Site,
) -> None:
    """Held for right of way in the middle of rotate_recovery, the robot reported "resumed" when released and
    went on turning in place (the rotation flag outlived the hold). Held drops the behaviour; released, the
    controller drives again."""
    costmap = LayeredCostmap(tiny.grid, INFLATION)
    robot = SimTurtleBot3("robot1", SimWorldGrid(tiny.grid), (1.0, 4.0, 0.0))
    controller = Dithering()
    nav = Navigator(
        costmap, GlobalPlanner(PlannerParams()), controller, robot, NavigatorParams(recovery=RecoveryParams())
    )
    nav.set_goal((9.0, 4.0, 0.0), "B", 0.0)
    t = 0.0
    while nav.reason != "recovery: rotate_recovery" and t < 60.0:
        nav.step(t)
        robot.step(DT, t + DT)
        t += DT
    assert nav.mode is Mode.CLEARING, "the dithering robot got to move_base's second behaviour"
    nav.hold(t, "yielding to robot2")
    assert (nav.mode, nav.state, nav.holding) == (Mode.HELD, "waiting", "yielding to robot2")
    for _ in range(20):
        nav.step(t)
        robot.step(DT, t + DT)
        t += DT
    assert abs(robot.velocity().angular) < 1e-6, "held: not turning"
    nav.release(t)
    calls = controller.calls
    for _ in range(20):
        nav.step(t)
        robot.step(DT, t + DT)
        t += DT
    assert (nav.mode, nav.reason) == (Mode.CONTROLLING, None)
    assert controller.calls >= calls + 8, (
        "released, the controller drives at 10 Hz (not the abandoned rotation)"
    )
    assert [e.kind for e in nav.events][-1] == "resumed"
