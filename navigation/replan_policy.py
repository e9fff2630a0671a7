"""The paper's Algorithm 3, improved, as one rule for every navigator that reacts to zone changes: wsnav's own
(navigation/navigator.py) and move_base's supervisor (ros_bridge/move_base_supervisor.py), which Nav2's
(ros2_bridge/nav2_supervisor.py) drives by goal UUID.

What a zone change means for a goal being navigated, in this order:
- the goal now lies in a blocked zone: cancel, at once;
- the robot is held (another robot's right of way) or already settled at the goal: nothing;
- the robot stands in a blocked area: leave it first, at once (it is one plan, and staying is the harm);
- the change touches the plan, or a zone got cheaper (a shorter way may have opened): replan, but at most once
  per interval; changes within it are planned for at its end, so the last change is always planned (a node
  flipping its zone caused 4,077 replans in 41 s in the agent, and 20 re-sent move_base goals in 2 s);
- anything else: nothing.

Pure logic in the caller's time (no clock, no numpy), so lock-step simulation stays deterministic and a bridge
loads nothing heavy for it.
"""

from __future__ import annotations

import math
from enum import Enum

ZONE_REPLAN_INTERVAL_S = 0.5
"""At most one replan for zone changes per this many seconds."""


class Verdict(Enum):
    """What to do about a zone change."""

    NOTHING = "nothing"
    CANCEL = "cancel"
    """The goal lies in a blocked zone."""
    ESCAPE = "escape"
    """The robot stands in a blocked area: drive out of it first (now)."""
    REPLAN = "replan"
    """Plan again now; `planned` has been recorded."""
    LATER = "later"
    """Plan again at `due` (the end of the interval): call `is_due` from the caller's timer."""


class ReplanPolicy:
    """Algorithm 3's decision for one navigator, with its replan rate limit (trailing edge)."""

    def __init__(self, interval_s: float = ZONE_REPLAN_INTERVAL_S) -> None:
        self.interval_s = interval_s
        self.last = -math.inf
        """When the last zone replan was made."""
        self.due: float | None = None
        """When changes held back by the interval are planned for (None: none held back)."""

    def on_zones_changed(
        self,
        now: float,
        *,
        goal_blocked: bool,
        robot_blocked: bool = False,
        relevant: bool = True,
        holding: bool = False,
        settled: bool = False,
    ) -> Verdict:
        """Decide about a zone change. `relevant`: the change touches the plan or made some cell cheaper (a
        caller that does not know which cells changed passes True); `holding`: the navigator waits for something
        else and plans when that ends; `settled`: the robot is within the goal's tolerance."""
        if goal_blocked:
            self.due = None
            return Verdict.CANCEL
        if holding or settled:
            return Verdict.NOTHING
        if robot_blocked:
            return Verdict.ESCAPE
        if not relevant:
            return Verdict.NOTHING
        next_allowed = self.last + self.interval_s
        if now < next_allowed:
            self.due = next_allowed
            return Verdict.LATER
        self.planned(now)
        return Verdict.REPLAN

    def planned(self, now: float) -> None:
        """A zone replan (or a way out) was made now: it counts against the interval and settles what was due."""
        self.last = now
        self.due = None

    def is_due(self, now: float) -> bool:
        """Changes held back are due now: the caller plans (then calls `planned`) or `drop`s them."""
        return self.due is not None and now >= self.due

    def drop(self) -> None:
        """Forget changes held back (a new goal, a cancel, nothing navigated any more)."""
        self.due = None
