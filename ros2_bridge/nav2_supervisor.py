"""Algorithm 3 on Nav2: move_base's supervisor (wsnav.ros_bridge.move_base_supervisor, which decides by
wsnav.navigation.replan_policy) fed what Nav2's NavigateToPose action shows, its actions turned into goals and
cancels by goal UUID. Pure logic (no DDS): the bridge feeds it the goal requests it sees, the status arrays, the
plan and the zone changes, and sends what it returns.

Nav2 and move_base differ where it matters here:
- Nav2's default behaviour trees (navigate_to_pose_w_replanning_and_recovery.xml, Humble and Jazzy) plan again
  at 1 Hz over the current costmap, and a new goal ABORTS the goal it preempts (nav2_util's SimpleActionServer):
  re-sending the goal on a zone change would only end the sender's goal (RViz's, a script's) for a replan Nav2
  makes within a second anyway. So by default zone changes re-send nothing (`replans_itself`), as with a
  move_base whose planner_frequency is above 0; a behaviour tree that does not replan by itself
  (`--nav2-resend`) gets move_base's re-sends, at most one per the policy's interval.
- Cancels of goals in blocked zones and the goal out of a blocked area go out in either case: Nav2 does neither.
- Goal ids are UUIDs chosen by the client: a goal the supervisor makes (a re-send, the way out) gets a new one.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field

from wsnav.ros2_bridge.nav2_messages import ABORTED, ACCEPTED, CANCELED, CANCELING, EXECUTING, SUCCEEDED
from wsnav.ros_bridge import move_base_supervisor as mb
from wsnav.ros_bridge.move_base_supervisor import Action, Cancel, Goal, MoveBaseSupervisor, Resend
from wsnav.ros_bridge.zone_feed import ZoneFeed

ACTIONLIB_CODE = {
    ACCEPTED: mb.PENDING,
    EXECUTING: mb.ACTIVE,
    CANCELING: mb.PREEMPTING,
    SUCCEEDED: mb.SUCCEEDED,
    CANCELED: mb.PREEMPTED,
    ABORTED: mb.ABORTED,
}
"""action_msgs/GoalStatus -> actionlib's GoalStatus, which the supervisor reads (UNKNOWN has none: skipped)."""


@dataclass(frozen=True)
class SendGoal:
    """Send NavigateToPose goal `uuid` to `goal.pose` (Nav2 aborts the goal it was following)."""

    uuid: bytes
    goal: Goal
    reason: str


@dataclass(frozen=True)
class CancelGoal:
    uuid: bytes
    reason: str


Nav2Action = SendGoal | CancelGoal


@dataclass
class Nav2Supervisor:
    """The supervisor of one Nav2 robot, by goal UUID."""

    robot_id: str
    feed: ZoneFeed
    replans_itself: bool = True
    """Nav2's behaviour tree replans by itself (the default trees do, at 1 Hz)."""
    sup: MoveBaseSupervisor = field(init=False)
    _uuid_of: dict[str, bytes] = field(default_factory=dict)
    _id_of: dict[bytes, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.sup = MoveBaseSupervisor(self.robot_id, self.feed, navigator="bt_navigator")
        self.sup.replans_itself = self.replans_itself

    # -- what Nav2 shows -----------------------------------------------------------------------------------

    def on_goal_request(self, goal_uuid: bytes, pose: mb.Pose) -> list[Nav2Action]:
        """A send_goal request seen on the wire (anyone's: RViz, a script, the bridge's own echo)."""
        if goal_uuid in self._id_of:
            return []  # ours: made current when it was sent
        goal_id = goal_uuid.hex()
        self._remember(goal_id, goal_uuid)
        return self._wire(self.sup.on_goal(Goal(goal_id, pose, pose)))

    def own(self, goal: Goal) -> bytes:
        """The UUID of a goal of ours (an MQTT goal the supervisor made current with `sup.sending`)."""
        goal_uuid = uuid.uuid4().bytes
        self._remember(goal.goal_id, goal_uuid)
        return goal_uuid

    def on_reply(self, goal_uuid: bytes, accepted: bool) -> None:
        """send_goal's reply to one of our goals: a refused goal ends there (no status will list it)."""
        current = self.sup.goal
        if accepted or current is None or self._uuid_of.get(current.goal_id) != goal_uuid:
            return
        if self.sup.state == "navigating":
            self.sup.state, self.sup.reason = "cancelled", "bt_navigator rejected the goal"

    def on_statuses(self, statuses: list[tuple[bytes, int]]) -> list[Nav2Action]:
        """One `_action/status` message: (goal UUID, action_msgs status) each."""
        listed = [
            (self._id_of.get(u, u.hex()), ACTIONLIB_CODE[code])
            for u, code in statuses
            if code in ACTIONLIB_CODE
        ]
        return self._wire(self.sup.on_statuses(listed))

    # -- Algorithm 3 (the supervisor's) ------------------------------------------------------------------

    def carry(self, actions: list[Action]) -> list[Nav2Action]:
        """What the supervisor's actions (from on_zones_changed, tick, on_pose, cancel) are on Nav2."""
        return self._wire(actions)

    # -- internals -----------------------------------------------------------------------------------------

    def _remember(self, goal_id: str, goal_uuid: bytes) -> None:
        self._uuid_of[goal_id] = goal_uuid
        self._id_of[goal_uuid] = goal_id
        if len(self._uuid_of) > 1000:  # a long-running bridge: forget the oldest goals
            for old in list(self._uuid_of)[:500]:
                self._id_of.pop(self._uuid_of.pop(old), None)

    def _wire(self, actions: list[Action]) -> list[Nav2Action]:
        out: list[Nav2Action] = []
        for action in actions:
            if isinstance(action, Cancel):
                goal_uuid = self._uuid_of.get(action.goal_id)
                if goal_uuid is not None:
                    out.append(CancelGoal(goal_uuid, action.reason))
            elif isinstance(action, Resend):
                goal_uuid = uuid.uuid4().bytes
                self._remember(action.goal.goal_id, goal_uuid)
                out.append(SendGoal(goal_uuid, action.goal, action.reason))
        return out
