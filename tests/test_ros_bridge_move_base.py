# pyright: reportMissingImports=false
"""Algorithm 3 on move_base: `wsnav ros bridge --robot` against a real roscore and broker.

move_base is not packaged for Debian, so a minimal actionlib server (the real actionlib, MoveBaseAction) stands in
for it here and only here: it accepts goals, publishes an L-shaped global plan along the school's south and middle
corridors, and arrives only when the test says so. Like move_base it relays `/move_base_simple/goal` (what RViz
publishes) to its own action server with an empty goal id, which actionlib then names. What it leaves out:
planning, the costmaps, control and recoveries (a plan is a fixed line, not navfn's), so what these tests check is
the bridge's goal tracking over move_base's real action interface, not where move_base drives. The robot's pose
comes from a real tf2 static transform.
"""

from __future__ import annotations

import contextlib
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.move_base_standin import PLAN, FakeMoveBase
from tests.ros_fixtures import (
    Operator,
    RosMaster,
    WsnavChild,
    bridge_args,
    send_goal,
    slow_heartbeat_school,
    wait_until,
    zone_state,
)
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas import topics


@pytest.fixture(scope="module")
def move_base(ros_node: RosMaster) -> FakeMoveBase:
    import rospy
    import tf2_ros
    from geometry_msgs.msg import TransformStamped

    fake = FakeMoveBase().start()
    tf = TransformStamped()
    tf.header.stamp = rospy.Time.now()
    tf.header.frame_id, tf.child_frame_id = "map", "base_footprint"
    tf.transform.translation.x, tf.transform.translation.y = PLAN[0]
    tf.transform.rotation.w = 1.0
    broadcaster = tf2_ros.StaticTransformBroadcaster()
    broadcaster.sendTransform(tf)
    fake.tf_broadcaster = broadcaster  # type: ignore[attr-defined]  (kept alive with the fake)
    return fake


@pytest.fixture
def rig(
    tmp_path: Path, ros_node: RosMaster, move_base: FakeMoveBase
) -> Iterator[tuple[WsnavChild, Operator, dict[str, MqttBus]]]:
    with bridge_rig(tmp_path, ros_node) as started:
        yield started


@pytest.fixture
def relay_rig(
    tmp_path: Path, ros_node: RosMaster, move_base: FakeMoveBase
) -> Iterator[tuple[WsnavChild, Operator, dict[str, MqttBus]]]:
    with bridge_rig(tmp_path, ros_node, "--relay", "/wsnav/move_base") as started:
        yield started


@contextlib.contextmanager
def bridge_rig(
    tmp_path: Path, ros_node: RosMaster, *extra: str
) -> Iterator[tuple[WsnavChild, Operator, dict[str, MqttBus]]]:
    site_dir = slow_heartbeat_school(tmp_path)
    with BrokerThread(site_dir) as broker:
        bus = connect_with_credentials(broker.host, broker.port, broker.credentials("operator"))
        bus.subscribe(topics.robot_status("school", "robot1"))
        nodes = {
            n: connect_with_credentials(broker.host, broker.port, broker.credentials(n))
            for n in ("n1", "n2", "n7")
        }
        bridge = WsnavChild(
            ["ros", "bridge", *bridge_args(site_dir, broker, "--robot", "robot1", *extra)], ros_node.env()
        )
        try:
            bridge.wait_for("supervising /move_base for robot1", 30)
            yield bridge, Operator(bus, "school"), nodes
        finally:
            bridge.stop()
            print("bridge output:", *bridge.lines, sep="\n")  # shown when a test fails
            bus.close()
            for node in nodes.values():
                node.close()


