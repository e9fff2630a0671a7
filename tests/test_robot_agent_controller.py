"""The path follower driving the simulated TurtleBot3 along global plans on real maps (the school, the TurtleBot3
sandbox), in simulated time: it arrives without touching anything, and stops short of an obstacle that closes
its corridor, reporting `blocked`. The local costmap it sees is a 3 x 3 m window cut around the robot from the
static map plus what the world holds, inflated as costmap_2d does."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from numpy.typing import NDArray

from robot_agent.backend import Velocity
from robot_agent.controller import ControlResult, PathFollower
from robot_agent.global_planner import plan_path
from robot_agent.inflation import LETHAL_OBSTACLE, InflationParams, inflate, static_layer
from robot_agent.sim_turtlebot3 import SimTurtleBot3
from robot_agent.sim_world_grid import SimWorldGrid
from robot_agent.zone_geometry import GridFrame
from schemas.messages import SimObstacle, SimWorld
from schemas.site import Site, load_site
from tests.conftest import SITES

CONTROL_DT = 0.05
INFLATION = InflationParams()
LOCAL_SIZE_M = 3.0


def world_costs(site: Site, world: SimWorldGrid) -> NDArray[np.uint8]:
    """What a perfect obstacle layer would give: the static map with the world's obstacles lethal, inflated."""
    costs = static_layer(site.grid)
    costs[world.occupied] = LETHAL_OBSTACLE
    return inflate(costs, site.grid.resolution, INFLATION)


def local_window(
    costs: NDArray[np.uint8], frame: GridFrame, x: float, y: float
) -> tuple[NDArray[np.uint8], GridFrame]:
    """A rolling window of the costmap centred on the robot, with its own origin (a local costmap)."""
    half = int(LOCAL_SIZE_M / frame.resolution / 2)
    row, col = frame.world_to_cell(x, y)
    r0, c0 = max(row - half, 0), max(col - half, 0)
    r1, c1 = min(row + half, frame.height), min(col + half, frame.width)
    window = costs[r0:r1, c0:c1]
    origin_x, origin_y = frame.origin_x + c0 * frame.resolution, frame.origin_y + r0 * frame.resolution
    return window, GridFrame(c1 - c0, r1 - r0, frame.resolution, origin_x, origin_y)


@dataclass
class Drive:
    results: list[ControlResult] = field(default_factory=list)
    min_clearance: float = math.inf
    time_s: float = 0.0


def drive(
    site: Site,
    world: SimWorldGrid,
    bot: SimTurtleBot3,
    follower: PathFollower,
    limit_s: float,
    costs: NDArray[np.uint8] | None = None,
    until: tuple[str, ...] = ("arrived",),
) -> Drive:
    """Controller at 20 Hz, physics at 0.05 s, until a status in `until` or `limit_s` of simulated time."""
    out = Drive()
    full = costs if costs is not None else world_costs(site, world)
    t = 0.0
    while t < limit_s:
        x, y, _ = bot.pose()
        local, frame = local_window(full, world.frame, x, y)
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


def follow(site_name: str, start: str, goal: str) -> tuple[Site, SimTurtleBot3, PathFollower, Drive, float]:
    site = load_site(SITES / site_name)
    world = SimWorldGrid(site.grid)
    costs = world_costs(site, world)
    a, b = site.point(start), site.point(goal)
    plan = plan_path(costs, site.grid.resolution, site.grid.origin, a[:2], b[:2])
    assert plan.reachable
    bot = SimTurtleBot3("robot1", world, a)
    follower = PathFollower()
    follower.set_path(plan.path, goal_yaw=b[2])
    run = drive(site, world, bot, follower, limit_s=4 * plan.length_m / 0.22 + 30, costs=costs)
    return site, bot, follower, run, plan.length_m


@pytest.mark.parametrize(("site_name", "start", "goal"), [("school", "A", "B"), ("tb3_sandbox", "P1", "P2")])
def test_follows_a_global_plan_to_the_goal_without_touching_anything(
    site_name: str, start: str, goal: str
) -> None:
    site, bot, _, run, length = follow(site_name, start, goal)
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
    world = SimWorldGrid(site.grid)
    a, b = site.point("A"), site.point("B")
    plan = plan_path(world_costs(site, world), site.grid.resolution, site.grid.origin, a[:2], b[:2])
    z1 = site.spec.zone("z1").polygon  # the plan runs east along the south corridor, through z1 (x 17..19)
    assert any(17.0 <= px <= 19.0 for px, _ in plan.densify(0.1))
    bot = SimTurtleBot3("robot1", world, a)
    follower = PathFollower()
    follower.set_path(plan.path, goal_yaw=b[2])
    first = drive(site, world, bot, follower, limit_s=5.0)
    assert first.results[-1].status == "following"
    # People fill z1 wall to wall: the world has them, the local costmap sees them.
    world.apply(SimWorld(t=5.0, obstacles=[SimObstacle(id="crowd", zone="z1", polygon=z1)]))
    run = drive(site, world, bot, follower, limit_s=60.0, until=("blocked",))
    last = run.results[-1]
    assert last.status == "blocked" and last.velocity == Velocity(0.0, 0.0)
    assert "lethal" in last.reason or "inscribed" in last.reason
    # Blocked where the corridor is closed, not anywhere: within the check distance of the obstacle's face.
    x_blocked = bot.pose()[0]
    assert 17.0 - 1.6 < x_blocked < 17.0 - bot.radius
    # It stays blocked and comes to rest without touching the obstacle.
    rest = drive(site, world, bot, follower, limit_s=3.0, until=())
    assert {r.status for r in rest.results} == {"blocked"}
    assert bot.velocity() == Velocity(0.0, 0.0)
    assert bot.collisions == 0 and bot.pose()[0] < 17.0 - bot.radius - 0.2
    assert min(run.min_clearance, rest.min_clearance) > bot.radius


def test_it_turns_in_place_when_the_path_starts_behind_it() -> None:
    site = load_site(SITES / "school")
    world = SimWorldGrid(site.grid)
    bot = SimTurtleBot3("robot1", world, (12.0, 7.2, 0.0))
    follower = PathFollower()
    follower.set_path(np.array([[12.0, 7.2], [9.0, 7.2]]))
    run = drive(site, world, bot, follower, limit_s=3.0, until=())
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
