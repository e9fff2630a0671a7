"""Nav2's supervisor (ros2_bridge/nav2_supervisor.py) as the ROS 2 bridge feeds it, by goal UUID: with Nav2's
default behaviour trees (which replan at 1 Hz by themselves) zone changes re-send nothing, yet a goal in a
blocked zone is cancelled whoever sent it; the goal a re-send preempts ends ABORTED (as nav2_util's
SimpleActionServer ends it), which is not the robot's goal ending. On the wire: tests/test_ros2_nav2.py."""

from __future__ import annotations

import numpy as np

from tests.conftest import SCHOOL
from wsnav.ros2_bridge.nav2_messages import ABORTED, EXECUTING, SUCCEEDED
from wsnav.ros2_bridge.nav2_supervisor import CancelGoal, Nav2Supervisor, SendGoal
from wsnav.ros_bridge.zone_feed import ZoneChange, ZoneFeed
from wsnav.runtime.bus import Message
from wsnav.schemas import topics
from wsnav.schemas.messages import ZoneState
from wsnav.schemas.site import load_site
from wsnav.zones.geometry import GridFrame

RVIZ_GOAL = bytes(range(16))
PLAN_THROUGH_Z1 = np.array([(12.0 + 0.05 * i, 7.2) for i in range(200)])


def school() -> ZoneFeed:
    site = load_site(SCHOOL)
    return ZoneFeed(site.spec, GridFrame.of_grid(site.grid))


def set_zone(feed: ZoneFeed, zone: str, node: str, state: str, seq: int, t: float) -> list[ZoneChange]:
    payload = ZoneState(zone=zone, node=node, state=state, seq=seq).to_payload()  # type: ignore[arg-type]
    return feed.take([Message(topics.zone_state("school", zone, node), payload, True, t)], t)


def test_with_nav2_s_default_tree_zone_changes_re_send_nothing_but_a_blocked_goal_is_cancelled() -> None:
    feed = school()
    nav2 = Nav2Supervisor("robot1", feed)
    assert nav2.on_goal_request(RVIZ_GOAL, (29.0, 22.8, 0.0)) == []
    nav2.on_statuses([(RVIZ_GOAL, EXECUTING)])
    nav2.sup.on_plan(PLAN_THROUGH_Z1)
    sent = []
    for i in range(21):
        t = 1.0 + 0.1 * i
        changes = set_zone(feed, "z1", "n1", "blocked" if i % 2 == 0 else "clear", 10 + i, t)
        sent += nav2.carry(nav2.sup.on_zones_changed(changes, t, pose=(12.0, 7.2, 0.0)) + nav2.sup.tick(t))
    assert sent == [], "Nav2 replans by itself: a re-send would only abort the sender's goal"
    assert nav2.sup.state == "navigating"

    # another client's goal into z4 (it preempts the first), then z4 blocked
    goal_in_z4 = bytes(range(16, 32))
    nav2.on_goal_request(goal_in_z4, (25.0, 15.0, 0.0))
    nav2.on_statuses([(RVIZ_GOAL, ABORTED), (goal_in_z4, EXECUTING)])
    assert nav2.sup.state == "navigating", "the preempted goal's ABORTED is not the robot's goal ending"
    node = next(n.id for n in load_site(SCHOOL).spec.nodes if n.zone == "z4")
    changes = set_zone(feed, "z4", node, "blocked", 5, 5.0)
    [cancel] = nav2.carry(nav2.sup.on_zones_changed(changes, 5.0, pose=(12.0, 7.2, 0.0)))
    assert isinstance(cancel, CancelGoal) and cancel.uuid == goal_in_z4, "cancelled by the sender's own UUID"
    assert nav2.sup.state == "cancelled" and "z4" in (nav2.sup.reason or "")


def test_a_re_sent_goal_gets_a_new_uuid_and_its_success_is_the_robot_s_arrival() -> None:
    feed = school()
    nav2 = Nav2Supervisor("robot1", feed, replans_itself=False)
    nav2.on_goal_request(RVIZ_GOAL, (29.0, 22.8, 0.0))
    nav2.on_statuses([(RVIZ_GOAL, EXECUTING)])
    nav2.sup.on_plan(PLAN_THROUGH_Z1)
    [resend] = nav2.carry(nav2.sup.on_zones_changed(set_zone(feed, "z1", "n1", "blocked", 5, 1.0), 1.0))
    assert isinstance(resend, SendGoal) and resend.uuid != RVIZ_GOAL and resend.goal.pose == (29.0, 22.8, 0.0)
    assert nav2.on_goal_request(resend.uuid, resend.goal.pose) == [], "its echo on the wire is ours"
    nav2.on_statuses([(RVIZ_GOAL, ABORTED), (resend.uuid, EXECUTING)])
    assert nav2.sup.state == "navigating"
    nav2.on_statuses([(RVIZ_GOAL, ABORTED), (resend.uuid, SUCCEEDED)])
    assert nav2.sup.state == "arrived"
