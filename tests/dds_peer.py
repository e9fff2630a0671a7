"""An independent ROS 2 subscriber for the `wsnav ros2 bridge` tests, run as its own process (no tests here).

Plain cyclonedds with its OWN copies of ROS 2 Humble's type definitions (not wsnav.ros2_bridge.messages), used
only to match the writers; every sample is handed over raw, as the CDR bytes that crossed the wire, for the test
to decode with rosbags. The reader asks for what a ROS 2 (rmw_cyclonedds) subscriber of Nav2 asks for: reliable,
transient_local, XCDR1 only; its history keeps 10 samples, so a writer that kept more than one would show it.
One JSON line per sample on stdout: the topic, the matched writer's type name and QoS, the bytes in base64.

    python -m tests.dds_peer --domain N rt/wsn/zone_grid rt/wsn/costmap_filter_info
"""

# No `from __future__ import annotations`: cyclonedds reads the field types from the live annotations.

import argparse
import base64
import json
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from cyclonedds.core import Policy, Qos, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, bounded_str, float32, float64, int8, int32, sequence, uint8, uint32
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

if TYPE_CHECKING:
    Int8s = list[int]
else:
    Int8s = sequence[int8]


@dataclass
class Stamp(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Hdr(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Stamp = field(default_factory=Stamp)
    frame_id: str = ""


@dataclass
class Pt(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quat(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class PoseMsg(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Pt = field(default_factory=Pt)
    orientation: Quat = field(default_factory=Quat)


@dataclass
class Meta(IdlStruct, typename="nav_msgs::msg::dds_::MapMetaData_"):
    map_load_time: Stamp = field(default_factory=Stamp)
    resolution: float32 = 0.0
    width: uint32 = 0
    height: uint32 = 0
    origin: PoseMsg = field(default_factory=PoseMsg)


@dataclass
class Grid(IdlStruct, typename="nav_msgs::msg::dds_::OccupancyGrid_"):
    header: Hdr = field(default_factory=Hdr)
    info: Meta = field(default_factory=Meta)
    data: Int8s = field(default_factory=list)


@dataclass
class FilterInfo(IdlStruct, typename="nav2_msgs::msg::dds_::CostmapFilterInfo_"):
    header: Hdr = field(default_factory=Hdr)
    type: uint8 = 0
    filter_mask_topic: str = ""
    base: float32 = 0.0
    multiplier: float32 = 1.0


if TYPE_CHECKING:
    Gid24Data = list[int]
    Gid16Data = list[int]
    String256 = str
else:
    Gid24Data = array[uint8, 24]
    Gid16Data = array[uint8, 16]
    String256 = bounded_str[256]


@dataclass
class GidMsg(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    data: Gid24Data = field(default_factory=lambda: [0] * 24)


@dataclass
class GidMsg16(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    data: Gid16Data = field(default_factory=lambda: [0] * 16)


if TYPE_CHECKING:
    Gids = list[GidMsg]
    Gids16 = list[GidMsg16]
else:
    Gids = sequence[GidMsg]
    Gids16 = sequence[GidMsg16]


@dataclass
class NodeInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace: String256 = ""
    node_name: String256 = ""
    reader_gid_seq: Gids = field(default_factory=list)
    writer_gid_seq: Gids = field(default_factory=list)


@dataclass
class NodeInfo16(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace: String256 = ""
    node_name: String256 = ""
    reader_gid_seq: Gids16 = field(default_factory=list)
    writer_gid_seq: Gids16 = field(default_factory=list)


if TYPE_CHECKING:
    NodeInfos = list[NodeInfo]
    NodeInfos16 = list[NodeInfo16]
else:
    NodeInfos = sequence[NodeInfo]
    NodeInfos16 = sequence[NodeInfo16]


@dataclass
class EntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
    """Humble's layout (24-byte gids)."""

    gid: GidMsg = field(default_factory=GidMsg)
    node_entities_info_seq: NodeInfos = field(default_factory=list)


@dataclass
class EntitiesInfo16(IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
    """Iron's and later layout (16-byte gids): `--gid-bytes 16`. Cyclone checks the bytes against the reader's
    type before handing them over, so the reader must have the writer's layout."""

    gid: GidMsg16 = field(default_factory=GidMsg16)
    node_entities_info_seq: NodeInfos16 = field(default_factory=list)


TYPES: dict[str, type[IdlStruct]] = {
    "zone_grid": Grid,
    "costmap_filter_info": FilterInfo,
    "ros_discovery_info": EntitiesInfo,
}


class Raw:
    """A sample as the bytes that arrived (the 4-byte encapsulation header, then the CDR body)."""

    def __init__(self, data: bytes) -> None:
        self.data = bytes(data)
        self.sample_info: Any = None


class RawType:
    """Put in place of the topic's data type once the topic exists: the reader then hands samples over raw."""

    @staticmethod
    def deserialize(data: bytes, **_: Any) -> Raw:
        return Raw(data)

    deserialize_key = deserialize


def describe(qos: Qos) -> dict[str, Any]:
    """The writer's QoS as discovery told it, in the DDS spec's words."""
    out: dict[str, Any] = {}
    for policy in qos:
        if isinstance(policy, Policy.Reliability.Reliable):
            out["reliability"] = "RELIABLE"
        elif policy == Policy.Reliability.BestEffort:
            out["reliability"] = "BEST_EFFORT"
        elif policy in (Policy.Durability.Volatile, Policy.Durability.TransientLocal):
            out["durability"] = "VOLATILE" if policy == Policy.Durability.Volatile else "TRANSIENT_LOCAL"
        elif policy in (Policy.Durability.Transient, Policy.Durability.Persistent):
            out["durability"] = str(policy)
        elif isinstance(policy, Policy.History.KeepLast):
            out["history"] = ["KEEP_LAST", policy.depth]
        elif policy == Policy.History.KeepAll:
            out["history"] = ["KEEP_ALL"]
        elif isinstance(policy, Policy.DataRepresentation):
            out["data_representation"] = [
                name
                for name, on in (
                    ("XCDR1", policy.use_cdrv0_representation),
                    ("XCDR2", policy.use_xcdrv2_representation),
                )
                if on
            ]
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--seconds", type=float, default=120.0)
    parser.add_argument("--gid-bytes", type=int, choices=[24, 16], default=24)
    parser.add_argument("topics", nargs="+")
    args = parser.parse_args()
    # rmw_cyclonedds's readers carry no XTypes type information and are matched by type name; this one ignores
    # the type information of Cyclone writers (vendor 1.16) to be matched the same way: Cyclone 11 would find its
    # int8 (TK_INT8) not assignable to the TK_CHAR8 that Cyclone 0.10, and so the bridge, announce.
    domain = Domain(
        args.domain, "<Compatibility><IgnoreTypeInformation>1.16</IgnoreTypeInformation></Compatibility>"
    )
    participant = DomainParticipant(args.domain)
    qos = Qos(
        Policy.Reliability.Reliable(duration(seconds=1)),
        Policy.Durability.TransientLocal,
        Policy.History.KeepLast(10),
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )
    waitset = WaitSet(participant)
    readers: list[tuple[str, DataReader[Any]]] = []
    for name in args.topics:
        short = name.rsplit("/", 1)[-1]
        datatype = EntitiesInfo16 if short == "ros_discovery_info" and args.gid_bytes == 16 else TYPES[short]
        topic = Topic(participant, name, datatype)
        topic.data_type = RawType  # pyright: ignore[reportAttributeAccessIssue]
        reader = DataReader(participant, topic, qos=qos)
        waitset.attach(reader)
        readers.append((name, reader))
    print(json.dumps({"ready": True}), flush=True)
    deadline = time.monotonic() + args.seconds
    while time.monotonic() < deadline:
        waitset.wait(duration(milliseconds=200))
        for name, reader in readers:
            for sample in reader.take(N=100):
                if not isinstance(sample, Raw):
                    continue
                writer = reader.get_matched_publication_data(sample.sample_info.publication_handle)
                line = {
                    "topic": name,
                    "writer_topic": writer.topic_name if writer else None,
                    "type_name": writer.type_name if writer else None,
                    "writer_guid": str(writer.key) if writer else None,
                    "participant_guid": str(writer.participant_key) if writer else None,
                    "qos": describe(writer.qos) if writer else {},
                    "cdr": base64.b64encode(sample.data).decode(),
                }
                print(json.dumps(line), flush=True)
    del domain
    sys.exit(0)


if __name__ == "__main__":
    main()
