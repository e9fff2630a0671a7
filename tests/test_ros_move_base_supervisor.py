"""The supervisor's goal tracking as pure logic, fed what move_base's topics show (goal, status lists, plan)
exactly as the bridge feeds it; the same rules run against a real roscore in test_ros_bridge_move_base.py."""

from __future__ import annotations

import numpy as np

from tests.conftest import SCHOOL
from wsnav.navigation.behaviors.escape import exit_beside
from wsnav.ros_bridge.move_base_supervisor import (
    ACTIVE,
    PREEMPTED,
    SUCCEEDED,
    Cancel,
    Goal,
    MoveBaseSupervisor,
    Resend,
)
from wsnav.ros_bridge.zone_feed import ESCAPE_COST, ZoneFeed
from wsnav.runtime.bus import Message
from wsnav.schemas import topics
from wsnav.schemas.messages import ZoneState
from wsnav.schemas.ros_map import FREE
from wsnav.schemas.site import load_site
from wsnav.zones.cost_values import LETHAL_OBSTACLE
from wsnav.zones.geometry import GridFrame

PLAN = np.array([(12.0 + 0.05 * i, 7.2) for i in range(200)])
"""A -> east along the south corridor, through z1."""


def supervisor() -> tuple[MoveBaseSupervisor, ZoneFeed]:
    site = load_site(SCHOOL)
    feed = ZoneFeed(site.spec, GridFrame.of_grid(site.grid))
    return MoveBaseSupervisor("robot1", feed), feed


def block(feed: ZoneFeed, zone: str, node: str, t: float, state: str = "blocked") -> list:  # type: ignore[type-arg]
    payload = ZoneState(zone=zone, node=node, state=state, seq=int(t * 10) + 1).to_payload()  # type: ignore[arg-type]
    return feed.take([Message(topics.zone_state("school", zone, node), payload, True, t)], t)


def test_the_re_sent_goal_is_followed_and_replans_count_per_goal() -> None:
    sup, feed = supervisor()
    assert sup.on_goal(Goal("g1", (29.0, 22.8, 0.0), "B")) == []
    sup.on_statuses([("g1", ACTIVE)])
    sup.on_plan(PLAN)
    [resend] = sup.on_zones_changed(block(feed, "z1", "n1", 1.0))
    assert isinstance(resend, Resend) and sup.goal == resend.goal and sup.replans == 1
    sup.on_statuses([("g1", PREEMPTED), (resend.goal.goal_id, ACTIVE)])
    assert (sup.state, sup.reason) == ("navigating", None)
    sup.on_statuses([("g1", PREEMPTED), (resend.goal.goal_id, SUCCEEDED)])
    assert sup.state == "arrived"
    sup.on_goal(Goal("g2", (14.0, 7.2, 0.0), (14.0, 7.2, 0.0)))
    assert sup.replans == 0, "replans count per goal"


def test_an_rviz_goal_takes_the_id_move_base_gives_it_and_is_never_cancelled_by_the_empty_id() -> None:
    sup, feed = supervisor()
    sup.on_statuses([("old", SUCCEEDED)])
    block(feed, "z5", "n7", 1.0)
    assert sup.on_goal(Goal("", (27.8, 7.2, 0.0), (27.8, 7.2, 0.0))) == [], "no cancel by the empty id"
    assert sup.state == "cancelled"
    assert sup.on_statuses([("old", SUCCEEDED), ("/move_base-7-123.4", ACTIVE)]) == [
        Cancel("/move_base-7-123.4", "goal [27.80, 7.20] lies in blocked zone z5")
    ]


def test_a_goal_move_base_stops_listing_while_active_is_lost_and_never_re_sent() -> None:
    """move_base restarted: the goal is gone; re-sending its target on the next zone change would start a drive
    nobody asked for any more."""
    sup, feed = supervisor()
    sup.on_goal(Goal("g1", (29.0, 22.8, 0.0), "B"))
    sup.on_plan(PLAN)
    sup.on_statuses([("g1", ACTIVE)])
    sup.on_statuses([])
    assert (sup.state, sup.reason) == ("cancelled", "move_base lost the goal (restarted?)")
    assert sup.on_zones_changed(block(feed, "z1", "n1", 2.0)) == []


def test_a_replan_waits_for_the_master_costmap_and_goes_out_anyway_after_a_second() -> None:
    sup, feed = supervisor()
    sup.on_goal(Goal("g1", (29.0, 22.8, 0.0), "B"))
    sup.on_statuses([("g1", ACTIVE)])
    sup.on_plan(PLAN)
    assert sup.on_zones_changed(block(feed, "z1", "n1", 1.0), 1.0, wait_for_master=True) == []
    assert sup.waiting is not None and sup.tick(1.5) == []
    [resend] = sup.master_caught_up()
    assert isinstance(resend, Resend) and resend.reason == "a zone on the plan changed"
    assert sup.on_zones_changed(block(feed, "z1", "n1", 3.0, "clear"), 3.0, wait_for_master=True) == []
    [late] = sup.tick(4.0)
    assert isinstance(late, Resend) and "did not show it within 1 s" in late.reason
    assert sup.replans == 2 and sup.waiting is None


