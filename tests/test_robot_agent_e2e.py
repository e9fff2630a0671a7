"""The robot agent end to end: the school site on the real amqtt broker, zone states from the nodes' own
credentials, goals from the operator, the agent on robot1's MQTT connection driving a simulated TurtleBot3 in
lock-step simulated time, and its status read back over MQTT."""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import SCHOOL
from tests.robot_agent_rig import LIDAR_RANGE_M, REAL_TIMEOUT_S, Rig, connect, distance_to_polygon
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.runtime.drop_log import DROP_LOG_INTERVAL
from wsnav.schemas import topics
from wsnav.schemas.messages import RobotStatus


def z4_polygon(rig: Rig) -> list[tuple[float, float]]:
    return list(rig.site.spec.zone("z4").polygon)


def entered(rig: Rig, zone: str) -> bool:
    polygon = list(rig.site.spec.zone(zone).polygon)
    return any(distance_to_polygon(polygon, x, y) == 0.0 for x, y, _ in rig.trajectory)


def test_z4_blocked_before_the_start_the_robot_plans_around_it_and_reaches_b(tmp_path: Path) -> None:
    with Rig(tmp_path) as rig:
        rig.block("z4")
        rig.send_goal("B")
        path = rig.agent.navigator.path.copy()
        rig.drive(rig.finished)
        statuses = rig.collect_statuses()
        # Status is retained: an operator who connects now still learns where the robot is and that it arrived.
        rig.operator.close()
        late = connect(rig.broker, "operator")
        late.subscribe("wsn/school/robots/+/status")
        assert late.wait(10.0)
        retained = [RobotStatus.model_validate_json(m.payload) for m in late.poll()]
        late.close()
    assert [(s.state, s.goal, s.t) for s in retained] == [("arrived", "B", statuses[-1].t)]
    assert rig.state() == "arrived"
    assert rig.robot.collisions == 0
    assert not entered(rig, "z4")
    assert min(distance_to_polygon(z4_polygon(rig), x, y) for x, y in path) > 0.1
    # The detour is the long way round: the direct route through z4 is ~30 m.
    assert rig.robot.distance_m > 45.0
    assert statuses[-1].state == "arrived" and statuses[-1].goal == "B"
    assert all(s.blocked_zones == ["z4"] for s in statuses if s.state != "idle")
    x, y, _ = statuses[-1].pose
    bx, by, _ = rig.site.point("B")
    assert np.hypot(x - bx, y - by) < 0.2


def test_z4_blocked_while_driving_replans_at_once_before_the_lidar_could_see_it(tmp_path: Path) -> None:
    with Rig(tmp_path) as rig:
        rig.send_goal("B")
        first_length = rig.agent.navigator.plan_length_m
        assert first_length is not None and first_length < 35.0  # straight up the middle corridor
        rig.drive(lambda: rig.robot.distance_m > 3.0)
        assert rig.agent.navigator.replans == 0
        rig.block("z4")
        # Handled in the step that took the message in, at this simulated instant: no driving in between.
        replan = [e for e in rig.agent.navigator.events if e.kind == "replan" and e.trigger == "zone"]
        assert len(replan) == 1
        assert replan[0].pose is not None
        gap = distance_to_polygon(z4_polygon(rig), replan[0].pose[0], replan[0].pose[1])
        assert gap > LIDAR_RANGE_M
        detour = rig.agent.navigator.plan_length_m
        rig.drive(rig.finished)
        statuses = rig.collect_statuses()
    assert rig.state() == "arrived"
    assert detour is not None and detour > first_length + 10.0
    assert rig.robot.collisions == 0
    assert not entered(rig, "z4")
    # The operator saw it over MQTT: the first status counting the replan names z4, far from it.
    seen = next(s for s in statuses if s.replans >= 1)
    assert seen.state == "navigating" and seen.blocked_zones == ["z4"]
    assert distance_to_polygon(z4_polygon(rig), seen.pose[0], seen.pose[1]) > LIDAR_RANGE_M
    assert statuses[-1].state == "arrived"


