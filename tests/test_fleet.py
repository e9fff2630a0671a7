"""A fleet on one site: robots see each other through their published statuses (the robots layer), a fixed rule
says who yields when two meet, and simulated robots share one world. The end-to-end tests run the agents on the
real broker, each robot with its own credentials and connection, in lock-step simulated time.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import SCHOOL
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.experiments.fleet_sim import FleetError, SimFleet, start_poses
from wsnav.experiments.single_run import BrokerAt
from wsnav.navigation.behaviors.right_of_way import must_yield_to
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.costmap.layers import OtherRobot, RobotsLayer
from wsnav.robot_agent.agent import RobotAgent
from wsnav.robot_agent.agent_config import load_agent_config
from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.runtime.clock import SimClock
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.messages import RobotStatus, SimWorld
from wsnav.schemas.site import Site, load_site
from wsnav.zones.cost_values import LETHAL_OBSTACLE
from wsnav.zones.geometry import GridFrame

REAL_TIMEOUT_S = 20.0


@pytest.fixture(scope="module")
def broker() -> Iterator[BrokerThread]:
    with BrokerThread(SCHOOL) as b:
        yield b


def other(robot: str, x: float, y: float, *, yaw: float = 0.0, state: str = "navigating", priority: int = 0,
          expires_at: float = 10.0, radius: float = 0.105) -> OtherRobot:  # fmt: skip
    return OtherRobot(robot, (x, y, yaw), radius, state, priority, expires_at)


# -- the robots layer -------------------------------------------------------------------------------------


def test_other_robots_are_lethal_where_they_stand_incrementally_as_a_rebuild_would_and_expire(
    school: Site,
) -> None:
    frame = GridFrame.of_grid(school.grid)
    layer = RobotsLayer(frame)
    costmap = LayeredCostmap(school.grid, InflationParams(0.105, 1.0, 3.0), robots_layer=layer)
    free_before = costmap.master.copy()
    rng = np.random.default_rng(3)
    for i in range(30):  # robots appear, move (overlapping each other at times) and go
        robot = f"robot{rng.integers(2, 5)}"
        x, y = 8.0 + rng.uniform(0, 1.5), 7.2 + rng.uniform(-0.3, 0.3)
        layer.put(other(robot, x, y, expires_at=float(i + 5)))
        layer.expire(float(i))
        costmap.update()
        incremental = costmap.master.copy()
        costmap.rebuild()
        np.testing.assert_array_equal(incremental, costmap.master)
    for robot in layer.robots.values():
        row, col = frame.world_to_cell(*robot.pose[:2])
        assert costmap.master[row, col] == LETHAL_OBSTACLE
        assert costmap.in_lethal(robot.pose[0] + 0.2, robot.pose[1])  # the two footprints would touch
    layer.expire(math.inf)
    costmap.update()
    np.testing.assert_array_equal(costmap.master, free_before)


def test_the_lidar_leaves_known_robots_to_the_robots_layer_so_they_leave_no_ghost_behind(
    school: Site,
) -> None:
    """A robot seen by the lidar and marked would stay marked after it drove on, wherever no later beam passes
    (it kept a robot of the fleet experiment waiting for minutes: "the goal is occupied by an obstacle")."""
    world = SimWorldGrid(school.grid)
    me = SimTurtleBot3("robot1", world, (9.0, 7.2, 0.0))
    SimTurtleBot3("robot2", world, (10.0, 7.2, math.pi))
    SimTurtleBot3("robot3", world, (9.0, 8.2, math.pi))  # unknown to the robots layer: marked as an obstacle
    me.step(0.05, 0.05)
    scan = me.scan()
    assert scan is not None
    frame = GridFrame.of_grid(school.grid)
    for known in (False, True):
        layer = RobotsLayer(frame)
        if known:
            layer.put(other("robot2", 10.05, 7.2, priority=1))  # its status is a little behind
        costmap = LayeredCostmap(school.grid, InflationParams(0.105, 1.0, 3.0), robots_layer=layer)
        costmap.update_scan(scan)
        assert costmap.obstacles is not None
        marked = costmap.obstacles.marked
        r2, c2 = frame.world_to_cell(10.0 - 0.105, 7.2)
        r3, c3 = frame.world_to_cell(9.0, 8.2 - 0.105)
        assert bool(marked[r2 - 1 : r2 + 2, c2 - 1 : c2 + 2].any()) is not known
        assert marked[r3 - 1 : r3 + 2, c3 - 1 : c3 + 2].any()


# -- who yields -------------------------------------------------------------------------------------------


def test_right_of_way_is_the_site_order_and_only_a_robot_driving_towards_this_one_is_waited_for() -> None:
    me = (0.0, 0.0, 0.0)  # heading +x, third in the site's list
    head_on = other("robot1", 1.0, 0.0, yaw=math.pi, priority=0)
    assert must_yield_to(me, 2, [head_on]) == head_on
    assert must_yield_to(me, 0, [other("robot3", 1.0, 0.0, yaw=math.pi, priority=2)]) is None  # I have it
    assert must_yield_to(me, 2, [other("robot1", 1.0, 0.0, yaw=0.0)]) is None  # going the same way
    assert must_yield_to(me, 2, [other("robot1", -1.0, 0.0, yaw=0.0)]) is None  # behind me
    assert must_yield_to(me, 2, [other("robot1", 3.0, 0.0, yaw=math.pi)]) is None  # still far
    assert must_yield_to(me, 2, [other("robot1", 1.0, 0.0, yaw=math.pi, state="waiting")]) is None
    crossing = other("robot2", 1.0, 0.8, yaw=-math.pi / 2 - 0.3, priority=1)
    assert must_yield_to(me, 2, [crossing, head_on]) == head_on  # the one with most right of way


# -- agents on the real broker ----------------------------------------------------------------------------


def connect(broker: BrokerThread, ident: str, clock: SimClock | None = None) -> MqttBus:
    return connect_with_credentials(broker.host, broker.port, broker.credentials(ident), clock=clock)


def test_an_agent_keeps_others_fresh_poses_only_and_drops_bad_statuses(
    school: Site, broker: BrokerThread
) -> None:
    clock = SimClock(1000.0)
    robot2 = connect(broker, "robot2")
    robot3 = connect(broker, "robot3")
    old = RobotStatus(robot="robot2", state="idle", pose=(30.0, 7.2, 0.0), t=10.0)
    robot2.publish(topics.robot_status(school.name, "robot2"), old.to_payload(), qos=1, retain=True)
    world = SimWorldGrid(school.grid)
    bus = connect(broker, "robot1", clock)
    agent = RobotAgent(
        school, load_agent_config("full"), SimTurtleBot3("robot1", world, (9.0, 7.2, 0.0)), bus, clock
    )
    assert agent.robots_layer is not None
    status3 = topics.robot_status(school.name, "robot3")
    operator = connect(broker, "operator")
    try:
        # The simulated world is subscribed last: once the agent has it, its other subscriptions are in place.
        operator.publish(topics.sim_world(school.name), SimWorld(t=0.0).to_payload(), qos=1, retain=True)
        deadline = time.monotonic() + REAL_TIMEOUT_S
        while agent.stats.sim_worlds == 0 and time.monotonic() < deadline:
            bus.wait(0.05)
            agent.step(clock.now())
        robot3.publish(status3, b'{"robot": "robot3", "state": "flying"}', qos=1)
        robot3.publish(status3, RobotStatus(robot="robot2", state="idle", pose=(1, 1, 0)).to_payload(), qos=1)
        here = RobotStatus(
            robot="robot3", state="navigating", pose=(12.0, 7.2, math.pi), t=1000.0, footprint_radius=0.3
        )
        robot3.publish(status3, here.to_payload(), qos=1)
        deadline = time.monotonic() + REAL_TIMEOUT_S
        while "robot3" not in agent.robots_layer.robots and time.monotonic() < deadline:
            bus.wait(0.05)
            agent.step(clock.now())
        assert set(agent.robots_layer.robots) == {"robot3"}  # robot2's retained status is 990 s old
        assert agent.robots_layer.robots["robot3"].radius == 0.105, (
            "the site's footprint, not the status's 0.3"
        )
        assert (
            agent.dropped()["robot_status_invalid"] == 2
        )  # an unknown state; robot2's name on robot3's topic
        assert agent.costmap.in_lethal(12.0 + 0.15, 7.2)
        clock.advance(2.5)
        agent.step(clock.now())
        assert not agent.robots_layer.robots  # robot3 went silent: forgotten
        assert not agent.costmap.in_lethal(12.0 + 0.15, 7.2)
    finally:
        robot2.publish(topics.robot_status(school.name, "robot2"), b"", qos=1, retain=True)
        for b in (bus, robot2, robot3, operator):
            b.close()


def test_a_site_with_one_robot_subscribes_to_no_other_robot(tmp_path: Path) -> None:
    site = load_site(tiny_site(tmp_path / "tiny"))
    world = SimWorldGrid(site.grid)
    robot = SimTurtleBot3("robot1", world, (1.0, 4.0, 0.0))
    with BrokerThread(tmp_path / "tiny") as b:
        bus = connect(b, "robot1")
        try:
            agent = RobotAgent(site, load_agent_config("full"), robot, bus, SimClock())
        finally:
            bus.close()
    assert agent.robots_layer is None
    assert not [s for s in agent.subscriptions() if "/robots/" in s and not s.endswith("/goal")]
    assert world.occupied_seen_by("robot1") is world.occupied  # the lidar's world is the map, uncopied


def test_two_robots_meeting_head_on_in_a_corridor_both_arrive_apart_and_the_later_one_says_it_yields(
    school: Site, broker: BrokerThread
) -> None:
    watcher = connect(broker, "operator")
    watcher.subscribe(topics.all_robot_statuses(school.name))
    at = BrokerAt(broker.host, broker.port, broker.credentials_dir)
    fleet = SimFleet(
        school, at, load_agent_config("full"), {"robot1": (8.0, 7.2, 0.0), "robot2": (16.0, 7.2, math.pi)}
    )
    try:
        fleet.start()
        fleet.set_goal("robot1", (15.0, 7.2, 0.0), "east")
        fleet.set_goal("robot2", (9.0, 7.2, math.pi), "west")
        closest = math.inf
        navs = [m.agent.navigator for m in fleet.members.values()]
        while not all(n.state == "arrived" for n in navs):
            assert fleet.clock.now() < 200.0, [
                m.agent.status(fleet.clock.now()) for m in fleet.members.values()
            ]
            fleet.step()
            closest = min(closest, fleet.min_separation_m())
        assert fleet.collisions == 0
        assert closest > 0.3  # footprints apart by more than a robot's width all the way (lidar alone: ~3 cm)
        reasons: dict[str, set[str]] = {"robot1": set(), "robot2": set()}
        deadline = time.monotonic() + REAL_TIMEOUT_S
        while not reasons["robot2"] and time.monotonic() < deadline:
            watcher.wait(0.05)
            for m in watcher.poll():
                status = RobotStatus.model_validate_json(m.payload)
                if status.reason and status.robot in reasons:
                    reasons[status.robot].add(status.reason)
        assert reasons["robot2"] == {
            "yielding to robot1: it has right of way (earlier in the site's robot list) and is coming this way"
        }
        assert not reasons["robot1"]  # it has right of way: it went round robot2
    finally:
        fleet.close()
        watcher.close()


def test_simulated_robots_are_obstacles_to_each_others_lidar_and_bumper(school: Site) -> None:
    world = SimWorldGrid(school.grid)
    a = SimTurtleBot3("robot1", world, (9.0, 7.2, 0.0))
    b = SimTurtleBot3("robot2", world, (10.0, 7.2, math.pi))
    a.step(0.05, 0.05)
    scan = a.scan()
    assert scan is not None and abs(float(scan.ranges[0]) - (1.0 - 0.105)) < 0.06  # robot2 ahead
    assert world.robot_touching("robot1", 9.8, 7.2, 0.105) == "robot2"
    from wsnav.navigation.backend import Velocity

    a.command(Velocity(0.22, 0.0))
    for i in range(100):
        a.step(0.05, 0.1 + 0.05 * i)
        a.command(Velocity(0.22, 0.0))
    assert a.collisions == 1 and a.pose()[0] < 10.0 - 0.2 + 1e-6  # stopped at robot2's footprint
    assert b.pose()[:2] == (10.0, 7.2)


def test_a_fleet_needs_a_start_point_for_every_robot(tmp_path: Path) -> None:
    site = load_site(tiny_site(tmp_path / "tiny"))
    with pytest.raises(FleetError, match="robot1 has no start point"):
        start_poses(site)


@pytest.mark.slow
def test_no_status_another_robot_publishes_stops_an_agent_or_widens_a_robot(
    school: Site, broker: BrokerThread
) -> None:
    """A robot credential is enough to publish these on its own topic. A pose of 1.7e308 (retained: at every
    start) killed every other agent with OverflowError; a 2 m footprint ahead of robot1 held it in place. Each is
    dropped and counted, or held to the site's footprint, and the agent goes on."""
    clock = SimClock(1000.0)
    robot3 = connect(broker, "robot3")
    status3 = topics.robot_status(school.name, "robot3")
    robot3.publish(
        status3, b'{"v":1,"robot":"robot3","state":"navigating","pose":[1.7e308,0,0]}', qos=1, retain=True
    )
    world = SimWorldGrid(school.grid)
    bus = connect(broker, "robot1", clock)
    agent = RobotAgent(
        school, load_agent_config("full"), SimTurtleBot3("robot1", world, (9.0, 7.2, 0.0)), bus, clock
    )
    assert agent.robots_layer is not None
    operator = connect(broker, "operator")
    try:
        operator.publish(topics.sim_world(school.name), SimWorld(t=0.0).to_payload(), qos=1, retain=True)
        deadline = time.monotonic() + REAL_TIMEOUT_S
        while agent.stats.sim_worlds == 0 and time.monotonic() < deadline:
            bus.wait(0.05)
            agent.step(clock.now())
        attacks = [
            b'{"v":1,"robot":"robot3","state":"navigating","pose":[0,0,1e308]}',
            b'{"v":1,"robot":"robot3","state":"navigating","pose":[12,7.2,0],"t":NaN}',
            b'{"v":1,"robot":"robot3","state":"navigating","pose":[5000,7.2,0],"t":1000}',
        ]
        for payload in attacks:
            robot3.publish(status3, payload, qos=1)
        wide = RobotStatus(
            robot="robot3", state="navigating", pose=(11.0, 7.2, math.pi), t=1000.0, footprint_radius=2.0
        )
        robot3.publish(status3, wide.to_payload(), qos=1)
        deadline = time.monotonic() + REAL_TIMEOUT_S
        while "robot3" not in agent.robots_layer.robots and time.monotonic() < deadline:
            bus.wait(0.05)
            agent.step(clock.now())
        assert agent.robots_layer.robots["robot3"].radius == 0.105
        dropped = agent.dropped()
        assert dropped["robot_status_invalid"] == 3, dropped  # the retained overflow, the huge yaw, the NaN
        assert dropped["robot_status_off_map"] == 1, dropped
        assert not agent.costmap.in_lethal(9.5, 7.2), "2 m of claimed footprint does not reach robot1"
        clock.advance(0.5)
        jump = RobotStatus(robot="robot3", state="navigating", pose=(30.0, 7.2, 0.0), t=1000.5)
        robot3.publish(status3, jump.to_payload(), qos=1)
        deadline = time.monotonic() + REAL_TIMEOUT_S
        while agent.dropped()["robot_status_jump"] == 0 and time.monotonic() < deadline:
            bus.wait(0.05)
            agent.step(clock.now())
        assert agent.robots_layer.robots["robot3"].pose[0] == 11.0, "19 m in half a second is not believed"
        agent.step(clock.now())
        assert agent.status(clock.now()).state == "idle"  # the agent is alive and answers
    finally:
        robot3.publish(status3, b"", qos=1, retain=True)
        for b in (bus, robot3, operator):
            b.close()


