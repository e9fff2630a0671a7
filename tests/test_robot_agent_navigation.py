"""How the agent's configuration changes the robot's behaviour, on the school site through the real broker:
a lidar-only robot finds the blocked corridor when it gets there and replans because the controller is blocked;
the stock configuration replans on a 5 Hz timer, the full one only on events."""

from __future__ import annotations

from pathlib import Path

from tests.robot_agent_rig import LIDAR_RANGE_M, Rig, distance_to_polygon
from wsnav.robot_agent.agent_config import load_agent_config


def drive_a_to_b_with_z4_obstructed(rig: Rig, *, tell_the_agent: bool) -> None:
    rig.place_obstacles("z4")
    if tell_the_agent:
        rig.set_zone("z4", "blocked")
    rig.send_goal("B")
    rig.drive(rig.finished)


def entered_z4(rig: Rig) -> bool:
    polygon = list(rig.site.spec.zone("z4").polygon)
    return any(distance_to_polygon(polygon, x, y) == 0.0 for x, y, _ in rig.trajectory)


def test_without_the_zone_layer_the_lidar_finds_the_obstacle_and_the_blocked_controller_replans(
    tmp_path: Path,
) -> None:
    lidar_only = load_agent_config("full").model_copy(update={"zone_layer": False, "name": "lidar-only"})
    with Rig(tmp_path, config=lidar_only) as rig:
        drive_a_to_b_with_z4_obstructed(rig, tell_the_agent=False)
    nav = rig.agent.navigator
    assert nav.state == "arrived"
    assert rig.robot.collisions == 0 and not entered_z4(rig)
    assert nav.replans_by["blocked"] >= 1 and nav.replans_by["periodic"] == 0
    first = next(e for e in nav.events if e.kind == "replan" and e.trigger == "blocked")
    assert first.pose is not None
    gap = distance_to_polygon(list(rig.site.spec.zone("z4").polygon), first.pose[0], first.pose[1])
    assert gap < LIDAR_RANGE_M  # it had to get close enough to see it
    assert rig.robot.distance_m > 55.0  # there and back: more than the 52 m detour


def test_stock_config_replans_at_5_hz_and_full_only_on_events(tmp_path: Path) -> None:
    """The rates are honoured tick by tick: the experiment compares the agents' CPU on this."""
    rigs = {}
    for name in ("default", "full"):
        with Rig(tmp_path / name, config=name) as rig:
            rig.set_zone("z4", "blocked")  # only the full agent listens
            rig.send_goal("B")
            rig.drive(lambda: rig.clock.now() >= 20.0)
        rigs[name] = rig
    stock, full = rigs["default"].agent, rigs["full"].agent
    assert stock.blocked_zones() == [] and full.blocked_zones() == ["z4"]
    assert 99 <= stock.navigator.replans_by["periodic"] <= 101
    assert stock.navigator.replans == stock.navigator.replans_by["periodic"]
    assert full.navigator.replans == 0 and full.navigator.plans == 1
    assert 199 <= stock.stats.costmap_scans <= 201  # 10 Hz
    assert 99 <= full.stats.costmap_scans <= 101  # 5 Hz
    assert stock.navigator.plan_length_m is not None and full.navigator.plan_length_m is not None
    assert full.navigator.plan_length_m > stock.navigator.plan_length_m + 10.0  # full knows about z4


def test_a_flapping_zone_cannot_make_the_robot_replan_without_end(tmp_path: Path) -> None:
    """A node flipping its zone on the route between blocked and clear, 20 times a second over MQTT, caused one
    replan per flip (4,077 in 41 s seen); the robot replans for zone changes at most every 0.5 s, and the last
    word still counts: the zone left blocked, the robot goes round it."""
    with Rig(tmp_path / "flap", config="full") as rig:
        rig.send_goal("B")
        rig.drive(lambda: rig.clock.now() >= 2.0)
        before = rig.agent.navigator.replans_by["zone"]
        for i in range(100):  # 5 s of simulated time
            rig.set_zone("z1", "blocked" if i % 2 == 0 else "clear")
            until = rig.clock.now() + 0.05
            rig.drive(lambda: rig.clock.now() >= until)  # noqa: B023  (called before `until` changes)
        rig.set_zone("z1", "blocked")
        rig.drive(lambda: rig.clock.now() >= 9.0)
        flaps = rig.agent.navigator.replans_by["zone"] - before
        assert 5 <= flaps <= 13, flaps  # 5 s of flapping at one replan per 0.5 s, and the last word
        assert rig.agent.blocked_zones() == ["z1"] and rig.state() == "navigating"
        assert rig.agent.navigator.last_plan is not None and rig.agent.navigator.last_plan.reachable
