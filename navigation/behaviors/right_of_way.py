"""Who yields when two robots meet: a fixed, deterministic rule every agent applies alone, with no negotiation.

The site's robot list is the order of right of way (the first robot has it over all others). A robot yields
(stops where it is and waits, its status saying to whom and why) while a robot with right of way is driving
towards it: within `distance_m`, each in front of the other (within `cone_deg` of its heading). The robot with
right of way never stops for it: it sees the yielding robot's footprint in its costmap (wsnav.navigation.costmap.layers
.RobotsLayer) and plans round it, as round any obstacle; once it has passed (no longer in front), the yielding
robot plans again and goes on. A robot with right of way that is not driving (waiting for a way, arrived, idle)
is never yielded to, so two robots can never wait for each other: the lower one plans round the other instead.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from wsnav.navigation.backend import Pose
from wsnav.navigation.costmap.layers import OtherRobot
from wsnav.schemas.messages import YIELD_REASON_PREFIX

YIELD_DISTANCE_M = 1.5
"""Centre to centre: at the TurtleBot3's 0.22 m/s, seven seconds before the two footprints would meet."""
CONE_DEG = 60.0


def in_front(pose: Pose, x: float, y: float, cone_deg: float = CONE_DEG) -> bool:
    """Whether point (x, y) lies within `cone_deg` either side of the heading of `pose`."""
    bearing = math.atan2(y - pose[1], x - pose[0]) - pose[2]
    return abs(math.atan2(math.sin(bearing), math.cos(bearing))) <= math.radians(cone_deg)


def must_yield_to(
    me: Pose,
    my_priority: int,
    others: Iterable[OtherRobot],
    distance_m: float = YIELD_DISTANCE_M,
    cone_deg: float = CONE_DEG,
) -> OtherRobot | None:
    """The robot with right of way this one must wait for now (the one with most right of way), or None."""
    for other in sorted(others, key=lambda o: o.priority):
        if other.priority >= my_priority or other.state != "navigating":
            continue
        ox, oy, _ = other.pose
        if math.hypot(ox - me[0], oy - me[1]) > distance_m:
            continue
        if in_front(me, ox, oy, cone_deg) and in_front(other.pose, me[0], me[1], cone_deg):
            return other
    return None


def yield_reason(other: OtherRobot) -> str:
    """The status reason of a yielding robot: whom it waits for and why (constant while it waits)."""
    return f"{YIELD_REASON_PREFIX}{other.robot}: it has right of way (earlier in the site's robot list) and is coming this way"