@pytest.mark.slow
def test_a_robot_yields_to_another_for_a_bounded_time_then_plans_round_it(
    school: Site, broker: BrokerThread
) -> None:
    """A stolen robot1 credential publishing `navigating` just ahead of robot3 kept it yielding for as long as it
    published (40 s seen). After `max_yield_s` (30 s) robot3 takes robot1 for an obstacle and drives on."""
    for other in ("robot1", "robot2"):  # earlier tests' robots left their last statuses retained
        link = connect(broker, other)
        link.publish_confirmed(topics.robot_status(school.name, other), b"", retain=True)
        link.close()
    clock = SimClock(1000.0)
    world = SimWorldGrid(school.grid)
    bus = connect(broker, "robot3", clock)
    agent = RobotAgent(
        school, load_agent_config("full"), SimTurtleBot3("robot3", world, (9.0, 7.2, 0.0)), bus, clock
    )
    fake = connect(broker, "robot1")
    operator = connect(broker, "operator")
    status1 = topics.robot_status(school.name, "robot1")
    try:
        operator.publish(topics.sim_world(school.name), SimWorld(t=0.0).to_payload(), qos=1, retain=True)
        deadline = time.monotonic() + REAL_TIMEOUT_S
        while agent.stats.sim_worlds == 0 and time.monotonic() < deadline:
            bus.wait(0.05)
            agent.step(clock.now())
        agent.set_goal(school.point("A"), "A", clock.now())
        states: list[tuple[float, str, str | None]] = []
        while clock.now() < 1040.0:
            claim = RobotStatus(robot="robot1", state="navigating", pose=(10.2, 7.2, math.pi), t=clock.now())
            fake.publish(status1, claim.to_payload(), qos=1)
            seen = agent.stats.robot_statuses
            deadline = time.monotonic() + REAL_TIMEOUT_S
            while agent.stats.robot_statuses == seen and time.monotonic() < deadline:
                bus.wait(0.05)
                agent.step(clock.now())
            status = agent.status(clock.now())
            states.append((clock.now(), status.state, status.reason))
            clock.advance(0.5)
            agent.step(clock.now())
        yielding = [
            t for t, _, reason in states if reason is not None and reason.startswith("yielding to robot1")
        ]
        assert yielding and yielding[0] < 1002.0, states[:6]
        assert 1029.0 <= yielding[-1] <= 1032.0, (
            "held for max_yield_s (30 s), not for as long as robot1 claims"
        )
        assert states[-1][1] == "navigating" and not (states[-1][2] or "").startswith("yielding"), states[-1]
    finally:
        for b in (bus, fake, operator):
            b.close()