def test_a_zone_on_the_plan_makes_move_base_replan_at_once(
    rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase
) -> None:
    bridge, operator, nodes = rig
    before = len(move_base.goals)
    send_goal(operator, "B")
    wait_until(
        lambda: len(move_base.goals) > before or bool(move_base.errors), 15, "the MQTT goal at move_base"
    )
    assert not move_base.errors
    first_id, gx, gy = move_base.goals[-1]
    assert (gx, gy) == (29.0, 22.8)
    status = operator.wait_status(
        "navigating to B with the pose from tf", lambda s: s.state == "navigating" and s.goal == "B"
    )
    assert status.pose[:2] == PLAN[0]
    time.sleep(0.5)  # the plan reaches the bridge
    sent = time.monotonic()
    zone_state(nodes["n1"], "z1", "n1", "blocked", 100)
    zone_state(nodes["n2"], "z1", "n2", "blocked", 100)
    wait_until(
        lambda: len(move_base.goals) > before + 1, 10, "the goal re-sent after z1 on the plan was blocked"
    )
    resent_id, rx, ry = move_base.goals[-1]
    assert (rx, ry) == (29.0, 22.8) and resent_id != first_id
    assert first_id in move_base.preempted  # move_base dropped the old goal for the new one: it plans now
    assert time.monotonic() - sent < 10
    status = operator.wait_status(
        "the replan counted, z1 blocked", lambda s: s.replans >= 1 and "z1" in s.blocked_zones
    )
    assert status.state == "navigating" and status.goal == "B"
    assert any("replan now (a zone on the plan changed)" in line for line in bridge.lines), bridge.lines


def test_an_mqtt_goal_off_the_map_or_in_a_wall_never_reaches_move_base(
    rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase
) -> None:
    """The agent's goal check (schemas.goal_check), in the bridge too: only a reachable place goes to move_base."""
    bridge, operator, _ = rig
    before = len(move_base.goals)
    send_goal(operator, [500.0, 3.0, 0.0])
    send_goal(operator, [0.05, 0.05, 0.0])
    send_goal(operator, "B")  # the sentinel: goals arrive in order
    wait_until(lambda: len(move_base.goals) > before, 15, "the sentinel goal at move_base")
    assert [(x, y) for _, x, y in move_base.goals[before:]] == [(29.0, 22.8)]
    dropped = [line for line in bridge.lines if "goal dropped" in line]
    assert any("outside the map" in line for line in dropped) and any("in a wall" in line for line in dropped)


def test_a_goal_in_a_blocked_zone_is_cancelled_whoever_sent_it(
    rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase
) -> None:
    import actionlib
    import rospy
    from actionlib_msgs.msg import GoalStatus
    from move_base_msgs.msg import MoveBaseAction, MoveBaseGoal

    _bridge, operator, nodes = rig
    in_z5 = [27.8, 7.2, 0.0]
    send_goal(operator, in_z5)
    wait_until(
        lambda: any((x, y) == (27.8, 7.2) for _, x, y in move_base.goals), 15, "the goal in z5 at move_base"
    )
    goal_id = next(i for i, x, y in reversed(move_base.goals) if (x, y) == (27.8, 7.2))
    zone_state(nodes["n7"], "z5", "n7", "blocked", 100)
    wait_until(lambda: goal_id in move_base.preempted, 10, "move_base to be told to cancel the goal in z5")
    status = operator.wait_status("cancelled with the reason", lambda s: s.state == "cancelled")
    assert status.reason is not None and "lies in blocked zone z5" in status.reason, status

    # A goal straight to move_base (as RViz sends one) into the blocked zone is cancelled too.
    client = actionlib.SimpleActionClient("/move_base", MoveBaseAction)
    assert client.wait_for_server(rospy.Duration(10))
    goal = MoveBaseGoal()
    goal.target_pose.header.frame_id = "map"
    goal.target_pose.pose.position.x, goal.target_pose.pose.position.y = 28.0, 7.5
    goal.target_pose.pose.orientation.w = 1.0
    client.send_goal(goal)
    assert client.wait_for_result(rospy.Duration(15))
    assert client.get_state() in (GoalStatus.PREEMPTED, GoalStatus.RECALLED)
    status = operator.wait_status(
        "the ROS goal's cancel on MQTT",
        lambda s: (
            s.state == "cancelled" and s.goal != "B" and s.goal is not None and abs(s.goal[0] - 28.0) < 1e-6
        ),
    )  # type: ignore[index]
    assert status.reason is not None and "z5" in status.reason
    assert np.isfinite(status.pose).all()


