"""The robot's MQTT side for a bridge that supervises a ROS navigator (move_base on ROS 1, Nav2 on ROS 2): goals
and cancels from `robots/<id>/goal` turned into the supervisor's goals, and the supervisor's view of the robot
published as `robots/<id>/status`. Shared by both bridges, so an operator's goal means the same on either."""

from __future__ import annotations

from collections.abc import Callable

from wsnav.ros_bridge.move_base_supervisor import Action, Goal, MoveBaseSupervisor, Pose
from wsnav.runtime.bus import Bus
from wsnav.schemas import topics
from wsnav.schemas.goal_check import GoalRefused, read_goal
from wsnav.schemas.messages import OPERATOR_CANCEL_REASON
from wsnav.schemas.site import Site

Say = Callable[[str, bool], None]
"""How the bridge logs a line: (text, warn)."""


def take_mqtt_goal(
    site: Site, supervisor: MoveBaseSupervisor, payload: bytes, new_id: Callable[[], str], say: Say
) -> tuple[list[Action], Goal | None]:
    """A goal or cancel from `robots/<id>/goal`: the actions to carry out (a cancel of the current goal) and the
    goal to send the navigator (None: refused, a cancel, or it lies in a blocked zone, so the navigator never
    sees it). A refused payload is one warning, never an exception."""
    try:
        target = read_goal(site, payload)
    except GoalRefused as refused:
        say(f"goal dropped: {refused}", True)
        return [], None
    say(f"MQTT goal: {payload.decode(errors='replace')[:200]}", False)
    if target == "cancel":
        return supervisor.cancel(OPERATOR_CANCEL_REASON), None
    pose, label = target
    goal = Goal(new_id(), pose, label)
    cancel = supervisor.sending(goal)
    if cancel:
        say(f"goal {goal.goal_id} not sent: {cancel[0].reason}", True)
        return [], None
    return [], goal


def publish_robot_status(
    bus: Bus, site: Site, robot: str, supervisor: MoveBaseSupervisor, pose: Pose, now: float
) -> None:
    """The robot's status as the agent publishes it (retained, QoS 1)."""
    status = supervisor.status(pose, now)
    bus.publish(topics.robot_status(site.name, robot), status.to_payload(), qos=1, retain=True)