def test_a_goal_in_a_zone_that_becomes_blocked_is_cancelled_naming_the_zone(tmp_path: Path) -> None:
    with Rig(tmp_path) as rig:
        rig.send_goal((25.0, 15.0, 1.5708))  # the middle of z4
        rig.drive(lambda: rig.robot.distance_m > 2.0)
        assert rig.state() == "navigating"
        rig.block("z4")
        assert rig.state() == "cancelled"
        where = rig.robot.pose()
        rig.drive(lambda: rig.clock.now() > 20.0)  # cancelled means stopped: it stays put
        statuses = rig.collect_statuses()
    assert np.hypot(rig.robot.pose()[0] - where[0], rig.robot.pose()[1] - where[1]) < 0.1
    last = statuses[-1]
    assert last.state == "cancelled"
    assert last.reason is not None and "z4" in last.reason
    assert rig.robot.collisions == 0


def test_a_goal_already_in_a_blocked_zone_is_cancelled_at_once(tmp_path: Path) -> None:
    with Rig(tmp_path) as rig:
        rig.set_zone("z1", "blocked")
        rig.send_goal((18.0, 7.2, 0.0))
        statuses = rig.collect_statuses()
    assert rig.state() == "cancelled"
    assert statuses[-1].state == "cancelled" and statuses[-1].reason is not None
    assert "z1" in statuses[-1].reason
    assert rig.agent.navigator.plans == 0


def test_every_way_blocked_waits_then_resumes_by_itself_when_a_zone_clears(tmp_path: Path) -> None:
    with Rig(tmp_path) as rig:
        rig.place_obstacles("z1", "z3")
        rig.set_zone("z1", "blocked")
        rig.set_zone("z3", "blocked")
        rig.send_goal("B")
        assert rig.state() == "waiting"
        rig.drive(lambda: rig.clock.now() > 30.0)
        assert rig.state() == "waiting"
        assert rig.robot.distance_m < 0.05  # stopped while it waits
        rig.place_obstacles("z3")
        rig.set_zone("z1", "clear")
        assert rig.state() == "navigating"
        rig.drive(rig.finished)
        statuses = rig.collect_statuses()
    assert rig.state() == "arrived"
    assert rig.robot.collisions == 0
    assert not entered(rig, "z3")
    states = [s.state for s in statuses if s.state != "idle"]
    assert [a for a, b in zip(states, [None, *states], strict=False) if a != b] == [
        "waiting",
        "navigating",
        "arrived",
    ]
    waiting = next(s for s in statuses if s.state == "waiting")
    assert waiting.reason is not None and "z1" in waiting.reason and "z3" in waiting.reason
    resumed = [e for e in rig.agent.navigator.events if e.kind == "resumed"]
    assert resumed and resumed[0].trigger == "zone"