def test_an_rviz_goal_is_named_even_when_its_first_status_comes_before_the_goal() -> None:
    """The goal (move_base/goal) and its status (move_base/status) come on different connections: CI saw the
    status first, and the goal was never named, so its cancel never went out."""
    sup, feed = supervisor()
    sup.on_goal(Goal("g1", (14.0, 7.2, 0.0), (14.0, 7.2, 0.0)))
    sup.on_statuses([("g1", ACTIVE)])
    block(feed, "z5", "n7", 1.0)
    sup.on_statuses([("g1", PREEMPTED), ("/move_base-9-5.0", ACTIVE)])
    assert sup.on_goal(Goal("", (27.8, 7.2, 0.0), (27.8, 7.2, 0.0))) == [
        Cancel("/move_base-9-5.0", "goal [27.80, 7.20] lies in blocked zone z5")
    ]
    sup.on_statuses([("g1", PREEMPTED), ("/move_base-9-5.0", ACTIVE)])
    assert sup.goal is not None and sup.goal.goal_id == "/move_base-9-5.0"


def test_a_robot_standing_in_a_zone_that_becomes_blocked_drives_out_first_then_goes_on() -> None:
    """navfn clears only the robot's own cell: in a blocked zone move_base finds no plan and gives up. So the
    robot is sent to the nearest way out, the zone sent passable but dear meanwhile, then on to its goal."""
    sup, feed = supervisor()
    walls = load_site(SCHOOL).grid.data != FREE

    def exit_of(areas: list) -> tuple[float, float] | None:  # type: ignore[type-arg]
        return exit_beside(feed.frame, walls, feed.blocked_mask(areas), (18.0, 7.2))

    sup.on_goal(Goal("g1", (29.0, 22.8, 0.0), "B"))
    sup.on_statuses([("g1", ACTIVE)])
    assert sup.on_pose((18.0, 7.2, 0.0), exit_of) == []  # z1 clear: nothing to do
    block(feed, "z1", "n1", 1.0)
    [out] = sup.on_pose((18.0, 7.2, 0.0), exit_of)
    assert isinstance(out, Resend) and out.goal.label == "B"
    ex, ey, _ = out.goal.pose
    assert feed.blocked_areas_at(ex, ey) == [] and abs(ey - 7.2) < 1.0, "an exit along the corridor"
    assert not 16.9 < ex < 19.1 and min(abs(ex - 17.0), abs(ex - 19.0)) < 0.6, "just beyond the zone's edge"
    assert sup.reason is not None and "leaving blocked z1" in sup.reason
    assert [a.name for a in sup.escape_areas] == ["z1"]
    feed.set_escape(sup.escape_areas)
    row, col = feed.frame.world_to_cell(18.0, 7.2)
    assert feed.costs[row, col] == ESCAPE_COST, "passable for navfn, but dear"
    sup.on_statuses([("g1", PREEMPTED), (out.goal.goal_id, ACTIVE)])
    assert sup.on_pose((18.5, 7.2, 0.0), exit_of) == [], "still inside: nothing new"
    sup.on_statuses([("g1", PREEMPTED), (out.goal.goal_id, SUCCEEDED)])
    assert sup.state == "navigating", "reaching the exit is not arriving"
    [on] = sup.on_pose((ex, ey, 0.0), exit_of)
    assert isinstance(on, Resend) and on.goal.pose == (29.0, 22.8, 0.0) and on.goal.label == "B"
    assert sup.escape_areas == frozenset() and sup.reason is None
    feed.set_escape(sup.escape_areas)
    assert feed.costs[row, col] == LETHAL_OBSTACLE, "lethal again once the robot is out"


def test_a_robot_in_a_blocked_zone_with_no_way_out_cancels_with_a_reason() -> None:
    sup, feed = supervisor()
    sup.on_goal(Goal("g1", (29.0, 22.8, 0.0), "B"))
    sup.on_statuses([("g1", ACTIVE)])
    block(feed, "z1", "n1", 1.0)
    [cancel] = sup.on_pose((18.0, 7.2, 0.0), lambda _areas: None)
    assert isinstance(cancel, Cancel) and cancel.goal_id == "g1"
    assert sup.state == "cancelled" and sup.reason is not None and "no way out" in sup.reason