def rviz_goal(ros_node: RosMaster, x: float, y: float) -> None:
    """What RViz's 2D Nav Goal publishes, sent by the real ROS tool."""
    pose = f"{{header: {{frame_id: map}}, pose: {{position: {{x: {x}, y: {y}}}, orientation: {{w: 1.0}}}}}}"
    subprocess.run(
        ["rostopic", "pub", "-1", "/move_base_simple/goal", "geometry_msgs/PoseStamped", pose],
        env=ros_node.env(),
        check=True,
        capture_output=True,
        timeout=60,
    )


@pytest.mark.slow
def test_after_a_replan_the_re_sent_goal_is_followed_to_its_arrival(
    rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase
) -> None:
    """The re-sent goal is the one followed: the PREEMPTED of the goal it replaced made the robot `cancelled`
    while move_base drove on, and nothing after (no cancel, no arrival) reached MQTT."""
    _bridge, operator, nodes = rig
    before = len(move_base.goals)
    send_goal(operator, "B")
    wait_until(lambda: len(move_base.goals) > before, 15, "the MQTT goal at move_base")
    first_id = move_base.goals[-1][0]
    operator.wait_status("navigating to B", lambda s: s.state == "navigating" and s.goal == "B")
    time.sleep(0.5)  # the plan reaches the bridge
    zone_state(nodes["n1"], "z1", "n1", "blocked", 200)
    wait_until(lambda: first_id in move_base.preempted, 10, "the old goal preempted by the re-sent one")
    time.sleep(1.5)  # several of move_base's status messages (5 Hz) list the old goal PREEMPTED
    status = operator.wait_status("a status after the preemption", lambda s: s.replans >= 1)
    assert (status.state, status.reason) == ("navigating", None), status
    move_base.arrive = True
    status = operator.wait_status("arrived", lambda s: s.state != "navigating")
    assert (status.state, status.goal) == ("arrived", "B"), status


@pytest.mark.slow
def test_rviz_goals_are_followed_replanned_and_arrive_by_the_id_move_base_gives_them(
    rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase, ros_node: RosMaster
) -> None:
    """`rostopic pub /move_base_simple/goal` as RViz does: the goal reaches move_base/goal with an empty id. The
    bridge tracked "", ignored every later RViz goal as its own, re-sent the first target on a zone change and
    never saw the arrival."""
    bridge, operator, nodes = rig
    before = len(move_base.goals)
    rviz_goal(ros_node, 14.0, 7.2)
    wait_until(lambda: len(move_base.goals) > before, 15, "the first RViz goal at move_base")
    operator.wait_status(
        "navigating to the first",
        lambda s: s.state == "navigating" and s.goal is not None and s.goal[0] == 14.0,
    )  # type: ignore[index]
    rviz_goal(ros_node, 29.0, 22.8)
    wait_until(lambda: len(move_base.goals) > before + 1, 15, "the second RViz goal at move_base")
    second_id = move_base.goals[-1][0]
    assert second_id, "actionlib names a goal that came without an id"
    operator.wait_status("the second goal followed", lambda s: s.goal is not None and s.goal[0] == 29.0)  # type: ignore[index]
    time.sleep(0.5)  # the plan reaches the bridge
    zone_state(nodes["n1"], "z1", "n1", "blocked", 300)
    wait_until(lambda: len(move_base.goals) > before + 2, 10, "the RViz goal re-sent after z1 was blocked")
    _resent_id, rx, ry = move_base.goals[-1]
    assert (rx, ry) == (29.0, 22.8), "the user's latest goal is re-sent, not the first RViz target"
    assert second_id in move_base.preempted
    time.sleep(1.0)
    move_base.arrive = True
    status = operator.wait_status("arrived", lambda s: s.state != "navigating")
    assert status.state == "arrived", status
    assert not any("cancel goal :" in line or "cancel goal  " in line for line in bridge.lines), bridge.lines


