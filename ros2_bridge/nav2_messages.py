"""Nav2's NavigateToPose action and what a Nav2 robot publishes, as Cyclone DDS types laid out as rmw_cyclonedds
lays them on the wire, so the bridge is an action client of bt_navigator with no rclpy.

An action `/navigate_to_pose` is three services and two topics (rcl_action): `_action/send_goal`,
`_action/cancel_goal`, `_action/get_result`, `_action/status` and `_action/feedback`. A service `/s` is the DDS
topics `rq/sRequest` and `rr/sReply`; rmw_cyclonedds puts its request id in front of the message in both, in
the CDR itself: the client's request writer (8 bytes: its instance handle) and a sequence number (int64), which
the reply repeats (`cdds_request_header_t` in its serdata.hpp). rmw_fastrtps puts nothing in front: a request's id
is its DATA's sample identity (writer GUID and sequence number, which every DDS writer sends) and the reply names
it in inline QoS (related_sample_identity), so its requests and replies are the messages' CDR alone (the `Plain`
types here). The bridge writes whichever layout the matched server's rmw reads (ros2_bridge.nav2_client).

nav2_msgs/action/NavigateToPose's goal and feedback are the same in Humble and Jazzy; the result differs
(Humble: std_msgs/Empty; Jazzy: error_code, error_msg), and the bridge never asks for it: it follows the goals
on `_action/status`, which every rcl_action server publishes.
"""

# No `from __future__ import annotations` here: cyclonedds reads the field types from the live annotations.

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from cyclonedds.core import Policy, Qos
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float64, int8, int64, sequence, uint8, uint64
from cyclonedds.util import duration

from wsnav.ros2_bridge.messages import Header, Pose, Time, announce_as_cyclone_0_10

if TYPE_CHECKING:
    Uuid16 = list[int]
    Covariance36 = list[float]
else:
    Uuid16 = array[uint8, 16]
    Covariance36 = array[float64, 36]

# action_msgs/msg/GoalStatus
STATUS_UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = range(7)


def request_topic(service: str) -> str:
    return f"rq{service}Request"


def reply_topic(service: str) -> str:
    return f"rr{service}Reply"


@dataclass
class UUID(IdlStruct, typename="unique_identifier_msgs::msg::dds_::UUID_"):
    uuid: Uuid16 = field(default_factory=lambda: [0] * 16)


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class NavigateToPoseGoal(IdlStruct, typename="nav2_msgs::action::dds_::NavigateToPose_Goal_"):
    pose: PoseStamped = field(default_factory=PoseStamped)
    behavior_tree: str = ""


@dataclass
class SendGoalRequest(IdlStruct, typename="nav2_msgs::action::dds_::NavigateToPose_SendGoal_Request_"):
    client: uint64 = 0
    """rmw_cyclonedds's request header: the client's request writer..."""
    seq: int64 = 0
    """...and the request's number, repeated in the reply."""
    goal_id: UUID = field(default_factory=UUID)
    goal: NavigateToPoseGoal = field(default_factory=NavigateToPoseGoal)


@dataclass
class PlainSendGoalRequest(IdlStruct, typename="nav2_msgs::action::dds_::NavigateToPose_SendGoal_Request_"):
    """rmw_fastrtps's send_goal request: no header (the id is the DATA's sample identity)."""

    goal_id: UUID = field(default_factory=UUID)
    goal: NavigateToPoseGoal = field(default_factory=NavigateToPoseGoal)


@dataclass
class SendGoalReply(IdlStruct, typename="nav2_msgs::action::dds_::NavigateToPose_SendGoal_Response_"):
    client: uint64 = 0
    seq: int64 = 0
    accepted: bool = False
    stamp: Time = field(default_factory=Time)


@dataclass
class GoalInfo(IdlStruct, typename="action_msgs::msg::dds_::GoalInfo_"):
    goal_id: UUID = field(default_factory=UUID)
    stamp: Time = field(default_factory=Time)


@dataclass
class CancelGoalRequest(IdlStruct, typename="action_msgs::srv::dds_::CancelGoal_Request_"):
    client: uint64 = 0
    seq: int64 = 0
    goal_info: GoalInfo = field(default_factory=GoalInfo)


@dataclass
class PlainCancelGoalRequest(IdlStruct, typename="action_msgs::srv::dds_::CancelGoal_Request_"):
    """rmw_fastrtps's cancel_goal request: no header."""

    goal_info: GoalInfo = field(default_factory=GoalInfo)


if TYPE_CHECKING:
    GoalInfoSequence = list[GoalInfo]
else:
    GoalInfoSequence = sequence[GoalInfo]


@dataclass
class CancelGoalReply(IdlStruct, typename="action_msgs::srv::dds_::CancelGoal_Response_"):
    client: uint64 = 0
    seq: int64 = 0
    return_code: int8 = 0
    goals_canceling: GoalInfoSequence = field(default_factory=list)


@dataclass
class GoalStatus(IdlStruct, typename="action_msgs::msg::dds_::GoalStatus_"):
    goal_info: GoalInfo = field(default_factory=GoalInfo)
    status: int8 = 0


if TYPE_CHECKING:
    GoalStatusSequence = list[GoalStatus]
else:
    GoalStatusSequence = sequence[GoalStatus]


@dataclass
class GoalStatusArray(IdlStruct, typename="action_msgs::msg::dds_::GoalStatusArray_"):
    status_list: GoalStatusSequence = field(default_factory=list)


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose = field(default_factory=Pose)
    covariance: Covariance36 = field(default_factory=lambda: [0.0] * 36)


@dataclass
class PoseWithCovarianceStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"):
    """AMCL's /amcl_pose (and slam_toolbox's /pose): the robot's pose in the map frame."""

    header: Header = field(default_factory=Header)
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)


if TYPE_CHECKING:
    PoseStampedSequence = list[PoseStamped]
else:
    PoseStampedSequence = sequence[PoseStamped]


@dataclass
class Path(IdlStruct, typename="nav_msgs::msg::dds_::Path_"):
    """planner_server's /plan: the global plan a zone change may touch."""

    header: Header = field(default_factory=Header)
    poses: PoseStampedSequence = field(default_factory=list)


for _type in (
    SendGoalRequest,
    PlainSendGoalRequest,
    PlainCancelGoalRequest,
    SendGoalReply,
    CancelGoalRequest,
    CancelGoalReply,
    GoalStatusArray,
    PoseWithCovarianceStamped,
    Path,
):
    announce_as_cyclone_0_10(_type)


def service_qos() -> Qos:
    """rmw_qos_profile_services_default: reliable, volatile, keep last 10."""
    return Qos(
        Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1)),
        Policy.Durability.Volatile,
        Policy.History.KeepLast(10),
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )


def status_qos() -> Qos:
    """rcl_action's status topic: reliable, transient_local, keep last 1 (also AMCL's /amcl_pose)."""
    return Qos(
        Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1)),
        Policy.Durability.TransientLocal,
        Policy.History.KeepLast(1),
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )
