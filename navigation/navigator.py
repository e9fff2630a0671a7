"""The navigator: goal -> global plan -> path follower, and when to plan again (the paper's Algorithm 3, improved).

Pure logic over the costmap, planner, controller and robot backend, driven by `step(now)` and by
`on_zones_changed(now)`; it never reads a clock or the bus, so lock-step simulation is deterministic.

- A zone-layer change, decided by the one Algorithm 3 rule (wsnav.navigation.replan_policy, shared with
  move_base's supervisor): if the goal lies in a blocked zone, stop and cancel naming the zone; else replan
  (a path that appeared may be shorter, one that vanished must be replaced), at most once per interval with the
  last change always planned; no path: stop and wait.
- Waiting resumes by itself: every later zone change retries, and so (configurably) does a timer.
- The robot's footprint touches a blocked zone (it was inside when the zone was reported): leave it by the
  shortest way out over the escape view (wsnav.navigation.behaviors.escape) (the zone passable, walls and lidar marks not; the controller
  sees the same view), then on to the goal by a route that avoids the zone, or stop and wait once out if there
  is none. Once out, back on the costmap as it is: the zone is lethal again, no way back in.
- The controller reports its path blocked (the lidar saw something): replan over the obstacle marks.
- Configurably, replan at a fixed rate too (stock move_base's planner_frequency).
- Configurably, stock move_base's oscillation detection, patience and recovery behaviours
  (wsnav.navigation.behaviors.recovery): the robot not 0.2 m further in 10 s, the controller without a valid command
  for 15 s, or (stock only) no plan for 5 s runs the next of conservative reset, rotation, aggressive reset,
  rotation; when all have run, the goal is aborted (cancelled, naming move_base's reason).

- Held by the agent (another robot has right of way, wsnav.navigation.behaviors.right_of_way): stop and wait, keeping the goal,
  with the agent's reason; released, plan again from where it stands.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from wsnav.navigation.backend import Pose, RobotBackend, Velocity
from wsnav.navigation.behaviors.escape import EscapePlan, EscapeView, Leaving, plan_escape
from wsnav.navigation.behaviors.recovery import (
    ABORT_REASONS,
    MoveBaseRecovery,
    RecoveryParams,
    RecoveryTrigger,
    Rotation,
)
from wsnav.navigation.planning.astar import Plan
from wsnav.navigation.planning.global_planner import GlobalPlanner, PlanningCostmap
from wsnav.navigation.replan_policy import ZONE_REPLAN_INTERVAL_S, ReplanPolicy, Verdict
from wsnav.runtime.timers import Every
from wsnav.zones.geometry import Bounds, GridFrame
from wsnav.zones.zone_rule import BlockedArea

NavState = Literal["idle", "navigating", "waiting", "arrived", "cancelled"]
"""What the robot's status says; `Navigator.mode` says more."""


class Mode(Enum):
    """What the navigator is doing, one at a time (move_base's PLANNING / CONTROLLING / CLEARING and the waits).

    A plan is made on an event, in whichever mode allows one; it is not a mode of its own."""

    IDLE = "idle"
    CONTROLLING = "controlling"
    """Following a plan: to the goal, or out of the blocked areas the robot stands in (`leaving`)."""
    CLEARING = "clearing"
    """A recovery behaviour runs (rotate_recovery turning in place): nothing else drives the robot."""
    WAITING = "waiting"
    """No path: retried on every zone change and on the retry timer."""
    HELD = "held"
    """Stopped by the agent (another robot has right of way), keeping the goal; plans again when released."""
    ARRIVED = "arrived"
    CANCELLED = "cancelled"


_STATE: dict[Mode, NavState] = {
    Mode.IDLE: "idle",
    Mode.CONTROLLING: "navigating",
    Mode.CLEARING: "navigating",
    Mode.WAITING: "waiting",
    Mode.HELD: "waiting",
    Mode.ARRIVED: "arrived",
    Mode.CANCELLED: "cancelled",
}
Trigger = Literal["goal", "zone", "blocked", "periodic", "retry", "recovery", "yield"]
EventKind = Literal[
    "goal",
    "plan",
    "replan",
    "waiting",
    "resumed",
    "cancelled",
    "arrived",
    "blocked",
    "leaving",
    "left",
    "recovery",
]
GoalLabel = str | Pose


class Costmap(PlanningCostmap, Protocol):
    """What the navigator reads of wsnav.navigation.costmap.layered_costmap.LayeredCostmap."""

    def in_lethal(self, x: float, y: float) -> bool: ...
    def clear_except_region(self, x: float, y: float, size_m: float) -> Bounds | None: ...
    def local_window(
        self, pose: Pose, size_m: float, overlay: tuple[Bounds, NDArray[np.uint8]] | None = None
    ) -> tuple[NDArray[np.uint8], GridFrame]: ...


class LocalCostmap(Protocol):
    """What the navigator reads of wsnav.navigation.costmap.local_costmap.LocalCostmap: the controller's own
    rolling window, updated by its owner at its own rate."""

    def window(self) -> tuple[NDArray[np.uint8], GridFrame]: ...
    def clear_except_region(self, x: float, y: float, size_m: float) -> None: ...


class Escape(Protocol):
    """What the navigator needs of wsnav.navigation.behaviors.escape.ZoneEscape."""

    def areas_at(self, x: float, y: float) -> list[BlockedArea]:
        """Blocked zones (and operator blocks) the robot's footprint would touch at this point."""
        ...

    def view(self, areas: list[BlockedArea]) -> EscapeView | None:
        """Costs around `areas` with their own cost passable, for driving out of them."""
        ...


class NoEscape:
    """A costmap without a zone layer: no blocked areas to stand in."""

    def areas_at(self, x: float, y: float) -> list[BlockedArea]:
        return []

    def view(self, areas: list[BlockedArea]) -> EscapeView | None:
        return None


class ControlOutput(Protocol):
    @property
    def velocity(self) -> Velocity: ...
    @property
    def status(self) -> str: ...
    @property
    def reason(self) -> str | None: ...


class Controller(Protocol):
    """What the navigator needs of wsnav.navigation.control.controller.PathFollower."""

    def set_path(self, path: NDArray[np.float64], goal_yaw: float | None = None) -> None: ...
    def clear(self) -> None: ...
    def compute(
        self, pose: Pose, odom: Velocity, costs: NDArray[np.uint8], frame: GridFrame
    ) -> ControlOutput: ...


@dataclass(frozen=True)
class NavigatorParams:
    controller_rate_hz: float = 10.0
    replan_rate_hz: float = 0.0
    """0: replan only on events."""
    waiting_retry_s: float = 2.0
    """0: while waiting, retry only when a zone changes."""
    blocked_replan_interval_s: float = 0.5
    zone_replan_interval_s: float = ZONE_REPLAN_INTERVAL_S
    """At most one replan for zone changes per this interval; changes within it are planned for at its end
    (a node flipping its zone caused 4,077 replans in 41 s). A goal that became blocked is cancelled at once."""
    local_costmap_size_m: float = 3.0
    settle_m: float = 0.25
    """Algorithm 3's tolerance: this near the goal a zone change no longer triggers a replan."""
    recovery: RecoveryParams | None = None
    """Stock move_base's oscillation detection and recovery behaviours; None: none."""


@dataclass(frozen=True)
class NavEvent:
    """One thing the navigator did, for status, tests and the experiment's log."""

    t: float
    kind: EventKind
    trigger: Trigger | None = None
    detail: str | None = None
    pose: Pose | None = None