@pytest.mark.slow
def test_an_rviz_goal_in_a_blocked_zone_is_cancelled_by_its_own_id_and_no_other(
    rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase, ros_node: RosMaster
) -> None:
    """A cancel with an empty id cancels every goal in actionlib: the bridge waits for move_base to name the
    RViz goal and cancels that one."""
    bridge, operator, nodes = rig
    zone_state(nodes["n7"], "z5", "n7", "blocked", 400)
    operator.wait_status("z5 blocked", lambda s: "z5" in s.blocked_zones)
    before = len(move_base.goals)
    rviz_goal(ros_node, 27.8, 7.2)
    wait_until(lambda: len(move_base.goals) > before, 15, "the RViz goal in z5 at move_base")
    goal_id = move_base.goals[-1][0]
    wait_until(lambda: goal_id in move_base.preempted, 10, "move_base told to cancel the RViz goal by its id")
    status = operator.wait_status("cancelled", lambda s: s.state == "cancelled")
    assert status.reason is not None and "lies in blocked zone z5" in status.reason, status
    assert any(f"cancel goal {goal_id}:" in line for line in bridge.lines), bridge.lines


@pytest.mark.slow
def test_a_goal_given_in_another_frame_is_checked_where_it_lies_on_the_map(
    rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase, ros_node: RosMaster
) -> None:
    """move_base transforms a goal stamped in `odom` into its global frame; the bridge took the numbers as map
    coordinates, so a goal in a blocked zone was not cancelled (and one beside it would have been)."""
    import rospy
    from geometry_msgs.msg import TransformStamped

    _bridge, operator, nodes = rig
    transforms = []
    for child, (x, y) in (("base_footprint", PLAN[0]), ("odom", (10.0, 0.0))):
        tf = TransformStamped()
        tf.header.stamp = rospy.Time.now()
        tf.header.frame_id, tf.child_frame_id = "map", child
        tf.transform.translation.x, tf.transform.translation.y = x, y
        tf.transform.rotation.w = 1.0
        transforms.append(tf)
    move_base.tf_broadcaster.sendTransform(transforms)  # type: ignore[attr-defined]
    zone_state(nodes["n7"], "z5", "n7", "blocked", 500)
    operator.wait_status("z5 blocked", lambda s: "z5" in s.blocked_zones)
    before = len(move_base.goals)
    pose = "{header: {frame_id: odom}, pose: {position: {x: 17.8, y: 7.2}, orientation: {w: 1.0}}}"
    subprocess.run(
        ["rostopic", "pub", "-1", "/move_base_simple/goal", "geometry_msgs/PoseStamped", pose],
        env=ros_node.env(), check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    wait_until(lambda: len(move_base.goals) > before, 15, "the goal in odom at move_base")
    goal_id = move_base.goals[-1][0]
    wait_until(lambda: goal_id in move_base.preempted, 10, "the goal (27.8, 7.2 on the map, in z5) cancelled")
    status = operator.wait_status("cancelled", lambda s: s.state == "cancelled")
    assert status.reason is not None and "lies in blocked zone z5" in status.reason, status
    assert status.goal is not None and abs(status.goal[0] - 27.8) < 1e-6  # type: ignore[index]


@pytest.mark.slow
def test_the_goal_is_re_sent_only_once_move_bases_master_costmap_shows_the_zone(
    rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase
) -> None:
    """Re-sent 3 ms after the MQTT message, move_base planned over a master costmap that did not have the zone
    yet (it takes 6-102 ms): 8 of 8 replans still went through the newly blocked zone. The bridge now waits for
    the master's update that shows the zone lethal."""
    _bridge, operator, nodes = rig
    before = len(move_base.goals)
    send_goal(operator, "B")
    wait_until(lambda: len(move_base.goals) > before, 15, "the MQTT goal at move_base")
    operator.wait_status("navigating to B", lambda s: s.state == "navigating" and s.goal == "B")
    time.sleep(0.5)  # the plan reaches the bridge
    updates = len(move_base.master_updates)
    zone_state(nodes["n1"], "z1", "n1", "blocked", 600)
    wait_until(lambda: len(move_base.goals) > before + 1, 10, "the goal re-sent after z1 was blocked")
    assert len(move_base.master_updates) > updates, "re-sent before the master costmap showed z1"
    assert move_base.goal_times[-1] >= move_base.master_updates[updates]


def robot_at(move_base: FakeMoveBase, x: float, y: float) -> None:
    """Move the robot (map -> base_footprint) where the test needs it."""
    import rospy
    from geometry_msgs.msg import TransformStamped

    tf = TransformStamped()
    tf.header.stamp = rospy.Time.now()
    tf.header.frame_id, tf.child_frame_id = "map", "base_footprint"
    tf.transform.translation.x, tf.transform.translation.y = x, y
    tf.transform.rotation.w = 1.0
    move_base.tf_broadcaster.sendTransform(tf)  # type: ignore[attr-defined]


def test_a_robot_standing_in_a_zone_that_becomes_blocked_is_sent_out_first_then_on_to_its_goal(
    rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase
) -> None:
    """navfn clears only the robot's own cell, so move_base found no plan out of a zone blocked around the robot
    and gave up. The bridge sends it to the nearest way out first (the zone passable but dear meanwhile), then
    on to its goal. What the stand-in leaves out: it plans nothing, so the robot is moved by tf here."""
    bridge, operator, nodes = rig
    robot_at(move_base, 18.0, 7.2)  # inside z1
    try:
        send_goal(operator, "B")
        wait_until(lambda: any(g[1:] == (29.0, 22.8) for g in move_base.goals), 15, "the goal at move_base")
        before = len(move_base.goals)
        zone_state(nodes["n1"], "z1", "n1", "blocked", 700)
        zone_state(nodes["n2"], "z1", "n2", "blocked", 700)

        def exits() -> list[tuple[str, float, float]]:
            return [g for g in move_base.goals[before:] if g[1:] != (29.0, 22.8)]

        wait_until(lambda: bool(exits()), 15, "a goal out of z1 at move_base")
        _, ex, ey = exits()[0]
        assert abs(ey - 7.2) < 1.0 and not 16.9 < ex < 19.1, (ex, ey)
        status = operator.wait_status("leaving z1", lambda s: s.reason is not None and "leaving" in s.reason)
        assert status.state == "navigating" and status.goal == "B"
        after_exit = len(move_base.goals)
        robot_at(move_base, ex, ey)
        wait_until(
            lambda: any(g[1:] == (29.0, 22.8) for g in move_base.goals[after_exit:]), 15, "on to B once out"
        )
        assert any("driving out first" in line for line in bridge.lines), bridge.lines
    finally:
        robot_at(move_base, *PLAN[0])


@pytest.mark.slow
def test_where_move_base_replans_by_itself_a_zone_change_keeps_the_scripts_goal_and_the_rviz_goal(
    rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase, ros_node: RosMaster
) -> None:
    """Every replan re-sent move_base's goal, so a mission script's SimpleActionClient saw its goal PREEMPTED
    ("another goal was received") and never SUCCEEDED while the robot drove on under the bridge's goal id. With
    planner_frequency above 0 (ROBOTIS' 5.0) move_base replans by itself: a zone change on the plan re-sends
    nothing, and the script's goal, like an RViz goal, ends as the robot's drive ends."""
    import actionlib
    import rospy
    from actionlib_msgs.msg import GoalStatus
    from move_base_msgs.msg import MoveBaseAction, MoveBaseGoal

    bridge, operator, nodes = rig
    rospy.set_param("/move_base/planner_frequency", 5.0)
    try:
        bridge.wait_for("move_base replans by itself", 15)
        client = actionlib.SimpleActionClient("/move_base", MoveBaseAction)
        assert client.wait_for_server(rospy.Duration(10))
        goal = MoveBaseGoal()
        goal.target_pose.header.frame_id = "map"
        goal.target_pose.header.stamp = rospy.Time.now()
        goal.target_pose.pose.position.x, goal.target_pose.pose.position.y = 29.0, 22.8
        goal.target_pose.pose.orientation.w = 1.0
        before = len(move_base.goals)
        client.send_goal(goal)
        wait_until(lambda: len(move_base.goals) > before, 15, "the script's goal at move_base")
        operator.wait_status(
            "navigating to the script's goal",
            lambda s: s.state == "navigating" and s.goal is not None and s.goal[0] == 29.0,  # type: ignore[index]
        )
        time.sleep(0.5)  # the plan reaches the bridge
        zone_state(nodes["n1"], "z1", "n1", "blocked", 800)
        operator.wait_status("z1 blocked", lambda s: "z1" in s.blocked_zones)
        time.sleep(1.5)  # a re-send would have gone out by now
        assert len(move_base.goals) == before + 1, move_base.goals[before:]
        assert client.get_state() == GoalStatus.ACTIVE, client.get_goal_status_text()
        move_base.arrive = True
        assert client.wait_for_result(rospy.Duration(10))
        assert client.get_state() == GoalStatus.SUCCEEDED, client.get_goal_status_text()
        status = operator.wait_status("arrived", lambda s: s.state != "navigating")
        assert status.state == "arrived", status

        before = len(move_base.goals)
        rviz_goal(ros_node, 29.0, 22.8)
        wait_until(lambda: len(move_base.goals) > before, 15, "the RViz goal at move_base")
        rviz_id = move_base.goals[-1][0]
        operator.wait_status("navigating to the RViz goal", lambda s: s.state == "navigating")
        time.sleep(0.5)
        zone_state(nodes["n1"], "z1", "n1", "clear", 801)  # a zone on the plan got cheaper
        operator.wait_status("z1 clear", lambda s: "z1" not in s.blocked_zones)
        time.sleep(1.5)
        assert len(move_base.goals) == before + 1 and rviz_id not in move_base.preempted, move_base.goals[
            before:
        ]
        move_base.arrive = True
        status = operator.wait_status("the RViz goal arrived", lambda s: s.state != "navigating")
        assert status.state == "arrived", status
        assert not any("replan now" in line for line in bridge.lines), bridge.lines
    finally:
        rospy.delete_param("/move_base/planner_frequency")


@pytest.mark.slow
def test_a_scripts_goal_on_the_relay_survives_the_re_sends_and_ends_succeeded(
    relay_rig: tuple[WsnavChild, Operator, dict[str, MqttBus]], move_base: FakeMoveBase
) -> None:
    """With planner_frequency 0 the bridge must re-send move_base's goal to make it plan now, which preempts the
    sender's goal. A script that sends its goal to the bridge's relay (`--relay /wsnav/move_base`, the same
    MoveBaseAction) keeps it: PREEMPTED at move_base stays inside the bridge, and the script's goal ends
    SUCCEEDED when the robot arrives."""
    import actionlib
    import rospy
    from actionlib_msgs.msg import GoalStatus
    from move_base_msgs.msg import MoveBaseAction, MoveBaseGoal

    _bridge, operator, nodes = relay_rig
    client = actionlib.SimpleActionClient("/wsnav/move_base", MoveBaseAction)
    assert client.wait_for_server(rospy.Duration(15))
    goal = MoveBaseGoal()
    goal.target_pose.header.frame_id = "map"
    goal.target_pose.header.stamp = rospy.Time.now()
    goal.target_pose.pose.position.x, goal.target_pose.pose.position.y = 29.0, 22.8
    goal.target_pose.pose.orientation.w = 1.0
    before = len(move_base.goals)
    client.send_goal(goal)
    wait_until(lambda: len(move_base.goals) > before, 15, "the relayed goal at move_base")
    first_id = move_base.goals[-1][0]
    operator.wait_status("navigating to the relayed goal", lambda s: s.state == "navigating")
    time.sleep(0.5)  # the plan reaches the bridge
    zone_state(nodes["n1"], "z1", "n1", "blocked", 900)
    wait_until(
        lambda: first_id in move_base.preempted, 10, "move_base's goal re-sent (the old one preempted)"
    )
    time.sleep(1.0)
    assert client.get_state() == GoalStatus.ACTIVE, client.get_goal_status_text()
    move_base.arrive = True
    assert client.wait_for_result(rospy.Duration(15))
    assert client.get_state() == GoalStatus.SUCCEEDED, client.get_goal_status_text()
