"""The Nav2 action's DDS types (ros2_bridge/nav2_messages.py) against rosbags' own ROS 2 Humble and Jazzy
definitions: a request or reply is rmw_cyclonedds's 16-byte request header (the client's writer id, little-endian
uint64, then the int64 sequence number) followed by exactly the CDR rosbags writes for the .srv/.action part
(registered from Nav2's and action_msgs' definitions, which rosbags' stores lack); the plain messages decode with
rosbags' stores as they are."""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
import pytest

from wsnav.ros2_bridge import messages as m
from wsnav.ros2_bridge import nav2_messages as n

SERVICE_PARTS = {
    "nav2_msgs/msg/NavigateToPoseGoal": "geometry_msgs/PoseStamped pose\nstring behavior_tree\n",
    "nav2_msgs/msg/SendGoalRequest": "unique_identifier_msgs/UUID goal_id\nnav2_msgs/NavigateToPoseGoal goal\n",
    "nav2_msgs/msg/SendGoalResponse": "bool accepted\nbuiltin_interfaces/Time stamp\n",
    "action_msgs/msg/CancelGoalRequest": "action_msgs/GoalInfo goal_info\n",
    "action_msgs/msg/CancelGoalResponse": "int8 return_code\naction_msgs/GoalInfo[] goals_canceling\n",
}
"""nav2_msgs/action/NavigateToPose's goal (Humble and Jazzy alike), rcl_action's SendGoal wrapping of it, and
action_msgs/srv/CancelGoal, as messages rosbags can register."""


def store(distro: str) -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE if distro == "humble" else Stores.ROS2_JAZZY)
    for name, text in SERVICE_PARTS.items():
        typestore.register(get_types_from_msg(text, name))
    return typestore


UUID = list(range(200, 216))
STAMP = m.Time(sec=17, nanosec=5)


def goal_pose() -> n.PoseStamped:
    return n.PoseStamped(
        header=m.Header(stamp=STAMP, frame_id="map"),
        pose=m.Pose(position=m.Point(x=29.0, y=22.8), orientation=m.Quaternion(z=0.5, w=0.866)),
    )


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_requests_and_replies_are_rmw_cyclonedds_header_then_the_messages_cdr(distro: str) -> None:
    ts = store(distro)
    client, seq = 0xF1E2D3C4B5A69788, 42
    request = n.SendGoalRequest(
        client=client, seq=seq, goal_id=n.UUID(UUID), goal=n.NavigateToPoseGoal(pose=goal_pose())
    ).serialize()
    assert request[4:20] == struct.pack("<Qq", client, seq)
    body = ts.deserialize_cdr(request[:4] + request[20:], "nav2_msgs/msg/SendGoalRequest")
    assert body.goal_id.uuid.tolist() == UUID
    p = body.goal.pose
    assert (p.header.frame_id, p.header.stamp.sec, p.pose.position.x, p.pose.orientation.z) == (
        "map",
        17,
        29.0,
        0.5,
    )
    assert request[20:] == ts.serialize_cdr(body, "nav2_msgs/msg/SendGoalRequest")[4:]

    reply = n.SendGoalReply(client=client, seq=seq, accepted=True, stamp=STAMP).serialize()
    back = ts.deserialize_cdr(reply[:4] + reply[20:], "nav2_msgs/msg/SendGoalResponse")
    assert (back.accepted, back.stamp.sec, back.stamp.nanosec) == (True, 17, 5)

    cancel = n.CancelGoalRequest(
        client=client, seq=seq, goal_info=n.GoalInfo(goal_id=n.UUID(UUID))
    ).serialize()
    assert cancel[4:20] == struct.pack("<Qq", client, seq)
    info = ts.deserialize_cdr(cancel[:4] + cancel[20:], "action_msgs/msg/CancelGoalRequest").goal_info
    assert info.goal_id.uuid.tolist() == UUID and (info.stamp.sec, info.stamp.nanosec) == (0, 0)
    answer = n.CancelGoalReply(
        client=client, seq=seq, return_code=0, goals_canceling=[n.GoalInfo(n.UUID(UUID))]
    )
    back_answer = ts.deserialize_cdr(
        answer.serialize()[:4] + answer.serialize()[20:], "action_msgs/msg/CancelGoalResponse"
    )
    assert back_answer.return_code == 0 and back_answer.goals_canceling[0].goal_id.uuid.tolist() == UUID


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_status_pose_and_plan_decode_with_rosbags_own_definitions(distro: str) -> None:
    ts = store(distro)
    status = n.GoalStatusArray([n.GoalStatus(n.GoalInfo(n.UUID(UUID), STAMP), n.EXECUTING)])
    back = ts.deserialize_cdr(status.serialize(), "action_msgs/msg/GoalStatusArray")
    [one] = back.status_list
    assert one.goal_info.goal_id.uuid.tolist() == UUID and one.status == 2 == n.EXECUTING
    amcl = n.PoseWithCovarianceStamped(
        header=m.Header(stamp=STAMP, frame_id="map"),
        pose=n.PoseWithCovariance(pose=goal_pose().pose, covariance=[0.25] + [0.0] * 35),
    )
    back_pose = ts.deserialize_cdr(amcl.serialize(), "geometry_msgs/msg/PoseWithCovarianceStamped")
    assert back_pose.pose.pose.position.y == 22.8 and back_pose.pose.covariance[0] == 0.25
    plan = n.Path(header=m.Header(frame_id="map"), poses=[goal_pose(), goal_pose()])
    back_plan = ts.deserialize_cdr(plan.serialize(), "nav_msgs/msg/Path")
    assert np.allclose([(p.pose.position.x, p.pose.position.y) for p in back_plan.poses], [(29.0, 22.8)] * 2)
