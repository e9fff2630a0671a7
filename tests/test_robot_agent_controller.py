"""The path follower driving the simulated TurtleBot3 along global plans on real maps (the school, the TurtleBot3
sandbox), in simulated time: it arrives without touching anything, and stops short of an obstacle that closes
its corridor, reporting `blocked`. The whole chain is real: the robot's lidar feeds the layered costmap's
obstacle layer, and the controller sees that costmap's 3 x 3 m rolling window."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest

from tests.conftest import SITES
from wsnav.navigation.backend import LaserScan, Velocity
from wsnav.navigation.control.controller import ControllerParams, ControlResult, PathFollower
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.planning.astar import plan_path
from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.schemas.messages import SimObstacle, SimWorld
from wsnav.schemas.site import Site, load_site
from wsnav.zones.geometry import GridFrame

CONTROL_DT = 0.05
INFLATION = InflationParams()
LOCAL_SIZE_M = 3.0


@dataclass
class Drive:
    results: list[ControlResult] = field(default_factory=list)
    min_clearance: float = math.inf
    time_s: float = 0.0


def drive(
    costmap: LayeredCostmap,
    bot: SimTurtleBot3,
    follower: PathFollower,
    limit_s: float,
    until: tuple[str, ...] = ("arrived",),
) -> Drive:
    """Controller at 20 Hz, physics at 0.05 s, scans into the costmap, until a status in `until` or `limit_s`."""
    out = Drive()
    t = 0.0
    seen: LaserScan | None = None
    while t < limit_s:
        scan = bot.scan()
        if scan is not None and scan is not seen:
            costmap.update_scan(scan)
            seen = scan
        local, frame = costmap.local_window(bot.pose(), LOCAL_SIZE_M)
        result = follower.compute(bot.pose(), bot.velocity(), local, frame)
        out.results.append(result)
        bot.command(result.velocity)
        t += CONTROL_DT
        bot.step(CONTROL_DT, t)
        out.min_clearance = min(out.min_clearance, bot.clearance(*bot.pose()[:2], reach=1.0))
        if result.status in until:
            break
    out.time_s = t
    return out


def start(
    site: Site, start: str, goal: str
) -> tuple[SimWorldGrid, LayeredCostmap, SimTurtleBot3, PathFollower, float]:
    """The robot at `start`, following the global plan to `goal` made on the static map."""
    world = SimWorldGrid(site.grid)
    costmap = LayeredCostmap(site.grid, INFLATION)
    a, b = site.point(start), site.point(goal)
    plan = plan_path(costmap.master, site.grid.resolution, site.grid.origin, a[:2], b[:2])
    assert plan.reachable
    bot = SimTurtleBot3("robot1", world, a)
    follower = PathFollower()
    follower.set_path(plan.path, goal_yaw=b[2])
    return world, costmap, bot, follower, plan.length_m


@pytest.mark.parametrize(
    ("site_name", "start_point", "goal"), [("school", "A", "B"), ("tb3_sandbox", "P1", "P2")]
)
def test_follows_a_global_plan_to_the_goal_without_touching_anything(
    site_name: str, start_point: str, goal: str
) -> None:
    site = load_site(SITES / site_name)
    _, costmap, bot, follower, length = start(site, start_point, goal)
    run = drive(costmap, bot, follower, limit_s=4 * length / 0.22 + 30)
    assert run.results[-1].status == "arrived"
    assert {r.status for r in run.results} <= {"following", "arrived"}
    gx, gy, gyaw = site.point(goal)
    x, y, yaw = bot.pose()
    assert math.hypot(gx - x, gy - y) <= 0.07
    assert abs(math.remainder(gyaw - yaw, 2 * math.pi)) <= 0.15
    assert bot.collisions == 0
    assert (
        run.min_clearance > bot.radius + 0.05
    )  # never nearer a wall than its own radius, with room to spare
    # It drives the plan, not a detour, and near the Burger's top speed where the corridors allow.
    assert length * 0.95 <= bot.distance_m <= length * 1.05
    assert run.time_s < 1.5 * length / 0.22 + 10


def test_an_obstacle_closing_the_corridor_makes_it_report_blocked_and_stop_short() -> None:
    site = load_site(SITES / "school")
    world, costmap, bot, follower, _ = start(site, "A", "B")
    # The plan runs east along the south corridor, through z1 (x 17..19).
    assert any(17.0 <= px <= 19.0 for px, _ in follower.path)
    first = drive(costmap, bot, follower, limit_s=5.0)
    assert first.results[-1].status == "following"
    # People fill z1 wall to wall: the world has them, and the lidar will show them to the costmap.
    z1 = site.spec.zone("z1").polygon
    world.apply(SimWorld(t=5.0, obstacles=[SimObstacle(id="crowd", zone="z1", polygon=z1)]))
    run = drive(costmap, bot, follower, limit_s=60.0, until=("blocked",))
    last = run.results[-1]
    assert last.status == "blocked" and last.velocity == Velocity(0.0, 0.0)
    assert "lethal" in last.reason or "inscribed" in last.reason
    # Blocked where the corridor is closed, not anywhere: within the check distance of the obstacle's face.
    assert 17.0 - 1.6 < bot.pose()[0] < 17.0 - bot.radius
    # It stays blocked and comes to rest without touching the obstacle.
    rest = drive(costmap, bot, follower, limit_s=3.0, until=())
    assert {r.status for r in rest.results} == {"blocked"}
    assert bot.velocity() == Velocity(0.0, 0.0)
    assert bot.collisions == 0 and bot.pose()[0] < 17.0 - bot.radius - 0.2
    assert min(run.min_clearance, rest.min_clearance) > bot.radius
    # Take the crowd away: the lidar clears the cells, and the path is free again.
    world.apply(SimWorld(t=70.0, obstacles=[]))
    resumed = drive(costmap, bot, follower, limit_s=200.0)
    assert resumed.results[-1].status == "arrived" and bot.collisions == 0


def test_it_turns_in_place_when_the_path_starts_behind_it() -> None:
    site = load_site(SITES / "school")
    bot = SimTurtleBot3("robot1", SimWorldGrid(site.grid), (12.0, 7.2, 0.0))
    follower = PathFollower()
    follower.set_path(np.array([[12.0, 7.2], [9.0, 7.2]]))
    run = drive(LayeredCostmap(site.grid, INFLATION), bot, follower, limit_s=3.0, until=())
    turning = [r for r in run.results if r.reason == "turning to path"]
    assert turning and all(r.velocity.linear == 0.0 for r in turning)
    assert abs(math.remainder(bot.pose()[2] - math.pi, 2 * math.pi)) < 0.5
    assert math.hypot(bot.pose()[0] - 12.0, bot.pose()[1] - 7.2) < 0.5


def test_it_slows_down_near_obstacles_and_in_tight_turns() -> None:
    frame = GridFrame(100, 100, 0.05, 0.0, 0.0)
    open_space = np.zeros((100, 100), dtype=np.uint8)
    follower = PathFollower()
    straight = np.array([[1.0, 2.5], [4.5, 2.5]])
    pose, odom = (1.0, 2.5, 0.0), Velocity(0.22, 0.0)
    follower.set_path(straight)
    fast = follower.compute(pose, odom, open_space, frame)
    assert fast.status == "following" and fast.velocity.linear == pytest.approx(0.22)
    near_wall = open_space.copy()
    near_wall[:, :] = 200  # cost 200: about 0.18 m from an obstacle
    follower.set_path(straight)
    slow = follower.compute(pose, odom, near_wall, frame)
    assert slow.status == "following" and slow.velocity.linear < 0.5 * fast.velocity.linear
    follower.set_path(np.array([[1.0, 2.5], [1.3, 2.5], [1.3, 4.5]]))
    turn = follower.compute((1.05, 2.5, 0.0), odom, open_space, frame)
    assert turn.velocity.linear < fast.velocity.linear and turn.velocity.angular > 0


def test_without_a_path_it_is_idle_and_still() -> None:
    frame = GridFrame(10, 10, 0.05, 0.0, 0.0)
    follower = PathFollower()
    idle = follower.compute((0.2, 0.2, 0.0), Velocity(0.0, 0.0), np.zeros((10, 10), np.uint8), frame)
    assert idle == ControlResult(Velocity(0.0, 0.0), "idle")
    follower.set_path(np.array([[0.2, 0.2], [0.4, 0.2]]))
    follower.clear()
    again = follower.compute((0.2, 0.2, 0.0), Velocity(0.0, 0.0), np.zeros((10, 10), np.uint8), frame)
    assert again.status == "idle"


def test_the_carrot_is_where_the_path_leaves_the_lookahead_circle_after_winding_long_around_the_robot() -> (
    None
):
    # 64 points (the first stretch the carrot search measures) on a 0.1 m circle around the robot, then out.
    angles = np.linspace(0.0, 3.0 * math.pi, 64)
    circle = np.column_stack([2.5 + 0.1 * np.cos(angles), 2.5 + 0.1 * np.sin(angles)])
    out = np.array([[2.5, 3.0], [2.5, 3.3], [2.5, 3.6]])
    follower = PathFollower(ControllerParams(path_step=1.0))  # keeps these points as they are
    follower.set_path(np.vstack([circle, out]))
    carrot = follower._carrot(2.5, 2.5, 0.3)
    # between the circle's last point (0.1 m away) and (2.5, 3.0) (0.5 m away), where the distance is 0.3 m
    assert carrot == pytest.approx(circle[-1] + (out[0] - circle[-1]) * 0.5)
    further = follower._carrot(2.5, 2.5, 0.65)  # between (2.5, 3.0) and (2.5, 3.3)
    assert further == pytest.approx([2.5, 3.15])