def test_garbage_and_spoofed_messages_change_nothing_and_are_counted(tmp_path: Path) -> None:
    with Rig(tmp_path) as rig:
        rig.set_zone("z4", "clear")  # seq 101 from n5 and n6
        rig.send_goal("B")
        rig.drive(lambda: rig.robot.distance_m > 1.0)
        master = rig.agent.costmap.master.copy()
        before = (rig.state(), rig.agent.navigator.plans, rig.agent.navigator.path.copy())
        intake = rig.agent.intake
        assert intake is not None
        accepted = intake.accepted
        site = rig.site.name
        n5_topic = f"wsn/{site}/zones/z4/state/n5"
        n5 = rig.node("n5")
        for payload in [
            b"not json at all",
            b'{"v": 1, "zone": "z4", "node": "n6", "state": "blocked", "seq": 500}',  # n5 speaking for n6
            b'{"v": 1, "zone": "z1", "node": "n5", "state": "blocked", "seq": 501}',  # topic says z4
            b'{"v": 1, "zone": "z4", "node": "n5", "state": "on fire", "seq": 502}',
            b'{"v": 1, "zone": "z4", "node": "n5", "state": "blocked", "seq": 50}',  # replayed, older seq
            b'{"v": 1, "zone": "z4", "node": "n5", "state": "blocked", "seq": 503, "pad": "'
            + b"x" * 2000
            + b'"}',
            b"\xff\xfe\x00",
        ]:
            n5.publish(n5_topic, payload, qos=1)
        # n1 watches z1: the broker's ACL refuses its writes to z4's topics (never delivered at all).
        n1 = rig.node("n1")
        n1.publish(
            f"wsn/{site}/zones/z4/state/n5", b'{"v":1,"zone":"z4","node":"n5","state":"blocked","seq":900}'
        )
        n1.publish(
            f"wsn/{site}/zones/z4/state/n1", b'{"v":1,"zone":"z4","node":"n1","state":"blocked","seq":901}'
        )
        rig.operator.publish(f"wsn/{site}/robots/robot1/goal", b'{"v": 1, "goal": "nowhere"}')
        rig.operator.publish(f"wsn/{site}/robots/robot1/goal", b"{")
        rig.operator.publish(f"wsn/{site}/robots/robot1/goal", b'{"v": 1, "goal": [500.0, 3.0, 0.0]}')
        rig.operator.publish(f"wsn/{site}/robots/robot1/goal", b'{"v": 1, "goal": [0.05, 0.05, 0.0]}')
        rig.operator.publish(f"wsn/{site}/operator/blocks/b1", b'{"v": 1, "zone": "z99"}')
        # Sentinels: a client's messages arrive in order, so once these are in, everything above was handled.
        rig.set_zone("z4", "clear")
        rig.set_zone("z1", "clear")
        dropped = rig.agent.dropped
        rig.settle(lambda: dropped()["goal_invalid"] >= 1 and dropped()["unknown_zone"] >= 1, "the garbage")
        assert intake.accepted == accepted + 4  # the sentinels only (n5, n6, n1, n2)
        assert dict(rig.agent.dropped()) == {
            "malformed": 2,
            "mismatch": 2,
            "invalid": 1,
            "old_seq": 1,
            "oversized": 1,
            "goal_unknown_point": 1,
            "goal_invalid": 1,
            "goal_off_map": 1,
            "goal_in_wall": 1,
            "unknown_zone": 1,
        }
        assert np.array_equal(rig.agent.costmap.master, master)
        assert rig.agent.blocked_zones() == []
        assert (rig.state(), rig.agent.navigator.plans) == before[:2]
        assert np.array_equal(rig.agent.navigator.path, before[2])
        rig.drive(rig.finished)
    assert rig.state() == "arrived"
    assert rig.robot.distance_m < 35.0  # straight through z4, which nobody honest blocked
    assert rig.robot.collisions == 0


def test_an_operator_block_detours_the_robot_and_its_removal_brings_it_back(tmp_path: Path) -> None:
    with Rig(tmp_path) as rig:
        rig.send_goal("B")
        rig.drive(lambda: rig.robot.distance_m > 2.0)
        intake = rig.agent.intake
        assert intake is not None
        topic = "wsn/school/operator/blocks/spill"
        for payload, length in ((b'{"v": 1, "zone": "z4", "reason": "spill"}', "detour"), (b"", "direct")):
            accepted = intake.accepted
            rig.operator.publish(topic, payload, qos=1, retain=True)
            rig.settle(lambda a=accepted: intake.accepted > a, f"the operator block ({length})")
            # zone replans come at most every 0.5 s: the second change may wait for the interval's end
            until = rig.clock.now() + 0.6
            rig.drive(lambda: rig.clock.now() >= until)  # noqa: B023  (called before `until` changes)
            plan = rig.agent.navigator.plan_length_m
            assert plan is not None
            assert (plan > 45.0) if length == "detour" else (plan < 35.0)
        rig.drive(rig.finished)
    assert rig.state() == "arrived"
    assert rig.agent.navigator.replans_by["zone"] == 2
    assert rig.robot.distance_m < 35.0 and rig.robot.collisions == 0


