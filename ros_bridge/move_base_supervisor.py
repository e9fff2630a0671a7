"""Algorithm 3 on move_base: cancel a goal that lies in a blocked zone, replan when a zone on the plan changes or
one got cheaper (at most once per interval, the last change always planned), drive out of a blocked area the
robot stands in, and say so on MQTT, from what move_base's action topics show. The decision is the agent's own
(wsnav.navigation.replan_policy); this module carries it out on move_base.

Pure logic (no rospy): the ROS node feeds it the goals it sees on `move_base/goal` (whoever sent them: RViz, a
script, the MQTT goal topic), the goal statuses, the global plan and the zone changes, and carries out the
actions it returns. A re-sent goal (same target, new goal id) is how move_base is told to plan now rather than
at its next `planner_frequency` tick; the re-sent goal becomes the one followed at once, so the PREEMPTED of the
goal it replaces is not taken for a cancel. A re-send preempts the goal of whoever sent it (a script's
SimpleActionClient sees PREEMPTED), so it is made only where move_base will not replan by itself
(`replans_itself`: its planner_frequency is above 0; then move_base's own timer picks the change up).

RViz's goals (`/move_base_simple/goal`) reach `move_base/goal` with an EMPTY goal id: move_base relays them to its
own action server, which makes up an id. The supervisor follows such a goal without an id until a new id shows
up in move_base's status, and never cancels by the empty id (to actionlib that means every goal).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from wsnav.navigation.replan_policy import ReplanPolicy, Verdict
from wsnav.ros_bridge.zone_feed import ZoneChange, ZoneFeed
from wsnav.schemas.messages import RobotStateValue, RobotStatus
from wsnav.zones.geometry import Bounds
from wsnav.zones.zone_rule import BlockedArea

Pose = tuple[float, float, float]

# actionlib_msgs/GoalStatus codes
PENDING, ACTIVE, PREEMPTED, SUCCEEDED, ABORTED, REJECTED, PREEMPTING, RECALLING, RECALLED, LOST = range(10)


@dataclass(frozen=True)
class Goal:
    goal_id: str
    pose: Pose
    label: str | Pose
    """A named point of the site when the goal came as one over MQTT, else the pose."""


@dataclass(frozen=True)
class Cancel:
    goal_id: str
    reason: str


@dataclass(frozen=True)
class Resend:
    """Send the same target again under `goal_id`: move_base preempts the old goal and plans at once."""

    goal: Goal
    reason: str


Action = Cancel | Resend

MASTER_WAIT_S = 1.0
"""How long a replan waits for move_base's master costmap to show the zone change (measured: 6-102 ms, median
57 ms, after the update message); then the goal is re-sent anyway."""


@dataclass(frozen=True)
class WaitingReplan:
    """A replan held until move_base's master costmap shows the change: re-sent at once, move_base planned over
    the old master and went through the zone it had just been told was blocked (8 of 8 tries)."""

    window: Bounds
    """The zone-grid cells that changed."""
    why: str
    deadline: float


@dataclass(frozen=True)
class Leaving:
    """The robot stands in blocked areas: move_base drives it to `exit` first (the areas sent passable but dear,
    ZoneFeed.set_escape), then on to `target`. navfn clears only the robot's own cell: without this, move_base
    found no plan out of a zone that became blocked around the robot and gave up."""

    areas: frozenset[BlockedArea]
    target: Goal


@dataclass
class MoveBaseSupervisor:
    robot_id: str
    feed: ZoneFeed
    goal: Goal | None = None
    state: RobotStateValue = "idle"
    reason: str | None = None
    replans: int = 0
    plan_length_m: float | None = None
    _plan_cells: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    _ours: set[str] = field(default_factory=set)
    """Goal ids this supervisor sent (MQTT goals, re-sends): already current when move_base echoes them."""
    _sent: int = 0
    _listed: set[str] = field(default_factory=set)
    """The goal ids of move_base's last status message."""
    _statuses: int = 0
    _first_listed: dict[str, int] = field(default_factory=dict)
    """Goal id -> the status message (count) that first listed it, for the ids still listed."""
    _active: set[str] = field(default_factory=set)
    """Goal ids move_base lists as pending or active now."""
    _followed: set[str] = field(default_factory=set)
    """Ids of goals followed before the current one: never the id of a new RViz goal."""
    _cancel_waiting: str | None = None
    """A cancel for the current goal that waits for move_base to name it (an RViz goal has no id yet)."""
    waiting: WaitingReplan | None = None
    """A replan waiting for the master costmap (see `on_zones_changed`)."""
    _listed_current: bool = False
    """move_base has listed the current goal in its status: once it stops listing it, the goal is gone."""
    leaving: Leaving | None = None
    _exit_reached: bool = False
    replans_itself: bool = False
    """move_base replans on its own timer (planner_frequency > 0): a zone change re-sends no goal (it would only
    preempt the sender's goal); cancels and the way out of a blocked area still go out."""
    policy: ReplanPolicy = field(default_factory=ReplanPolicy)
    """Algorithm 3's decision on zone changes, and their replan rate limit (the agent's own rule)."""
    _due_why: str = ""
    _due_window: Bounds | None = None
    """The cells of zone changes held back by the policy's interval, planned for at its end."""
    navigator: str = "move_base"
    """What the robot's status calls the navigator in its reasons (Nav2's supervisor says bt_navigator)."""

    # -- what move_base shows ------------------------------------------------------------------------------

    def on_goal(self, goal: Goal) -> list[Action]:
        """A goal seen on move_base/goal (RViz, a script, or our own); cancelled at once if it lies in a blocked
        zone. Our own goals were made current when they were sent, so their echo changes nothing. An empty id
        (RViz) is never taken as ours: every RViz goal is a new goal."""
        if goal.goal_id and goal.goal_id in self._ours:
            return []
        return self._follow(goal)

    def sending(self, goal: Goal) -> list[Action]:
        """Make `goal` current before it is sent (so the old goal's PREEMPTED status is not read as ours)."""
        self._ours.add(goal.goal_id)
        return self._follow(goal)

    def cancel(self, reason: str) -> list[Action]:
        """The operator's cancel (MQTT): stop the current goal, if one is being navigated."""
        if self.goal is None or self.state != "navigating":
            return []
        self.state, self.reason = "cancelled", reason
        return self._cancel_current(reason)

    def on_statuses(self, statuses: list[tuple[str, int]]) -> list[Action]:
        """One move_base/status message, (goal id, code) each. A goal followed without an id (RViz's) takes the
        id of a goal newly listed as pending or active; a cancel that waited for it goes out then."""
        self._statuses += 1
        self._listed = {g for g, _ in statuses}
        self._first_listed = {g: self._first_listed.get(g, self._statuses) for g in self._listed}
        self._active = {g for g, code in statuses if code in (PENDING, ACTIVE)}
        self._followed &= self._listed
        actions = self._name_rviz_goal()
        if self.goal is not None and self.goal.goal_id:
            if self.goal.goal_id in self._listed:
                self._listed_current = True
            elif self._listed_current and self.state == "navigating":
                # actionlib lists a goal until some seconds after it ends: an active goal that vanishes went with
                # a move_base that restarted. Its target is not re-sent on the next zone change.
                self.state, self.reason = "cancelled", f"{self.navigator} lost the goal (restarted?)"
        for goal_id, code in statuses:
            self.on_status(goal_id, code)
        return actions

    def on_status(self, goal_id: str, code: int) -> None:
        """One entry of move_base/status; only the current goal's counts."""
        if self.goal is None or not goal_id or goal_id != self.goal.goal_id or self.state == "cancelled":
            return
        if code in (PENDING, ACTIVE):
            self.state = "navigating"
        elif code == SUCCEEDED and self.leaving is not None:
            self._exit_reached = True  # at the exit: on_pose goes on to the target
        elif code == SUCCEEDED:
            self.state, self.reason = "arrived", None
        elif code in (ABORTED, REJECTED, LOST):
            self.state = "cancelled"
            self.reason = f"{self.navigator} gave up on the goal (no valid plan or control)"
        elif code in (PREEMPTED, RECALLED):
            self.state = "cancelled"
            self.reason = self.reason or "cancelled on the ROS side"

    def on_plan(self, xy: NDArray[np.float64]) -> None:
        """The current global plan, (N, 2) metres in the map frame."""
        frame = self.feed.frame
        if len(xy) == 0:
            self._plan_cells = np.zeros((0, 2), dtype=np.int64)
            self.plan_length_m = None
            return
        rows, cols = frame.world_to_cells(xy[:, 0], xy[:, 1])
        self._plan_cells = np.stack([rows, cols], axis=1).astype(np.int64)
        self.plan_length_m = float(np.hypot(*np.diff(xy, axis=0).T).sum()) if len(xy) > 1 else 0.0

    # -- where the robot is --------------------------------------------------------------------------------

    @property
    def escape_areas(self) -> frozenset[BlockedArea]:
        """The blocked areas the grid must send passable (but dear) while the robot drives out of them."""
        return self.leaving.areas if self.leaving is not None else frozenset()

    def on_pose(
        self,
        pose: Pose,
        exit_of: Callable[[list[BlockedArea]], tuple[float, float] | None],
        now: float = 0.0,
        *,
        wait_for_master: bool = False,
    ) -> list[Action]:
        """Start driving out when the robot stands in a blocked area while navigating (to the exit `exit_of`
        finds); once out (or at the exit), go on to the goal. With `wait_for_master`, the new goal waits, as a
        replan does, for the master costmap to show the areas passable."""
        x, y, yaw = pose
        inside = self.feed.blocked_areas_at(x, y)
        if self.leaving is not None:
            if self.state != "navigating":
                self.leaving, self._exit_reached = None, False
                return []
            if any(a in self.leaving.areas for a in inside) and not self._exit_reached:
                return []
            areas, target = self.leaving.areas, self.leaving.target
            self.leaving, self._exit_reached = None, False
            self.goal = replace(
                target, goal_id=self.goal.goal_id if self.goal is not None else target.goal_id
            )
            self.reason = None
            cancel = self._cancel_if_blocked()
            if cancel:
                return cancel
            self.policy.planned(now)
            return self._replan("out of the blocked area: on to the goal", areas, now, wait_for_master)
        if self.goal is None or self.state != "navigating" or not inside:
            return []
        names = ", ".join(a.name for a in inside)
        exit_xy = exit_of(inside)
        if exit_xy is None:
            self.state, self.reason = "cancelled", f"the robot stands in blocked {names} and found no way out"
            return self._cancel_current(self.reason)
        self.leaving = Leaving(frozenset(inside), self.goal)
        self.goal = replace(self.goal, pose=(exit_xy[0], exit_xy[1], yaw))
        self.reason = f"leaving blocked {names} before going on"
        # At once, not after the master shows the zone passable: move_base, still on the old goal, would plan
        # through the zone the moment it became passable (seen on the real move_base); its planner retries the
        # exit until the grid is in.
        self.policy.planned(now)
        return self._resend(f"the robot stands in blocked {names}: driving out first")

    def _replan(
        self, why: str, areas: frozenset[BlockedArea], now: float, wait_for_master: bool
    ) -> list[Action]:
        """Re-send the current goal, at once or once the master costmap shows the grid of `areas` changed."""
        if not wait_for_master:
            return self._resend(why)
        window: Bounds | None = None
        for area, w in self.feed.layer.blocked_areas():
            if area in areas:
                window = Bounds(w.row0, w.col0, w.row0 + w.mask.shape[0], w.col0 + w.mask.shape[1]).union(
                    window
                )
        if window is None:
            return self._resend(why)
        self.waiting = WaitingReplan(window, why, now + MASTER_WAIT_S)
        return []

    # -- what the zones say --------------------------------------------------------------------------------

    def on_zones_changed(
        self,
        changes: list[ZoneChange],
        now: float = 0.0,
        *,
        wait_for_master: bool = False,
        pose: Pose | None = None,
    ) -> list[Action]:
        """Algorithm 3 (wsnav.navigation.replan_policy): cancel if the goal now lies in a blocked zone; nothing
        if the robot (at `pose`) stands in a blocked area (`on_pose` sends the one goal out of it); else replan
        when a change touches the plan or opens a way (a zone cleared), at most once per the policy's interval
        (changes within it are re-sent by `tick` at its end); nothing while no goal is being navigated. With
        `wait_for_master`, the replan waits (`waiting`) until `master_caught_up` or `tick` past MASTER_WAIT_S."""
        if self.goal is None or self.state != "navigating" or not changes:
            return []
        on_plan = [c for c in changes if self._crosses(c)]
        inside = (
            pose is not None and self.leaving is None and bool(self.feed.blocked_areas_at(pose[0], pose[1]))
        )
        verdict = self.policy.on_zones_changed(
            now,
            goal_blocked=bool(self._goal_zones()),
            robot_blocked=inside,
            relevant=bool(on_plan) or any(c.cheaper for c in changes),
        )
        if verdict is Verdict.CANCEL:
            self.waiting = None
            self._due_window = None
            return self._cancel_if_blocked()
        if verdict not in (Verdict.REPLAN, Verdict.LATER):
            return []
        why = "a zone on the plan changed" if on_plan else "a zone cleared"
        window = self._due_window
        for c in changes:
            window = c.window.union(window)
        assert window is not None
        if verdict is Verdict.LATER:
            self._due_why, self._due_window = why, window
            return []
        self._due_window = None
        return self._replan_over(why, window, now, wait_for_master)

    def _replan_over(self, why: str, window: Bounds, now: float, wait_for_master: bool) -> list[Action]:
        """Replan for zone changes in `window`: re-send the goal at once, or once the master costmap shows them;
        nothing where move_base replans by itself."""
        if self.replans_itself:
            return []
        if not wait_for_master:
            return self._resend(why)
        if self.waiting is not None:
            window = window.union(self.waiting.window)
        deadline = self.waiting.deadline if self.waiting is not None else now + MASTER_WAIT_S
        self.waiting = WaitingReplan(window, why, deadline)
        return []

    def master_caught_up(self) -> list[Action]:
        """move_base's master costmap now shows the changes the waiting replan is for: re-send now."""
        if self.waiting is None:
            return []
        why, self.waiting = self.waiting.why, None
        if self.goal is None or self.state != "navigating":
            return []
        return self._resend(why)

    def tick(self, now: float, *, wait_for_master: bool = False) -> list[Action]:
        """Replan for zone changes the policy held back, once their interval is over; re-send a waiting replan
        whose master costmap did not show the change in time."""
        if self.policy.is_due(now):
            window, self._due_window = self._due_window, None
            if self.goal is None or self.state != "navigating" or window is None:
                self.policy.drop()
            else:
                self.policy.planned(now)
                return self._replan_over(self._due_why, window, now, wait_for_master)
        if self.waiting is None or now < self.waiting.deadline:
            return []
        why = f"{self.waiting.why}; the master costmap did not show it within {MASTER_WAIT_S:g} s"
        self.waiting = None
        if self.goal is None or self.state != "navigating":
            return []
        return self._resend(why)

    def _resend(self, why: str) -> list[Action]:
        assert self.goal is not None
        self.replans += 1
        self._sent += 1
        base = self.goal.goal_id.split("#wsnav")[0] or "wsnav-rviz"
        goal = Goal(f"{base}#wsnav{self._sent}", self.goal.pose, self.goal.label)
        self._ours.add(goal.goal_id)
        self.goal = goal  # followed from now on: the goal it preempts ends PREEMPTED, which is not a cancel
        self._listed_current = False
        self._cancel_waiting = None
        return [Resend(goal, why)]

    def status(self, pose: Pose, now: float) -> RobotStatus:
        x, y, yaw = pose
        label = None if self.goal is None else self.goal.label
        if label is not None and not isinstance(label, str):
            label = (round(label[0], 3), round(label[1], 3), round(label[2], 3))
        return RobotStatus(
            robot=self.robot_id,
            state=self.state,
            pose=(round(x, 3), round(y, 3), round(yaw, 3)),
            goal=label,
            blocked_zones=self.feed.layer.blocked_zones(),
            replans=self.replans,
            plan_length_m=round(self.plan_length_m, 3) if self.plan_length_m is not None else None,
            reason=self.reason[:200] if self.reason else None,
            t=round(now, 3),
        )

    # -- internals -----------------------------------------------------------------------------------------

    def _name_rviz_goal(self) -> list[Action]:
        """Give the current goal without an id (RViz's) the id of the goal move_base listed most recently as
        pending or active, within its last few status messages (the goal and its first status come on different
        connections, in either order), and send the cancel that waited for it."""
        if self.goal is None or self.goal.goal_id:
            return []
        recent = [
            (first, g)
            for g, first in self._first_listed.items()
            if first >= self._statuses - 2
            and g in self._active
            and g not in self._ours
            and g not in self._followed
        ]
        if not recent:
            return []
        self.goal = replace(self.goal, goal_id=max(recent)[1])
        if self._cancel_waiting is None:
            return []
        reason, self._cancel_waiting = self._cancel_waiting, None
        return [Cancel(self.goal.goal_id, reason)]

    def _follow(self, goal: Goal) -> list[Action]:
        if self.goal is not None and self.goal.goal_id:
            self._followed.add(self.goal.goal_id)
        self._plan_cells = np.zeros((0, 2), dtype=np.int64)
        self.plan_length_m = None
        self.goal = goal
        self.replans = 0  # per goal, as the agent counts them
        self.waiting = None
        self.policy.drop()
        self._due_window = None
        self._listed_current = False
        self._cancel_waiting = None
        self.state, self.reason = "navigating", None
        return self._cancel_if_blocked() + self._name_rviz_goal()

    def _cancel_current(self, reason: str) -> list[Action]:
        """Cancel the current goal by its id; one without an id yet (RViz's) is cancelled once move_base names
        it: an empty id would cancel every goal move_base has."""
        assert self.goal is not None
        if not self.goal.goal_id:
            self._cancel_waiting = reason
            return []
        return [Cancel(self.goal.goal_id, reason)]

    def _goal_zones(self) -> list[str]:
        """The blocked zones the current goal lies in."""
        if self.goal is None:
            return []
        x, y, _ = self.goal.pose
        if not (math.isfinite(x) and math.isfinite(y)):
            return []
        return self.feed.blocked_zones_at(x, y)

    def _cancel_if_blocked(self) -> list[Action]:
        zones = self._goal_zones()
        if not zones or self.goal is None:
            return []
        self.policy.drop()
        x, y, _ = self.goal.pose
        label = self.goal.label if isinstance(self.goal.label, str) else f"[{x:.2f}, {y:.2f}]"
        self.state, self.reason = "cancelled", f"goal {label} lies in blocked zone {', '.join(zones)}"
        return self._cancel_current(self.reason)

    def _crosses(self, change: ZoneChange) -> bool:
        w = change.window
        cells = self._plan_cells
        if len(cells) == 0:
            return False
        inside = (
            (cells[:, 0] >= w.row0)
            & (cells[:, 0] < w.row1)
            & (cells[:, 1] >= w.col0)
            & (cells[:, 1] < w.col1)
        )
        return bool(inside.any())
