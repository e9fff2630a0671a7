"""`wsnav ros2 bridge --robot`: what `wsnav ros bridge --robot` gives move_base users, for a Nav2 robot over DDS.
Goals in blocked zones cancelled, the robot driven out of a zone blocked around it, goals re-sent only where
Nav2 does not replan by itself (ros2_bridge.nav2_supervisor), MQTT goals, and the robot's status on MQTT (the
ROS 1 bridge's ros_bridge.robot_link).

The robot's pose is AMCL's `/amcl_pose` (reliable, transient_local, in the map frame; slam_toolbox's `/pose`
is the same type, `--pose-topic`): it is what Nav2 robots publish without a tf tree to walk, and the bridge's last
one is right while the robot stands. AMCL publishes it after every 0.25 m or 0.2 rad of motion (its
update_min_d / update_min_a), so a moving robot's pose lags by up to that: far less than a zone.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from cyclonedds.core import DDSException

from wsnav.ros2_bridge.nav2_client import Nav2Client, RobotPose
from wsnav.ros2_bridge.nav2_supervisor import CancelGoal, Nav2Action, Nav2Supervisor, SendGoal
from wsnav.ros_bridge.move_base_supervisor import Action
from wsnav.ros_bridge.robot_link import publish_robot_status, take_mqtt_goal
from wsnav.ros_bridge.zone_feed import ZoneChange, ZoneFeed
from wsnav.runtime.bus import Bus, Message
from wsnav.schemas import topics
from wsnav.schemas.ros_map import FREE
from wsnav.schemas.site import Site
from wsnav.zones.zone_rule import BlockedArea

log = logging.getLogger(__name__)

STATUS_PERIOD_S = 0.5
HOLD_GOALS_S = 30.0


def say(text: str, warn: bool) -> None:
    (log.warning if warn else log.info)(text)


@dataclass
class Nav2Robot:
    """One Nav2 robot supervised: `step` each loop, then `flush` once the grid it changed is written."""

    site: Site
    feed: ZoneFeed
    bus: Bus
    robot: str
    client: Nav2Client
    supervisor: Nav2Supervisor
    pose: RobotPose | None = None
    _outbox: list[Nav2Action] = field(default_factory=list)
    _mqtt_goals: int = 0
    _next_status: float = 0.0
    _told_frames: set[str] = field(default_factory=set)
    _held_since: float | None = None
    _held_why: str | None = None

    @property
    def goal_topic(self) -> str:
        return topics.robot_goal(self.site.name, self.robot)

    def step(self, goals: list[Message], changes: list[ZoneChange], now: float) -> bool:
        """Take in what Nav2 and MQTT said and the zone changes; True if the grid changed (the blocked areas the
        robot drives out of are sent passable but dear), so the caller writes it before `flush`."""
        sup = self.supervisor
        for seen in self.client.seen_goals():
            if seen.frame_id != self.client.frame_id and seen.frame_id not in self._told_frames:
                self._told_frames.add(seen.frame_id)
                say(f"goal in frame {seen.frame_id!r}: taken as {self.client.frame_id!r} (no tf here)", True)
            self._outbox += sup.on_goal_request(seen.uuid, seen.pose)
        for goal_uuid, accepted in self.client.replies():
            sup.on_reply(goal_uuid, accepted)
        for statuses in self.client.statuses():
            self._outbox += sup.on_statuses(statuses)
        self.pose = self.client.pose() or self.pose
        plan = self.client.plan()
        if plan is not None:
            sup.sup.on_plan(plan)
        for m in goals:
            self._mqtt_goal(m.payload)
        actions: list[Action] = sup.sup.on_zones_changed(changes, now, pose=self.pose)
        actions += sup.sup.tick(now)
        grid_changed = False
        if self.pose is not None and (now >= self._next_status or changes):
            actions += sup.sup.on_pose(self.pose, self._exit_of, now)
            grid_changed = bool(self.feed.set_escape(sup.sup.escape_areas))
            publish_robot_status(self.bus, self.site, self.robot, sup.sup, self.pose, time.time())
            self._next_status = now + STATUS_PERIOD_S
        self._outbox += sup.carry(actions)
        return grid_changed

    def flush(self, now: float) -> None:
        """Send the goals and cancels decided, in order, once Nav2's action server listens (held up to
        HOLD_GOALS_S, then dropped and the goal cancelled: a goal sent much later would start a drive nobody
        awaits). A write DDS refuses is one warning; the rest still go."""
        if not self._outbox:
            self._held_since = None
            return
        refused = self.client.server_refused()
        if refused is not None:
            if refused != self._held_why:
                self._held_why = refused
                say(f"{refused}: holding goals for Nav2", True)
            if self._held_since is None:
                self._held_since = now
            elif now - self._held_since > HOLD_GOALS_S:
                self._outbox.clear()
                self._held_since = None
                sup = self.supervisor.sup
                if sup.state == "navigating":
                    sup.state, sup.reason = "cancelled", f"not sent within {HOLD_GOALS_S:g} s: {refused}"
                say(f"goals held for Nav2 dropped after {HOLD_GOALS_S:g} s", True)
            return
        self._held_since, self._held_why = None, None
        for action in self._outbox:
            try:
                if isinstance(action, CancelGoal):
                    say(f"cancel goal {action.uuid.hex()}: {action.reason}", False)
                    self.client.cancel(action.uuid)
                else:
                    say(f"goal {action.uuid.hex()} -> {action.goal.pose} ({action.reason})", False)
                    self.client.send_goal(action.uuid, action.goal.pose)
            except DDSException as exc:
                say(f"not sent to Nav2 ({exc})", True)
        self._outbox.clear()

    def _mqtt_goal(self, payload: bytes) -> None:
        sup = self.supervisor
        actions, goal = take_mqtt_goal(self.site, sup.sup, payload, self._mqtt_goal_id, say)
        self._outbox += sup.carry(actions)
        if goal is not None:
            self._outbox.append(SendGoal(sup.own(goal), goal, "MQTT goal"))

    def _mqtt_goal_id(self) -> str:
        self._mqtt_goals += 1
        return f"wsnav-mqtt-{self._mqtt_goals}"

    def _exit_of(self, areas: list[BlockedArea]) -> tuple[float, float] | None:
        assert self.pose is not None
        from wsnav.navigation.behaviors.escape import exit_beside  # numba and the planner: only when needed

        walls = self.site.grid.data != FREE
        return exit_beside(self.feed.frame, walls, self.feed.blocked_mask(areas), self.pose[:2])
