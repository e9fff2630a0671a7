"""The DDS side of `wsnav ros2 bridge --robot`: an action client of Nav2's `navigate_to_pose` as rclcpp's is on
rmw_cyclonedds or rmw_fastrtps (ros2_bridge.nav2_messages), a watcher of everyone's goal requests, and readers of
the robot's pose (`/amcl_pose`) and of the global plan (`/plan`).

The two rmws lay a request out differently (rmw_cyclonedds: a 16-byte header, then the CDR; rmw_fastrtps: the CDR
alone), so the request writers are made in the layout of the rmw whose server is matched (a site runs one rmw):
rmw_cyclonedds's first, re-made as rmw_fastrtps's when the first server seen is on Fast DDS (vendor 1.15).
Other clients' goals are seen by reading the send_goal request topic itself (a DDS topic any reader may read);
the bridge's own requests come back there too and are told apart by the client id in rmw_cyclonedds's header,
or by their writer under rmw_fastrtps. The request writer carries no `clientid` user data: rmw_cyclonedds's
server then answers at once rather than waiting to match the client's reply reader by it (its
"backwards-compatibility" branch); rmw_fastrtps's waits for a reply reader only when the request names one
(related_sample_identity), which the bridge's do not. Replies are read under rmw_cyclonedds only (rmw_fastrtps's
name their request in inline QoS, which cyclonedds-python does not show): the bridge follows goals on the status
topic either way.
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
    PlainCancelGoalRequest,
    PlainSendGoalRequest,
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
"""The first bytes of a Cyclone DDS participant's GUID (its RTPS vendor id, 1.16)."""
FAST_DDS_VENDOR = b"\x01\x0f"
"""The same for Fast DDS (1.15)."""


@dataclass(frozen=True)
class RequestLayout:
    """How one rmw lays a service request on the wire: the DDS vendor its servers run on, and the types."""

    rmw: str
    vendor: bytes
    send_goal: type[Any]
    cancel_goal: type[Any]
    header: bool
    """The request carries rmw_cyclonedds's header (client id, sequence number) in its CDR."""


CYCLONEDDS_LAYOUT = RequestLayout("rmw_cyclonedds", CYCLONE_VENDOR, SendGoalRequest, CancelGoalRequest, True)
FASTRTPS_LAYOUT = RequestLayout(
    "rmw_fastrtps", FAST_DDS_VENDOR, PlainSendGoalRequest, PlainCancelGoalRequest, False
)
LAYOUT_OF_VENDOR = {layout.vendor: layout for layout in (CYCLONEDDS_LAYOUT, FASTRTPS_LAYOUT)}


def vendor_name(vendor: bytes) -> str:
    return f"{vendor[0]}.{vendor[1]:02x}"


def matched(lookup: Any, handle: int) -> Any:
    """A matched endpoint's discovery data, None when it has gone meanwhile."""
    try:
        return lookup(handle)
    except Exception:  # cyclonedds raises when the handle is no longer matched
        return None


DROPS = DropLog(log, "Nav2", "DDS samples")
"""Samples dropped (unreadable CDR, a pose that is no place), logged by the one rule every reader uses."""


