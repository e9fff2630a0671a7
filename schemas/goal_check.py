"""One goal check for everyone who sends or reads `robots/<id>/goal`: the console and `wsnav goal` before they
publish, the robot agent and the ROS bridge when a goal arrives (a goal published by another tool, or forged).

A goal is a named point of the site or a pose on free space of the site's map; anything else is refused with a
kind (for the readers' drop counters) and one line (for the senders' error messages).
"""

from __future__ import annotations

import math
from typing import Literal

from wsnav.schemas.messages import MAX_YAW_RAD, PayloadError, RobotGoal, parse_payload
from wsnav.schemas.ros_map import FREE
from wsnav.schemas.site import Site

Pose3 = tuple[float, float, float]
GoalLabel = str | Pose3
"""How a goal is named in statuses: its point's name, or the pose itself."""
RefusalKind = Literal["invalid", "unknown_point", "off_map", "in_wall"]


class GoalRefused(ValueError):
    """A goal no robot may be sent to; str() is one line, `kind` names the reason for counters."""

    def __init__(self, kind: RefusalKind, text: str) -> None:
        super().__init__(text)
        self.kind: RefusalKind = kind


def goal_target(site: Site, goal: str | Pose3) -> tuple[Pose3, GoalLabel]:
    """The pose a goal names, and its label; raises GoalRefused."""
    if isinstance(goal, str):
        if goal not in site.spec.points:
            names = sorted(site.spec.points)
            listed = ", ".join(names[:12]) + (" ..." if len(names) > 12 else "") if names else "none"
            raise GoalRefused("unknown_point", f"unknown point {goal!r} (site {site.name} has {listed})")
        return site.point(goal), goal
    x, y, yaw = goal
    if not all(math.isfinite(v) for v in goal):
        raise GoalRefused("invalid", "a goal pose needs finite numbers")
    if not abs(yaw) <= MAX_YAW_RAD:
        raise GoalRefused("invalid", f"goal yaw {yaw:g}: expected radians within +-{MAX_YAW_RAD:g}")
    if not site.grid.contains(x, y):
        raise GoalRefused("off_map", f"goal [{x:g}, {y:g}] lies outside the map")
    row, col = site.grid.world_to_cell(x, y)
    if int(site.grid.data[row, col]) != FREE:
        raise GoalRefused("in_wall", f"goal [{x:g}, {y:g}] lies in a wall or unknown space")
    return (x, y, yaw), (x, y, yaw)


def read_goal(site: Site, payload: bytes) -> tuple[Pose3, GoalLabel] | Literal["cancel"]:
    """A goal message as it arrived: its target, or "cancel"; raises GoalRefused."""
    try:
        msg = parse_payload(RobotGoal, payload)
    except PayloadError as exc:
        raise GoalRefused("invalid", str(exc)) from None
    if msg.cancel:
        return "cancel"
    assert msg.goal is not None
    return goal_target(
        site, msg.goal if isinstance(msg.goal, str) else (msg.goal[0], msg.goal[1], msg.goal[2])
    )
