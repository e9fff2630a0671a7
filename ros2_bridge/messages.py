"""ROS 2 Humble's messages for the zone grid as Cyclone DDS types, and the names and QoS ROS 2 gives them on the wire.

ROS 2 (rmw_cyclonedds, rmw_fastrtps) maps a topic `/a/b` to the DDS topic `rt/a/b` and a message `pkg/msg/T` to
the DDS type `pkg::msg::dds_::T_`, serialized as plain CDR (XCDR1): so a DDS writer with these names, these fields
in this order and these types is a ROS 2 publisher to any ROS 2 subscriber, with no rclpy. The fields follow
Humble's .msg files (builtin_interfaces, std_msgs, geometry_msgs, nav_msgs, nav2_msgs) exactly.
"""

# No `from __future__ import annotations` here: cyclonedds reads the field types from the live annotations.

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import cyclonedds.idl._typesupport.DDS.XTypes as xt  # pyright: ignore[reportMissingTypeStubs]
from cyclonedds.core import Policy, Qos
from cyclonedds.idl import IdlStruct
from cyclonedds.idl._support import Endianness
from cyclonedds.idl._xt_builder import TypeHash, XTBuilder
from cyclonedds.idl.types import array, bounded_str, float32, float64, int8, int32, sequence, uint8, uint32
from cyclonedds.util import duration

DDS_TOPIC_PREFIX = "rt"
"""ROS 2's prefix for topics (rmw's ros_topic_prefix): `/wsn/zone_grid` is DDS topic `rt/wsn/zone_grid`."""

WRITE_BLOCK_S = 1.0
"""How long a write may wait for a slow reliable reader before it fails (and is tried again): never hang."""


if TYPE_CHECKING:
    Int8Sequence = list[int]
    Gid24Data = list[int]
    Gid16Data = list[int]
    String256 = str
else:  # cyclonedds's sequence[...] is Annotated[Sequence[...], ...] at run time, which pyright does not read
    Int8Sequence = sequence[int8]
    Gid24Data = array[uint8, 24]
    Gid16Data = array[uint8, 16]
    String256 = bounded_str[256]
"""ROS 2's int8[]: an unbounded IDL sequence (serialized in one piece, unlike a plain list[int8]); char[24] and
char[16] (ROS's char is uint8): rmw_dds_common's Gid in Humble and from Iron on; string<=256."""


def dds_topic(ros_topic: str) -> str:
    """The DDS topic name of an absolute ROS 2 topic name."""
    return DDS_TOPIC_PREFIX + ros_topic


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class MapMetaData(IdlStruct, typename="nav_msgs::msg::dds_::MapMetaData_"):
    map_load_time: Time = field(default_factory=Time)
    resolution: float32 = 0.0
    width: uint32 = 0
    height: uint32 = 0
    origin: Pose = field(default_factory=Pose)


@dataclass
class OccupancyGrid(IdlStruct, typename="nav_msgs::msg::dds_::OccupancyGrid_"):
    header: Header = field(default_factory=Header)
    info: MapMetaData = field(default_factory=MapMetaData)
    data: Int8Sequence = field(default_factory=list)


@dataclass
class CostmapFilterInfo(IdlStruct, typename="nav2_msgs::msg::dds_::CostmapFilterInfo_"):
    header: Header = field(default_factory=Header)
    type: uint8 = 0
    filter_mask_topic: str = ""
    base: float32 = 0.0
    multiplier: float32 = 1.0


DISCOVERY_TOPIC = "ros_discovery_info"
"""rmw_dds_common's graph topic, without the rt/ prefix (rmw creates it avoiding ROS's namespace conventions)."""