def delete(entity: Any) -> None:
    """Delete a DDS entity now (cyclonedds-python deletes it when the object is collected)."""
    if entity is not None:
        entity.__del__()


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
        self._participant = participant
        self._names = names
        self._participant_key = participant.guid
        self._request_entities: list[Any] = []
        self._replies: DataReader[Any] | None = None
        self.layout = CYCLONEDDS_LAYOUT
        self._make_request_entities(CYCLONEDDS_LAYOUT)

        def topic(name: str, datatype: Any) -> Topic:
            return Topic(participant, name, datatype)

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

    def _make_request_entities(self, layout: RequestLayout) -> None:
        """(Re-)make the request writers, the request watcher and (rmw_cyclonedds) the reply reader in `layout`."""
        for entity in self._request_entities:
            delete(entity)
        self._request_entities.clear()
        self._replies = None
        self.layout = layout
        participant, names, services = self._participant, self._names, service_qos()
        send_request = Topic(participant, request_topic(names.send_goal), layout.send_goal)
        cancel_request = Topic(participant, request_topic(names.cancel_goal), layout.cancel_goal)
        self._send = DataWriter(participant, send_request, qos=services)
        self.client_id = int(self._send.instance_handle) & 0xFFFF_FFFF_FFFF_FFFF
        """rmw_cyclonedds's client id: its request writer's instance handle, as the header's first 8 bytes."""
        self._requests = DataReader(participant, send_request, qos=services)
        self._cancel = DataWriter(participant, cancel_request, qos=services)
        made: list[Any] = [self._send, self._requests, self._cancel]
        if layout.header:
            reply = Topic(participant, reply_topic(names.send_goal), SendGoalReply)
            self._replies = DataReader(participant, reply, qos=services)
            made += [self._replies, reply]
        self._request_entities = [*made, send_request, cancel_request]
        self._pending.clear()

    # -- what goes to Nav2 ---------------------------------------------------------------------------------

    def server_refused(self) -> str | None:
        """Why goals cannot go out now (None: they can). A request written before a server reads it is lost (as
        rclcpp's clients wait for the server for the same reason). The request layout follows the server's rmw
        (its DDS vendor): a server on the other one would read the goal's UUID and pose from the wrong bytes, so
        a change of rmw re-makes the writers (goals wait for the server to match them), and servers of both
        rmws at once, or of another DDS, get nothing."""
        servers = []
        for handle in self._send.get_matched_subscriptions():
            endpoint = matched(self._send.get_matched_subscription_data, handle)
            if endpoint is not None and endpoint.participant_key != self._participant_key:
                servers.append(endpoint.participant_key.bytes[:2])
        if not servers:
            return "no navigate_to_pose server listens"
        vendors = sorted(set(servers))
        unknown = [v for v in vendors if v not in LAYOUT_OF_VENDOR]
        if unknown:
            return (
                f"a navigate_to_pose server on a DDS the bridge does not speak (vendor {vendor_name(unknown[0])}) "
                "listens; the bridge writes rmw_cyclonedds's and rmw_fastrtps's request layouts only"
            )
        if len(vendors) > 1:
            return (
                "navigate_to_pose servers on rmw_cyclonedds AND rmw_fastrtps listen; their requests differ and a "
                "site runs one rmw, so neither gets goals"
            )
        layout = LAYOUT_OF_VENDOR[vendors[0]]
        if layout is not self.layout:
            log.warning("the navigate_to_pose server runs %s: requests now in its layout", layout.rmw)
            self._make_request_entities(layout)
            return f"request writers re-made for {layout.rmw}; waiting for the server to match them"
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
        goal = NavigateToPoseGoal(pose=target, behavior_tree="")
        if not self.layout.header:
            self._send.write(PlainSendGoalRequest(goal_id=UUID(list(goal_uuid)), goal=goal))
            return
        self._seq += 1
        self._pending[self._seq] = goal_uuid
        self._send.write(
            SendGoalRequest(client=self.client_id, seq=self._seq, goal_id=UUID(list(goal_uuid)), goal=goal)
        )

    def cancel(self, goal_uuid: bytes) -> None:
        """cancel_goal for one goal (stamp 0: that goal only, as rclcpp's async_cancel_goal sends it)."""
        info = GoalInfo(goal_id=UUID(list(goal_uuid)))
        if not self.layout.header:
            self._cancel.write(PlainCancelGoalRequest(goal_info=info))
            return
        self._seq += 1
        self._cancel.write(CancelGoalRequest(client=self.client_id, seq=self._seq, goal_info=info))

    # -- what Nav2 shows -----------------------------------------------------------------------------------

    def seen_goals(self) -> list[SeenGoal]:
        """Other clients' goal requests since the last call."""
        seen: list[SeenGoal] = []
        layout = self.layout
        own = int(self._send.instance_handle)
        for s in take(self._requests, 64):
            if not isinstance(s, layout.send_goal) or (layout.header and s.client == self.client_id):
                continue
            info: Any = getattr(s, "sample_info", None)  # cyclonedds attaches it to each sample it takes
            handle = info.publication_handle if info is not None else 0
            if handle == own:
                continue
            writer = matched(self._requests.get_matched_publication_data, handle)
            if writer is None or writer.participant_key.bytes[:2] != layout.vendor:
                DROPS.drop(
                    f"not {layout.rmw}", time.monotonic(), "a goal request", "its layout is another rmw's"
                )
                continue
            pose = pose_of(s.goal.pose.pose)
            if pose is not None:
                seen.append(SeenGoal(bytes(s.goal_id.uuid), pose, s.goal.pose.header.frame_id))
        return seen

    def replies(self) -> list[tuple[bytes, bool]]:
        """(our goal's UUID, accepted) for the send_goal replies to us since the last call."""
        out: list[tuple[bytes, bool]] = []
        if self._replies is None:
            return out
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