def agent_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "wsnav.robot_agent.agent"]


def test_forged_statuses_and_goals_are_logged_once_per_kind_then_summed_up_with_a_count(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """60 forged statuses of robot2 and 60 bad goals used to give one line in all: now one line per kind at
    once, then one line with the count of the rest after the interval (the zone intake's rule)."""
    caplog.set_level(logging.WARNING, logger="wsnav.robot_agent.agent")  # a worker quiets it in-process
    with Rig(tmp_path) as rig:
        robot2 = connect(rig.broker, "robot2")
        try:
            site = rig.site.name
            for i in range(60):
                robot2.publish(
                    topics.robot_status(site, "robot2"), b'{"v": 1, "robot": "robot2", "uptime": %d}' % i
                )
                rig.operator.publish(topics.robot_goal(site, "robot1"), b'{"v": 1, "goal": "nowhere%d"}' % i)
            dropped = rig.agent.dropped
            rig.settle(
                lambda: dropped()["robot_status_invalid"] == 60 and dropped()["goal_unknown_point"] == 60,
                "the forgeries",
            )
            lines = agent_lines(caplog)
            assert len(lines) == 2, lines
            assert any(
                "dropped wsn/school/robots/robot2/status (robot_status_invalid)" in line for line in lines
            )
            assert any("(goal_unknown_point)" in line for line in lines)
            rig.clock.advance(DROP_LOG_INTERVAL + 1.0)
            rig.agent.step(rig.clock.now())
            summaries = agent_lines(caplog)[2:]
            assert len(summaries) == 2, summaries
            assert any("dropped 59 messages (robot_status_invalid)" in line for line in summaries), summaries
            assert any("dropped 59 messages (goal_unknown_point)" in line for line in summaries), summaries
        finally:
            robot2.close()  # else its loop thread outlives the test, reconnecting


def test_a_broker_outage_is_said_once_with_the_stale_policy_and_its_end_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="wsnav.robot_agent.agent")  # a worker quiets it in-process
    with Rig(tmp_path) as rig:
        port, creds = rig.broker.port, tmp_path / "creds"
        shutil.copytree(rig.broker.credentials_dir, creds)  # the broker's own are removed when it stops
        rig.broker.stop()
        # Noticed at once: a shutdown aborts every connection it has not closed within SHUTDOWN_GRACE_S (before
        # that, a stop under load left one open twice in whole-suite runs, and paho saw it only after two
        # keepalives, 60 s). The deadline is generous: this test is about what the agent says.
        deadline = time.monotonic() + 3 * REAL_TIMEOUT_S
        while rig.agent_bus.connected:
            assert time.monotonic() < deadline, "the agent's bus did not notice the broker was gone"
            time.sleep(0.05)
        for _ in range(50):  # 5 simulated seconds of the agent's loop during the outage
            rig.clock.advance(0.1)
            rig.agent.step(rig.clock.now())
        down = [line for line in agent_lines(caplog) if "link" in line]
        assert len(down) == 1, down
        assert "robot1: broker link down" in down[0] and "stale policy 'keep'" in down[0], down
        with BrokerThread(SCHOOL, creds, port=port):
            deadline = time.monotonic() + REAL_TIMEOUT_S
            while not rig.agent_bus.connected:
                assert time.monotonic() < deadline, "the agent's bus did not reconnect"
                rig.agent_bus.wait(0.1)
            for _ in range(20):
                rig.clock.advance(0.1)
                rig.agent.step(rig.clock.now())
            link = [line for line in agent_lines(caplog) if "link" in line]
            assert len(link) == 2 and "robot1: broker link back after 5 s" in link[1], link