@dataclass
class Gid24(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    data: Gid24Data = field(default_factory=lambda: [0] * 24)


if TYPE_CHECKING:
    Gid24Sequence = list[Gid24]
else:
    Gid24Sequence = sequence[Gid24]


@dataclass
class NodeEntitiesInfo24(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace: String256 = ""
    node_name: String256 = ""
    reader_gid_seq: Gid24Sequence = field(default_factory=list)
    writer_gid_seq: Gid24Sequence = field(default_factory=list)


if TYPE_CHECKING:
    NodeEntitiesInfo24Sequence = list[NodeEntitiesInfo24]
else:
    NodeEntitiesInfo24Sequence = sequence[NodeEntitiesInfo24]


@dataclass
class ParticipantEntitiesInfo24(IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
    """Humble's rmw_dds_common/msg/ParticipantEntitiesInfo (24-byte gids: a DDS GUID and 8 zero bytes)."""

    gid: Gid24 = field(default_factory=Gid24)
    node_entities_info_seq: NodeEntitiesInfo24Sequence = field(default_factory=list)


@dataclass
class Gid16(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    data: Gid16Data = field(default_factory=lambda: [0] * 16)


if TYPE_CHECKING:
    Gid16Sequence = list[Gid16]
else:
    Gid16Sequence = sequence[Gid16]


@dataclass
class NodeEntitiesInfo16(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace: String256 = ""
    node_name: String256 = ""
    reader_gid_seq: Gid16Sequence = field(default_factory=list)
    writer_gid_seq: Gid16Sequence = field(default_factory=list)


if TYPE_CHECKING:
    NodeEntitiesInfo16Sequence = list[NodeEntitiesInfo16]
else:
    NodeEntitiesInfo16Sequence = sequence[NodeEntitiesInfo16]


@dataclass
class ParticipantEntitiesInfo16(IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
    """Iron's and later (Jazzy's) rmw_dds_common/msg/ParticipantEntitiesInfo: 16-byte gids, the DDS GUID."""

    gid: Gid16 = field(default_factory=Gid16)
    node_entities_info_seq: NodeEntitiesInfo16Sequence = field(default_factory=list)


KEEPOUT_FILTER = 0
"""CostmapFilterInfo.type of Nav2's KeepoutFilter (nav2_costmap_2d's filter_values.hpp: KEEPOUT_FILTER)."""


def latched_qos() -> Qos:
    """ROS 2's reliable + transient_local + keep-last 1 (Nav2's map_server and costmap_filter_info_server), as
    rmw_cyclonedds sets it: the durability service keeps the same history, instances are not disposed when the
    writer goes, and the data goes as XCDR1, the only representation Humble's rmw accepts."""
    return Qos(
        Policy.Reliability.Reliable(max_blocking_time=duration(seconds=WRITE_BLOCK_S)),
        Policy.Durability.TransientLocal,
        Policy.History.KeepLast(1),
        Policy.DurabilityService(
            cleanup_delay=0,
            history=Policy.History.KeepLast(1),
            max_samples=-1,
            max_instances=-1,
            max_samples_per_instance=-1,
        ),
        Policy.WriterDataLifecycle(autodispose=False),
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )


class _Cyclone010TypeObjects(XTBuilder):
    """XTypes type objects as Cyclone DDS 0.10's IDL compiler writes them: int8 as TK_CHAR8, uint8 as TK_BYTE.

    Cyclone DDS 11 writes TK_INT8 / TK_UINT8 (XTypes 1.3), which Cyclone 0.10 (what ROS 2 Humble and Jazzy
    ship) cannot validate: a 0.10 participant that looks the bridge's types up dies with SIGSEGV in its
    TypeLookup reply handling (eclipse-cyclonedds/cyclonedds#1554). Cyclone 11's Python binding cannot leave the
    type information out (a topic needs it), so the bridge announces the types exactly as 0.10 does: the same
    type identifiers, which a 0.10 reader with type information matches at once. The CDR on the wire is the same.
    """

    # its own cache of type hashes: the library's holds the TK_INT8 ones
    _type_hash_db: ClassVar[dict[Any, TypeHash]] = {}  # pyright: ignore[reportIncompatibleVariableOverride]

    @classmethod
    def _xt_type_identifier(cls, name: str, entity: Any, minimal: bool) -> Any:
        if entity == int8:
            return xt.TypeIdentifier(discriminator=xt.TK_CHAR8, value=None)
        if entity == uint8:
            return xt.TypeIdentifier(discriminator=xt.TK_BYTE, value=None)
        return super()._xt_type_identifier(name, entity, minimal)


def announce_as_cyclone_0_10(datatype: type[IdlStruct]) -> None:
    """Give a topic type the type information Cyclone 0.10 would announce for it (before any Topic uses it)."""
    idl: Any = datatype.__idl__
    info, mapping = _Cyclone010TypeObjects.process_type(datatype)
    idl._xt_data = (info, mapping)
    idl._xt_bytedata = (
        info.serialize(endianness=Endianness.Little, use_version_2=True)[4:],
        mapping.serialize(endianness=Endianness.Little, use_version_2=True)[4:],
    )


for _topic_type in (OccupancyGrid, CostmapFilterInfo, ParticipantEntitiesInfo24, ParticipantEntitiesInfo16):
    announce_as_cyclone_0_10(_topic_type)
