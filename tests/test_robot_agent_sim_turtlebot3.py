"""The simulated TurtleBot3 Burger on the school map: its limits, its kinematics, its bumper, its lidar's rate."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.conftest import SITES
from wsnav.navigation.backend import RobotBackend, Velocity
from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3, TurtleBot3Params
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.schemas.messages import SimObstacle, SimWorld
from wsnav.schemas.site import load_site

DT = 0.05
# The school's south corridor is free from y 6.0 to 8.4 (layout.yaml); at x 10.5 neither wall has a door,
# and eastwards it runs free to the zone z1 at x 17.
OPEN = (10.5, 7.2)


@pytest.fixture
def world() -> SimWorldGrid:
    return SimWorldGrid(load_site(SITES / "school").grid)


def run(bot: SimTurtleBot3, seconds: float, t0: float = 0.0) -> float:
    steps = round(seconds / DT)
    for i in range(1, steps + 1):
        bot.step(DT, t0 + i * DT)
    return t0 + steps * DT


def test_it_is_a_robot_backend(world: SimWorldGrid) -> None:
    bot: RobotBackend = SimTurtleBot3("robot1", world, (*OPEN, 0.0))
    assert bot.robot_id == "robot1" and bot.radius == 0.105
    assert bot.pose() == (*OPEN, 0.0) and bot.velocity() == Velocity(0.0, 0.0)
    assert bot.scan() is None


def test_commands_are_clamped_to_the_burgers_limits_and_accelerate_gradually(world: SimWorldGrid) -> None:
    bot = SimTurtleBot3("robot1", world, (*OPEN, 0.0))
    bot.command(Velocity(1.0, -10.0))
    assert bot.commanded == Velocity(0.22, -2.84)
    bot.step(DT, DT)
    v = bot.velocity()
    assert v.linear == pytest.approx(2.5 * DT) and v.angular == pytest.approx(-3.2 * DT)
    run(bot, 1.0, DT)
    assert bot.velocity() == Velocity(0.22, -2.84)
    bot.command(Velocity(float("nan"), 0.0))  # garbage in: the base stops rather than run away
    assert bot.commanded == Velocity(0.0, 0.0)
    bot.stop()
    bot.step(DT, 2.0)
    assert 0.0 < bot.velocity().linear < 0.22  # decelerating, not stopping dead
    run(bot, 1.0, 2.0)
    assert bot.velocity() == Velocity(0.0, 0.0)


def test_a_straight_line_integrates_to_speed_times_time(world: SimWorldGrid) -> None:
    bot = SimTurtleBot3("robot1", world, (*OPEN, 0.0))
    bot.command(Velocity(0.2, 0.0))
    run(bot, 5.0)
    x, y, yaw = bot.pose()
    # 0.2 m/s for 5 s less the 0.08 s ramp at 2.5 m/s^2 (half of 0.2 * 0.08 lost), to the substep.
    assert x - OPEN[0] == pytest.approx(0.2 * 5.0 - 0.5 * 0.2 * 0.08, abs=0.003)
    assert y == pytest.approx(OPEN[1], abs=1e-9) and yaw == 0.0
    assert bot.distance_m == pytest.approx(x - OPEN[0])
    assert bot.collisions == 0


def test_a_turn_follows_a_circle_of_radius_v_over_w(world: SimWorldGrid) -> None:
    bot = SimTurtleBot3("robot1", world, (*OPEN, 0.3))
    bot.command(Velocity(0.1, 0.5))
    run(bot, 0.5)  # past both ramps
    centres = []
    for _ in range(40):
        run(bot, DT)
        x, y, yaw = bot.pose()
        centres.append((x - 0.2 * math.sin(yaw), y + 0.2 * math.cos(yaw)))
    spread = np.ptp(np.array(centres), axis=0)
    assert float(spread.max()) < 1e-9
    before = bot.pose()
    run(bot, 250 * DT)  # 12.5 s at 0.5 rad/s: just short of a full turn
    x, y, yaw = bot.pose()
    assert yaw == pytest.approx(math.remainder(before[2] + 0.5 * 12.5, 2 * math.pi), abs=1e-9)
    assert math.hypot(x - before[0], y - before[1]) == pytest.approx(
        2 * 0.2 * math.sin((2 * math.pi - 6.25) / 2)
    )
    # Odometry: 0.1 m/s over the whole run, less the 0.04 s ramp (to the 0.02 s substep).
    assert bot.distance_m == pytest.approx(0.1 * (0.5 + 40 * DT + 12.5) - 0.5 * 0.1 * 0.04, abs=2e-3)


def test_turning_in_place_changes_only_the_heading(world: SimWorldGrid) -> None:
    bot = SimTurtleBot3("robot1", world, (*OPEN, 0.0))
    bot.command(Velocity(0.0, 1.0))
    run(bot, 1.0)
    x, y, yaw = bot.pose()
    assert (x, y) == OPEN
    # 1 rad/s reached after 1/3.2 s: 1 s of turning less half the ramp, to the substep.
    assert yaw == pytest.approx(1.0 - 0.5 / 3.2, abs=0.02)
    assert bot.distance_m == 0.0


def test_driving_into_a_wall_counts_one_collision_and_stops_at_the_wall(world: SimWorldGrid) -> None:
    bot = SimTurtleBot3("robot1", world, (*OPEN, math.pi / 2))
    bot.command(Velocity(0.22, 0.0))
    t = run(bot, 10.0)
    assert bot.collisions == 1
    assert bot.in_contact and bot.velocity() == Velocity(0.0, 0.0)
    # The north wall's face is y 8.4: the bumper rests on it, it does not go through.
    assert bot.pose()[1] == pytest.approx(8.4 - 0.105, abs=0.005)
    assert bot.clearance(*bot.pose()[:2]) >= 0.105
    # Turning on the spot is always possible for a round robot; backing off frees it, driving in again counts.
    bot.command(Velocity(0.0, 1.0))
    t = run(bot, 0.5, t)
    assert bot.collisions == 1
    bot.command(Velocity(-0.1, 0.0))
    t = run(bot, 1.0, t)
    assert not bot.in_contact and bot.pose()[1] < 8.4 - 0.105 - 0.05
    bot.command(Velocity(0.22, 0.0))
    bot.step(DT, t + DT)  # heading is no longer north: it scrapes along, but touches again
    run(bot, 10.0, t + DT)
    assert bot.collisions == 2


def test_an_obstacle_placed_in_the_world_is_hit_and_seen(world: SimWorldGrid) -> None:
    bot = SimTurtleBot3("robot1", world, (*OPEN, 0.0))
    world.apply(
        SimWorld(
            t=0.0,
            obstacles=[SimObstacle(id="z1", zone="z1", polygon=[(17, 5.9), (19, 5.9), (19, 8.5), (17, 8.5)])],
        )
    )
    bot.command(Velocity(0.22, 0.0))
    run(bot, 40.0)
    assert bot.collisions == 1
    assert bot.pose()[0] == pytest.approx(17.0 - 0.105, abs=0.005)
    scan = bot.scan()
    assert scan is not None and scan.ranges[0] == -np.inf  # 0.105 m ahead: nearer than the lidar can measure
    assert scan.ranges[40] == pytest.approx(0.105 / math.cos(math.radians(40)), abs=0.006)


def test_the_lidar_sweeps_at_its_rate_stamped_with_simulated_time(world: SimWorldGrid) -> None:
    bot = SimTurtleBot3("robot1", world, (*OPEN, 0.0))
    stamps = []
    for i in range(1, 41):
        bot.step(DT, 100.0 + i * DT)
        scan = bot.scan()
        assert scan is not None
        if not stamps or scan.stamp != stamps[-1]:
            stamps.append(scan.stamp)
    assert np.diff(stamps) == pytest.approx([0.2] * (len(stamps) - 1))
    assert len(stamps) == 10 and stamps[0] == pytest.approx(100.05)
    scan = bot.scan()
    assert scan is not None and scan.ranges[90] == pytest.approx(1.2, abs=0.05)


def test_an_obstacle_dropped_on_the_robot_lets_it_drive_out(world: SimWorldGrid) -> None:
    bot = SimTurtleBot3("robot1", world, (17.5, 7.2, math.pi))
    world.apply(
        SimWorld(
            t=0.0, obstacles=[SimObstacle(id="z1", polygon=[(17, 5.9), (19, 5.9), (19, 8.5), (17, 8.5)])]
        )
    )
    bot.command(Velocity(0.22, 0.0))
    run(bot, 5.0)
    assert bot.pose()[0] < 17.0 - 0.105 and not bot.overlaps(*bot.pose()[:2])


def test_bad_steps_and_limits_are_refused(world: SimWorldGrid) -> None:
    bot = SimTurtleBot3("robot1", world, (*OPEN, 0.0))
    with pytest.raises(ValueError, match="dt"):
        bot.step(-0.1, 0.0)
    with pytest.raises(ValueError, match="positive"):
        TurtleBot3Params(radius=0.0)


def test_the_bumpers_clearance_matches_a_brute_force_search_near_and_far_from_walls(
    world: SimWorldGrid,
) -> None:
    """The far-from-everything shortcut must never hide a contact: compare with every occupied square."""
    bot = SimTurtleBot3("r", world, (12.0, 7.2, 0.0))
    res = world.frame.resolution
    rows, cols = np.nonzero(world.occupied)
    x0 = world.frame.origin_x + cols * res
    y0 = world.frame.origin_y + rows * res
    rng = np.random.default_rng(3)
    limit = bot.params.radius + res
    near = 0
    for x, y in rng.uniform((0.0, 0.0), (50.0, 30.0), size=(400, 2)):
        dx = np.maximum(np.maximum(x0 - x, 0.0), x - (x0 + res))
        dy = np.maximum(np.maximum(y0 - y, 0.0), y - (y0 + res))
        exact = min(float(np.hypot(dx, dy).min()), limit)
        assert bot.clearance(float(x), float(y)) == pytest.approx(exact, abs=1e-9)
        near += exact < limit
    assert near > 0, "some samples must fall near a wall for the comparison to mean anything"


def test_velocity_noise_scatters_the_drive_around_the_command_and_follows_the_seed(
    world: SimWorldGrid,
) -> None:
    def drive(seed: int, noise: float) -> tuple[float, float]:
        bot = SimTurtleBot3("r", world, (12.0, 7.2, 0.0), TurtleBot3Params(velocity_noise=noise), seed=seed)
        t = 0.0
        for _ in range(100):  # 10 s of 0.2 m/s, commanded at 10 Hz as the controller does
            bot.command(Velocity(0.2, 0.0))
            t = run(bot, 0.1, t)
        return bot.pose()[0], bot.pose()[1]

    exact = drive(1, 0.0)
    assert exact[0] == pytest.approx(12.0 + 2.0, abs=0.02)
    runs = [drive(seed, 0.03) for seed in range(8)]
    assert drive(3, 0.03) == runs[3], "the same seed drives the same way"
    xs = np.array([x for x, _ in runs])
    assert float(xs.std()) > 0.002, "runs differ"
    assert abs(float(xs.mean()) - exact[0]) < 0.03, "but around the commanded motion"
    with pytest.raises(ValueError, match="velocity_noise"):
        TurtleBot3Params(velocity_noise=-0.1)
