"""Algorithm 3 is one rule (wsnav.navigation.replan_policy) for every navigator that reacts to zone changes; each
user of it is driven through the same flapping zone here: the agent's navigator (in lock-step with the simulated
TurtleBot3, zone messages over a real amqtt broker), move_base's supervisor (fed what the bridge feeds it) and
Nav2's (fed what the ROS 2 bridge feeds it, by goal UUID; on the wire in tests/test_ros2_nav2.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np
import pytest

from tests.conftest import SCHOOL
from tests.robot_agent_rig import Rig
from wsnav.navigation.behaviors.escape import exit_beside
from wsnav.ros2_bridge import nav2_messages
from wsnav.ros2_bridge.nav2_supervisor import Nav2Supervisor, SendGoal
from wsnav.ros_bridge.move_base_supervisor import ACTIVE, PREEMPTED, Action, Goal, MoveBaseSupervisor, Resend
from wsnav.ros_bridge.zone_feed import ZoneChange, ZoneFeed
from wsnav.runtime.bus import Message
from wsnav.schemas import topics
from wsnav.schemas.messages import ZoneState
from wsnav.schemas.ros_map import FREE
from wsnav.schemas.site import load_site
from wsnav.zones.geometry import GridFrame

FLIPS = 21
"""z1 flips between blocked and clear every 0.1 s, 2 s in all, and is left blocked (the last word)."""
FLIP_S = 0.1
INTERVAL_S = 0.5


class User(Protocol):
    """One navigator that takes Algorithm 3 from the policy, driven in simulated time."""

    def now(self) -> float: ...
    def flip(self, state: str) -> None: ...
    def advance(self, seconds: float) -> None: ...
    def zone_replans(self) -> list[float]:
        """When it planned again for zone changes (re-sent move_base's goal, for the supervisor)."""
        ...

    def goes_round_z1(self) -> bool:
        """It still navigates to B, planned (or re-sent) after z1 was left blocked."""
        ...


class AgentUser:
    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        rig.send_goal("B")
        rig.drive(lambda: rig.clock.now() >= 2.0)
        self.since = len(rig.agent.navigator.events)

    def now(self) -> float:
        return self.rig.clock.now()

    def flip(self, state: str) -> None:
        self.rig.set_zone("z1", state)  # type: ignore[arg-type]

    def advance(self, seconds: float) -> None:
        until = self.rig.clock.now() + seconds
        self.rig.drive(lambda: self.rig.clock.now() >= until)

    def zone_replans(self) -> list[float]:
        events = list(self.rig.agent.navigator.events)[self.since :]
        return [e.t for e in events if e.trigger == "zone" and e.kind in ("replan", "resumed", "waiting")]

    def goes_round_z1(self) -> bool:
        nav = self.rig.agent.navigator
        return (
            self.rig.agent.blocked_zones() == ["z1"]
            and nav.state == "navigating"
            and nav.last_plan is not None
            and nav.last_plan.reachable
        )


PLAN_THROUGH_Z1 = np.array([(12.0 + 0.05 * i, 7.2) for i in range(200)])
"""A -> east along the south corridor, through z1."""


class SupervisorUser:
    """The supervisor as the bridge drives it: zone changes as they come, `tick` every 50 ms."""

    def __init__(self) -> None:
        site = load_site(SCHOOL)
        self.feed = ZoneFeed(site.spec, GridFrame.of_grid(site.grid))
        self.sup = MoveBaseSupervisor("robot1", self.feed)
        self.t = 2.0
        self.seq = 100
        self.sent: list[tuple[float, Resend]] = []
        self.sup.on_goal(Goal("g1", (29.0, 22.8, 0.0), "B"))
        self.sup.on_statuses([("g1", ACTIVE)])
        self.sup.on_plan(PLAN_THROUGH_Z1)

    def now(self) -> float:
        return self.t

    def _take(self, actions: list[Action]) -> None:
        for action in actions:
            assert isinstance(action, Resend), action
            self.sent.append((self.t, action))
            self.sup.on_statuses([("g1", PREEMPTED), (action.goal.goal_id, ACTIVE)])

    def flip(self, state: str) -> None:
        self.seq += 1
        payload = ZoneState(zone="z1", node="n1", state=state, seq=self.seq).to_payload()  # type: ignore[arg-type]
        changes: list[ZoneChange] = self.feed.take(
            [Message(topics.zone_state("school", "z1", "n1"), payload, True, self.t)], self.t
        )
        assert changes, "each flip changes the grid"
        self._take(self.sup.on_zones_changed(changes, self.t))

    def advance(self, seconds: float) -> None:
        end = self.t + seconds
        while self.t < end - 1e-9:
            self.t = round(self.t + 0.05, 6)
            self._take(self.sup.tick(self.t))

    def zone_replans(self) -> list[float]:
        return [t for t, _ in self.sent]

    def goes_round_z1(self) -> bool:
        return (
            self.feed.layer.blocked_zones() == ["z1"]
            and self.sup.state == "navigating"
            and self.sup.goal is not None
            and self.sup.goal.label == "B"
        )


class Nav2SupervisorUser(SupervisorUser):
    """Nav2's supervisor as `wsnav ros2 bridge --robot --nav2-resend` drives it (a behaviour tree that does not
    replan by itself): goals and statuses by UUID, a re-sent goal aborting the one it preempts, as Nav2 does."""

    def __init__(self) -> None:
        site = load_site(SCHOOL)
        self.feed = ZoneFeed(site.spec, GridFrame.of_grid(site.grid))
        self.nav2 = Nav2Supervisor("robot1", self.feed, replans_itself=False)
        self.sup = self.nav2.sup
        self.t = 2.0
        self.seq = 100
        self.sent = []
        self.current = bytes(range(16))
        self.nav2.on_goal_request(self.current, (29.0, 22.8, 0.0))
        self.nav2.on_statuses([(self.current, nav2_messages.EXECUTING)])
        self.sup.on_plan(PLAN_THROUGH_Z1)

    def _take(self, actions: list[Action]) -> None:
        for action in self.nav2.carry(actions):
            assert isinstance(action, SendGoal), action
            self.sent.append((self.t, Resend(action.goal, action.reason)))
            self.nav2.on_statuses(
                [(self.current, nav2_messages.ABORTED), (action.uuid, nav2_messages.EXECUTING)]
            )
            self.current = action.uuid

    def goes_round_z1(self) -> bool:
        return (
            self.feed.layer.blocked_zones() == ["z1"]
            and self.sup.state == "navigating"
            and self.sup.goal is not None
            and self.sup.goal.pose == (29.0, 22.8, 0.0)
        )


@pytest.fixture(params=["agent navigator", "move_base supervisor", "Nav2 supervisor"])
def user(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[User]:
    if request.param == "agent navigator":
        with Rig(tmp_path / "flap", config="full") as rig:
            yield AgentUser(rig)
    elif request.param == "Nav2 supervisor":
        yield Nav2SupervisorUser()
    else:
        yield SupervisorUser()


def test_a_zone_flapping_on_the_route_is_planned_at_most_once_per_interval_and_its_last_word_counts(
    user: User,
) -> None:
    """A node flipping its zone caused 4,077 replans in 41 s in the agent, and the supervisor re-sent move_base's
    goal (preempting it) 20 times for 20 flips in 2 s: each user replans at most once per 0.5 s, and the change
    left standing is planned for (the trailing edge), not dropped."""
    start = user.now()
    for i in range(FLIPS):
        user.flip("blocked" if i % 2 == 0 else "clear")
        user.advance(FLIP_S)
    last_change = user.now() - FLIP_S
    user.advance(2.0)
    replans = user.zone_replans()
    span = last_change - start
    assert 2 <= len(replans) <= round(span / INTERVAL_S) + 2, replans
    gaps = np.diff(replans)
    assert (gaps >= INTERVAL_S - 1e-6).all(), replans
    assert replans[-1] >= last_change - 1e-6, "the last change is planned for, at the interval's end"
    assert replans[-1] <= last_change + INTERVAL_S + 0.06
    assert user.goes_round_z1()


def test_a_zone_that_becomes_blocked_around_the_robot_sends_one_goal_out_not_a_replan_then_the_exit() -> None:
    """The bridge tells the supervisor about the zone change (with the robot's pose), then about the pose: the
    supervisor sent the goal again for the change and the exit goal 15 ms later, two preempting goals for one
    event. Now the exit goal alone goes out."""
    site = load_site(SCHOOL)
    feed = ZoneFeed(site.spec, GridFrame.of_grid(site.grid))
    sup = MoveBaseSupervisor("robot1", feed)
    walls = site.grid.data != FREE
    pose = (18.0, 7.2, 0.0)  # inside z1

    def exit_of(areas: list) -> tuple[float, float] | None:  # type: ignore[type-arg]
        return exit_beside(feed.frame, walls, feed.blocked_mask(areas), pose[:2])

    sup.on_goal(Goal("g1", (29.0, 22.8, 0.0), "B"))
    sup.on_statuses([("g1", ACTIVE)])
    sup.on_plan(PLAN_THROUGH_Z1)
    payload = ZoneState(zone="z1", node="n1", state="blocked", seq=5).to_payload()
    changes = feed.take([Message(topics.zone_state("school", "z1", "n1"), payload, True, 1.0)], 1.0)
    sent = sup.on_zones_changed(changes, 1.0, pose=pose) + sup.on_pose(pose, exit_of, 1.015)
    assert len(sent) == 1, sent
    [out] = sent
    assert isinstance(out, Resend) and "driving out first" in out.reason
    assert feed.blocked_areas_at(*out.goal.pose[:2]) == [], "the one goal is the exit"
    assert sup.tick(1.6) == [] and sup.tick(3.0) == [], "and nothing is re-sent after it"