class Navigator:
    def __init__(
        self,
        costmap: Costmap,
        planner: GlobalPlanner,
        controller: Controller,
        backend: RobotBackend,
        params: NavigatorParams | None = None,
        blocked_zones: Callable[[], list[str]] | None = None,
        escape: Escape | None = None,
        local_costmap: LocalCostmap | None = None,
    ) -> None:
        """`blocked_zones` tells which zones the zone layer holds lethal now (none without a zone layer);
        `escape` finds the blocked areas the robot stands in and the way out (none without a zone layer);
        `local_costmap`: what the controller reads (None: a window of `costmap` around the robot)."""
        self.costmap = costmap
        self.local_costmap = local_costmap
        self.escape: Escape = escape or NoEscape()
        self.planner = planner
        self.controller = controller
        self.backend = backend
        self.params = params or NavigatorParams()
        self._blocked_zones = blocked_zones or list
        self.mode = Mode.IDLE
        self.reason: str | None = None
        self.goal: Pose | None = None
        self.goal_label: GoalLabel | None = None
        self.path: NDArray[np.float64] = np.zeros((0, 2))
        self.plan_length_m: float | None = None
        self.plans = 0
        """Global plans computed, all goals."""
        self.replans = 0
        """Plans after the first for the current goal (reset with each goal)."""
        self.replans_by: Counter[str] = Counter()
        self.planning_ms = 0.0
        self.last_plan: Plan | None = None
        self.events: deque[NavEvent] = deque(maxlen=10_000)
        """The newest events (a long-running agent must not grow without bound)."""
        self._control = Every(self.params.controller_rate_hz)
        self._periodic = Every(self.params.replan_rate_hz)
        self._retry = Every(1.0 / self.params.waiting_retry_s if self.params.waiting_retry_s > 0 else 0.0)
        self._last_blocked_replan = -math.inf
        self.replan_policy = ReplanPolicy(self.params.zone_replan_interval_s)
        """Algorithm 3's decision on zone changes, and their replan rate limit."""
        self.leaving: Leaving | None = None
        """The blocked areas the robot is driving out of, and whether a route goes on (None: in none)."""
        self.recovery = MoveBaseRecovery(self.params.recovery) if self.params.recovery is not None else None
        self._rotation: Rotation | None = None
        """The rotation in progress; set only in Mode.CLEARING."""

    @property
    def state(self) -> NavState:
        return _STATE[self.mode]

    @property
    def holding(self) -> str | None:
        """Why the agent holds the robot (it yields to another robot), None when it does not."""
        return self.reason if self.mode is Mode.HELD else None

    @property
    def active(self) -> bool:
        return self.mode in (Mode.CONTROLLING, Mode.CLEARING, Mode.WAITING, Mode.HELD)

    def next_due(self) -> float:
        """The earliest time `step` has work to do (for a real-time loop's sleep)."""
        due = self.replan_policy.due if self.replan_policy.due is not None else math.inf
        if self.state == "navigating":
            return min(self._control.next, self._periodic.next, due)
        if self.mode is Mode.WAITING:
            return min(self._retry.next, due)
        return math.inf

    def set_goal(self, goal: Pose, label: GoalLabel, now: float) -> None:
        """A new goal replaces the old one; planned at once."""
        self.goal, self.goal_label = goal, label
        self.replan_policy.drop()
        self.replans = 0
        self.replans_by.clear()
        self.reason = None
        self._record(now, "goal", detail=_label_text(label))
        self._rotation = None
        if self.recovery is not None:
            self.recovery.start_goal(now, self.backend.pose())
        self._periodic.start(now)
        self._control.next = now
        zone = self._goal_blocked_zone()
        if zone is not None:
            self._cancel(now, zone)
            return
        self.mode = Mode.CONTROLLING
        self._plan(now, "goal")

    def cancel(self, now: float, reason: str) -> None:
        if self.active:
            self._cancel(now, reason)

    def hold(self, now: float, reason: str) -> None:
        """Stop and wait for something outside the navigator (another robot's right of way), keeping the goal.

        Only a robot driving on its route (or turning in a recovery) is held: one leaving a blocked zone goes on
        out first. A recovery behaviour in progress is dropped: released, the robot plans afresh."""
        if self.mode is Mode.HELD:
            if reason != self.reason:
                self.reason = reason
                self._record(now, "waiting", "yield", reason)
            return
        if self.mode not in (Mode.CONTROLLING, Mode.CLEARING) or self.leaving is not None:
            return
        self._stop()
        self.mode, self.reason = Mode.HELD, reason
        self._record(now, "waiting", "yield", reason)

    def release(self, now: float) -> None:
        """The hold is over: plan again from where the robot stands."""
        if self.mode is not Mode.HELD:
            return
        self.mode = Mode.WAITING
        if self.recovery is not None:
            self.recovery.restart_clocks(now, self.backend.pose())
        self._plan(now, "yield")

    def on_zones_changed(self, now: float) -> None:
        """The zone layer changed the costmap: Algorithm 3, run at once rather than on the planner's timer."""
        if not self.active or self.goal is None:
            return
        zone = self._goal_blocked_zone()
        x, y, _ = self.backend.pose()
        verdict = self.replan_policy.on_zones_changed(
            now,
            goal_blocked=zone is not None,
            # The navigator does not know which cells changed: every change may touch its plan.
            relevant=True,
            holding=self.mode is Mode.HELD,  # planned when released, over the costmap as it is then
            settled=self.state == "navigating"
            and math.hypot(self.goal[0] - x, self.goal[1] - y) <= self.params.settle_m,
            # A robot standing in a blocked area is not told apart here: `_plan` finds the way out first.
        )
        if verdict is Verdict.CANCEL:
            assert zone is not None
            self._cancel(now, zone)
        elif verdict is Verdict.REPLAN:
            self._plan(now, "zone")

    def step(self, now: float) -> None:
        """Timers: periodic replanning, retries while waiting, and the controller at its rate."""
        if self.replan_policy.is_due(now):
            if self.mode in (Mode.CONTROLLING, Mode.WAITING):
                self.replan_policy.planned(now)
                self._plan(now, "zone")
            else:
                self.replan_policy.drop()
        if self.mode is Mode.WAITING:
            if self._retry.due(now):
                self._plan(now, "retry")
            return
        if self.mode is Mode.CLEARING:
            if self._control.due(now):
                self._rotate_tick(now)
            return
        if self.mode is not Mode.CONTROLLING:
            return
        if self._periodic.due(now):
            self._plan(now, "periodic")
            if self.state != "navigating":
                return
        if self._control.due(now):
            self._control_tick(now)

    def _control_tick(self, now: float) -> None:
        pose = self.backend.pose()
        if self.recovery is not None and self.recovery.control_cycle(now, pose):
            self._recover(now, "oscillation")
            return
        view: EscapeView | None = None
        if self.leaving is not None:
            here = self.escape.areas_at(pose[0], pose[1])
            if here:
                view = self.escape.view(here)
            else:
                onward = self.leaving.onward
                self._left(now)
                if not onward:
                    self._plan(now, "zone")
                    if self.state != "navigating":
                        return
        if (
            self.local_costmap is not None
        ):  # its own layers hold no zone: nothing to let the robot out through
            costs, frame = self.local_costmap.window()
        else:
            overlay = view.overlay if view is not None else None
            costs, frame = self.costmap.local_window(pose, self.params.local_costmap_size_m, overlay)
        result = self.controller.compute(pose, self.backend.velocity(), costs, frame)
        if result.status == "arrived" and self.leaving is not None and not self.leaving.onward:
            # At the end of the way out with no route on (normally `_left` got here first): plan from here
            # over the costmap as it is, which waits.
            self._plan(now, "zone", escape=False)
        elif result.status == "arrived":
            self._stop()
            self.mode, self.reason = Mode.ARRIVED, None
            self._record(now, "arrived")
        elif result.status == "blocked":
            self.backend.stop()
            if self.recovery is not None and self.recovery.controller_out_of_patience(now):
                self._recover(now, "controlling")
            elif now - self._last_blocked_replan >= self.params.blocked_replan_interval_s:
                self._last_blocked_replan = now
                self._record(now, "blocked", detail=result.reason)
                self._plan(now, "blocked")
        else:
            if self.recovery is not None:
                self.recovery.valid_control(now)
            self.backend.command(result.velocity)

    def _recover(self, now: float, trigger: RecoveryTrigger) -> None:
        """move_base's CLEARING state: stop, run the next recovery behaviour, then plan again; abort when all
        have run."""
        assert self.recovery is not None
        self.backend.stop()
        name = self.recovery.next_behaviour(trigger)
        if name is None:
            self._cancel(now, f"aborted: {ABORT_REASONS[trigger]} even after all recovery behaviours")
            return
        self._record(now, "recovery", detail=f"{name} ({trigger})")
        if self.mode is Mode.WAITING:
            self._control.start(now)
            self._periodic.start(now)
        self.mode, self.reason = Mode.CLEARING, f"recovery: {name}"
        side = self.recovery.params.reset_distance(name)
        if side is None:
            self.controller.clear()
            self._rotation = Rotation(self.backend.pose()[2])
            self._rotate_tick(now)
            return
        x, y, _ = self.backend.pose()
        self.costmap.clear_except_region(x, y, side)
        if self.local_costmap is not None:
            self.local_costmap.clear_except_region(x, y, side)
        self._after_behaviour(now)

    def _rotate_tick(self, now: float) -> None:
        assert self.recovery is not None and self._rotation is not None
        w = self._rotation.step(self.backend.pose()[2], self.recovery.params)
        if w is not None:
            self.backend.command(Velocity(0.0, w))
            return
        self.backend.stop()
        self._rotation = None
        self._after_behaviour(now)

    def _after_behaviour(self, now: float) -> None:
        assert self.recovery is not None
        self.recovery.behaviour_done(now)
        self.mode, self.reason = Mode.CONTROLLING, None
        self._plan(now, "recovery")

    def _plan(self, now: float, trigger: Trigger, *, escape: bool = True) -> None:
        """Plan to the goal and act on it; from inside blocked zones (and `escape`), by the way out first."""
        assert self.goal is not None
        pose = self.backend.pose()
        costmap = self.costmap
        here = self.escape.areas_at(pose[0], pose[1]) if escape else []
        view = self.escape.view(here) if here else None
        start, goal = (pose[0], pose[1]), (self.goal[0], self.goal[1])
        out: EscapePlan | None = None
        if view is not None:
            out = plan_escape(self.planner, costmap, view, start, goal)
            plan = out.onward if out.onward is not None else out.out
        else:
            plan = self.planner.plan(costmap, start, goal)
        self.plans += 1
        self.planning_ms += out.plan_ms if out is not None else plan.plan_ms
        self.last_plan = plan
        if trigger != "goal":
            self.replans += 1
            self.replans_by[trigger] += 1
        if out is not None and out.out.reachable:
            if plan.reason == "goal_outside":
                self._cancel(now, "the goal lies outside the map")
                return
            self._follow(now, trigger, out.path, out.length_m, Leaving(tuple(here), out.reaches_goal))
            if not out.reaches_goal:
                self.reason = f"{self.reason}; then waiting: {self._no_path_reason(plan)}"[:200]
            return
        if out is None and self.leaving is not None:
            self._left(now)  # planned from outside the zones: it is out
        self.leaving = None
        if plan.reachable:
            if self.recovery is not None:
                self.recovery.planned(now)
            self._follow(now, trigger, plan.path, plan.length_m, None)
            return
        if plan.reason == "goal_outside":
            self._cancel(now, "the goal lies outside the map")
            return
        if plan.reason == "start_outside":
            self._cancel(now, "the robot is outside the map")
            return
        if self.recovery is not None and self.recovery.plan_failed(now):
            self._recover(now, "planning")
            return
        self._wait(now, trigger, self._no_path_reason(plan))

    def _follow(
        self,
        now: float,
        trigger: Trigger,
        path: NDArray[np.float64],
        length_m: float,
        leaving: Leaving | None,
    ) -> None:
        """Drive `path`: the route to the goal, or only the way out of blocked areas (`leaving`, not onward)."""
        assert self.goal is not None
        self.path = path
        self.plan_length_m = length_m
        to_goal = leaving is None or leaving.onward
        self.controller.set_path(path, self.goal[2] if to_goal else None)
        resumed = self.mode is Mode.WAITING
        if self.mode is not Mode.CLEARING:  # a rotation in progress finishes first (move_base's CLEARING)
            self.mode = Mode.CONTROLLING
        self.reason = None
        if resumed:
            self._control.start(now)
            self._periodic.start(now)
        kind = "resumed" if resumed else ("plan" if trigger == "goal" else "replan")
        self._record(now, kind, trigger, f"{length_m:.2f} m")
        if leaving is not None:
            self.reason = f"leaving blocked zone {leaving.names}"
            if self.leaving is None or leaving.areas != self.leaving.areas:
                self._record(now, "leaving", trigger, leaving.names)
        self.leaving = leaving

    def _left(self, now: float) -> None:
        """The footprint is clear of the zones it was leaving: back on the costmap as it is."""
        self._record(now, "left", detail=self.leaving.names if self.leaving is not None else "")
        self.leaving = None
        if self.state == "navigating":
            self.reason = None

    def _no_path_reason(self, plan: Plan) -> str:
        blocked = self._blocked_zones()
        why = {
            "goal_blocked": "the goal is occupied",
            "start_blocked": "the robot stands in lethal space",
            "no_path": "no path to the goal",
        }.get(plan.reason, plan.reason)
        if self.goal is not None and plan.reason == "goal_blocked" and self.costmap.in_lethal(*self.goal[:2]):
            why = "the goal is occupied by an obstacle"
        if plan.reason == "start_blocked":
            here = self.escape.areas_at(*self.backend.pose()[:2])
            if here:
                why = f"the robot stands in blocked zone {', '.join(a.name for a in here)}"
        return f"{why} (blocked zones: {', '.join(blocked)})" if blocked else why

    def _goal_blocked_zone(self) -> str | None:
        """The cancel reason when the goal lies in lethal space of a blocked zone, else None."""
        if self.goal is None:
            return None
        x, y = self.goal[0], self.goal[1]
        if not self.costmap.frame.contains_cell(*self.costmap.frame.world_to_cell(x, y)):
            return None
        if not self.costmap.in_lethal(x, y):
            return None
        areas = self.escape.areas_at(x, y)
        if not areas:
            return None
        return f"goal {_label_text(self.goal_label)} lies in blocked zone {', '.join(a.name for a in areas)}"

    def _wait(self, now: float, trigger: Trigger, reason: str) -> None:
        self._stop()
        if self.mode is not Mode.WAITING or self.reason != reason:
            self._record(now, "waiting", trigger, reason)
        if self.mode is not Mode.WAITING:
            self._retry.start(now)
        self.mode, self.reason = Mode.WAITING, reason

    def _cancel(self, now: float, reason: str) -> None:
        self._stop()
        self.mode, self.reason = Mode.CANCELLED, reason
        self._record(now, "cancelled", detail=reason)

    def _stop(self) -> None:
        self._rotation = None
        if self.mode is Mode.CLEARING:
            self.mode = Mode.CONTROLLING
        self.backend.stop()
        self.controller.clear()
        self.path = np.zeros((0, 2))
        self.leaving = None

    def _record(
        self, now: float, kind: EventKind, trigger: Trigger | None = None, detail: str | None = None
    ) -> None:
        self.events.append(NavEvent(now, kind, trigger, detail, self.backend.pose()))


def _label_text(label: GoalLabel | None) -> str:
    if label is None:
        return "?"
    if isinstance(label, str):
        return label
    return "[" + ", ".join(f"{v:.2f}" for v in label) + "]"
