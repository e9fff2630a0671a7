"""The DDS side of `wsnav ros2 bridge --robot`: an action client of Nav2's `navigate_to_pose` as rclcpp's is on
rmw_cyclonedds (ros2_bridge.nav2_messages), a watcher of everyone's goal requests, and readers of the robot's
pose (`/amcl_pose`) and of the global plan (`/plan`).

Other clients' goals are seen by reading the send_goal request topic itself (a DDS topic any reader may read);
the bridge's own requests come back there too and are told apart by the client id in rmw's request header. The
request writer carries no `clientid` user data: rmw_cyclonedds's server then answers at once rather than
waiting to match the client's reply reader by it (its "backwards-compatibility" branch).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from numpy.typing import NDArray

from wsnav.ros2_bridge.messages import Header, Point, Pose, Quaternion, dds_topic
from wsnav.ros2_bridge.nav2_messages import (
    UUID,
    CancelGoalRequest,
    GoalInfo,
    GoalStatusArray,
    NavigateToPoseGoal,
    Path,
    PoseStamped,
    PoseWithCovarianceStamped,
    SendGoalReply,
    SendGoalRequest,
    reply_topic,
    request_topic,
    service_qos,
    status_qos,
)
from wsnav.ros2_bridge.writer import ros_time
from wsnav.runtime.drop_log import DropLog
from wsnav.schemas.messages import MAX_COORDINATE_M

log = logging.getLogger(__name__)

RobotPose = tuple[float, float, float]


@dataclass(frozen=True)
class Nav2Names:
    """The ROS 2 names the bridge meets Nav2 on (Nav2's defaults: /navigate_to_pose, /amcl_pose, /plan)."""

    action: str = "/navigate_to_pose"
    pose: str = "/amcl_pose"
    plan: str = "/plan"

    @property
    def send_goal(self) -> str:
        return f"{self.action}/_action/send_goal"

    @property
    def cancel_goal(self) -> str:
        return f"{self.action}/_action/cancel_goal"

    @property
    def status(self) -> str:
        return f"{self.action}/_action/status"


@dataclass(frozen=True)
class SeenGoal:
    """A send_goal request of another client: the goal's UUID, its pose and the frame it is in."""

    uuid: bytes
    pose: RobotPose
    frame_id: str


def yaw_of(q: Quaternion) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def pose_of(p: Pose) -> RobotPose | None:
    """A ROS pose as (x, y, yaw), None if it is no place (NaN, infinite or beyond any map): such a message is
    dropped, as the status it would become could not be published."""
    pose = (p.position.x, p.position.y, yaw_of(p.orientation))
    if not all(math.isfinite(v) for v in pose) or max(abs(pose[0]), abs(pose[1])) > MAX_COORDINATE_M:
        DROPS.drop("no place", time.monotonic(), "a pose", repr(pose))
        return None
    return pose


CYCLONE_VENDOR = b"\x01\x10"
"""The first bytes of a Cyclone DDS participant's GUID (its RTPS vendor id, 1.16; Fast DDS's is 1.15)."""


def matched(lookup: Any, handle: int) -> Any:
    """A matched endpoint's discovery data, None when it has gone meanwhile."""
    try:
        return lookup(handle)
    except Exception:  # cyclonedds raises when the handle is no longer matched
        return None


DROPS = DropLog(log, "Nav2", "DDS samples")
"""Samples dropped (unreadable CDR, a pose that is no place), logged by the one rule every reader uses."""


def take(reader: DataReader[Any], n: int) -> list[Any]:
    """Up to `n` samples; a batch that cannot be read (a peer's malformed CDR) is dropped and logged, never the
    end of the bridge."""
    now = time.monotonic()
    DROPS.flush(now)
    try:
        return list(reader.take(n))
    except Exception as exc:  # cyclonedds raises whatever its deserializer met
        DROPS.drop("unreadable", now, reader.topic.name, str(exc)[:200])
        return []


class Nav2Client:
    """One robot's Nav2, on the bridge's participant."""

    def __init__(self, participant: DomainParticipant, names: Nav2Names, frame_id: str) -> None:
        self.frame_id = frame_id
        self._seq = 0
        self._pending: dict[int, bytes] = {}
        """Request number -> the UUID of our goal it sent (until its reply)."""
        services = service_qos()

        def topic(name: str, datatype: Any) -> Topic:
            return Topic(participant, name, datatype)

        send_request = topic(request_topic(names.send_goal), SendGoalRequest)
        self._send = DataWriter(participant, send_request, qos=services)
        self.client_id = int(self._send.instance_handle) & 0xFFFF_FFFF_FFFF_FFFF
        self._participant_key = participant.guid
        """rmw_cyclonedds's client id: its request writer's instance handle, as the header's first 8 bytes."""
        self._requests = DataReader(participant, send_request, qos=services)
        self._replies = DataReader(
            participant, topic(reply_topic(names.send_goal), SendGoalReply), qos=services
        )
        self._cancel = DataWriter(
            participant, topic(request_topic(names.cancel_goal), CancelGoalRequest), qos=services
        )
        self._status = DataReader(
            participant, topic(dds_topic(names.status), GoalStatusArray), qos=status_qos()
        )
        self._pose = DataReader(
            participant, topic(dds_topic(names.pose), PoseWithCovarianceStamped), qos=status_qos()
        )
        plan_qos = Qos(
            Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1)),
            Policy.History.KeepLast(1),
            Policy.DataRepresentation(use_cdrv0_representation=True),
        )
        self._plan = DataReader(participant, topic(dds_topic(names.plan), Path), qos=plan_qos)

    # -- what goes to Nav2 ---------------------------------------------------------------------------------

    def server_refused(self) -> str | None:
        """Why goals cannot go out now (None: they can). A request written before a server reads it is lost (as
        rclcpp's clients wait for the server for the same reason); and a server on another DDS than Cyclone
        (rmw_fastrtps: vendor 01.0f) would read rmw_cyclonedds's request header as the goal's UUID and the rest
        as a garbled pose, so nothing is sent while one listens."""
        servers = []
        for handle in self._send.get_matched_subscriptions():
            endpoint = matched(self._send.get_matched_subscription_data, handle)
            if endpoint is not None and endpoint.participant_key != self._participant_key:
                servers.append(endpoint.participant_key)
        if not servers:
            return "no navigate_to_pose server listens"
        foreign = [k for k in servers if k.bytes[:2] != CYCLONE_VENDOR]
        if foreign:
            return (
                f"a navigate_to_pose server on another DDS (vendor {foreign[0].bytes[0]}.{foreign[0].bytes[1]:02x}: "
                "rmw_fastrtps?) listens; the bridge speaks rmw_cyclonedds's request layout only"
            )
        return None

    def send_goal(self, goal_uuid: bytes, pose: RobotPose) -> None:
        x, y, yaw = pose
        now = ros_time(time.time())
        target = PoseStamped(
            header=Header(stamp=now, frame_id=self.frame_id),
            pose=Pose(
                position=Point(x=x, y=y, z=0.0),
                orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
            ),
        )
        self._seq += 1
        self._pending[self._seq] = goal_uuid
        self._send.write(
            SendGoalRequest(
                client=self.client_id,
                seq=self._seq,
                goal_id=UUID(list(goal_uuid)),
                goal=NavigateToPoseGoal(pose=target, behavior_tree=""),
            )
        )

    def cancel(self, goal_uuid: bytes) -> None:
        """cancel_goal for one goal (stamp 0: that goal only, as rclcpp's async_cancel_goal sends it)."""
        self._seq += 1
        self._cancel.write(
            CancelGoalRequest(
                client=self.client_id, seq=self._seq, goal_info=GoalInfo(goal_id=UUID(list(goal_uuid)))
            )
        )

    # -- what Nav2 shows -----------------------------------------------------------------------------------

    def seen_goals(self) -> list[SeenGoal]:
        """Other clients' goal requests since the last call."""
        seen: list[SeenGoal] = []
        for s in take(self._requests, 64):
            if not isinstance(s, SendGoalRequest) or s.client == self.client_id:
                continue
            info: Any = getattr(s, "sample_info", None)  # cyclonedds attaches it to each sample it takes
            handle = info.publication_handle if info is not None else 0
            writer = matched(self._requests.get_matched_publication_data, handle)
            if writer is None or writer.participant_key.bytes[:2] != CYCLONE_VENDOR:
                DROPS.drop(
                    "not rmw_cyclonedds", time.monotonic(), "a goal request", "its layout is another rmw's"
                )
                continue
            pose = pose_of(s.goal.pose.pose)
            if pose is not None:
                seen.append(SeenGoal(bytes(s.goal_id.uuid), pose, s.goal.pose.header.frame_id))
        return seen

    def replies(self) -> list[tuple[bytes, bool]]:
        """(our goal's UUID, accepted) for the send_goal replies to us since the last call."""
        out: list[tuple[bytes, bool]] = []
        for s in take(self._replies, 64):
            if isinstance(s, SendGoalReply) and s.client == self.client_id and s.seq in self._pending:
                out.append((self._pending.pop(s.seq), bool(s.accepted)))
        return out

    def statuses(self) -> list[list[tuple[bytes, int]]]:
        """Each status array since the last call: (goal UUID, action_msgs status) each."""
        return [
            [(bytes(g.goal_info.goal_id.uuid), int(g.status)) for g in s.status_list]
            for s in take(self._status, 16)
            if isinstance(s, GoalStatusArray)
        ]

    def pose(self) -> RobotPose | None:
        """The latest pose published since the last call (None: none)."""
        latest = None
        for s in take(self._pose, 16):
            if isinstance(s, PoseWithCovarianceStamped):
                latest = pose_of(s.pose.pose) or latest
        return latest

    def plan(self) -> NDArray[np.float64] | None:
        """The latest global plan since the last call, (N, 2) metres (None: none)."""
        latest = None
        for s in take(self._plan, 4):
            if isinstance(s, Path):
                xy = np.array([(p.pose.position.x, p.pose.position.y) for p in s.poses], dtype=np.float64)
                latest = xy.reshape(-1, 2)[np.isfinite(xy.reshape(-1, 2)).all(axis=1)]
        return latest
