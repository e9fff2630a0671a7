"""The DDS side of `wsnav ros2 bridge`: one participant, the zone grid and its CostmapFilterInfo as ROS 2 topics.

Both are written reliable + transient_local with depth 1, so Nav2's StaticLayer (map_subscribe_transient_local)
and KeepoutFilter, and any subscriber that comes later, get the last grid; the whole grid goes out on each change
(a KeepoutFilter mask has no `_updates` topic, and a StaticLayer takes a new whole map as it comes).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

from cyclonedds.core import DDSException, Policy, Qos
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic

from wsnav.ros2_bridge.discovery import NODE_NAME, NODE_NAMESPACE
from wsnav.ros2_bridge.messages import (
    DISCOVERY_TOPIC,
    KEEPOUT_FILTER,
    CostmapFilterInfo,
    Gid16,
    Gid24,
    Header,
    MapMetaData,
    NodeEntitiesInfo16,
    NodeEntitiesInfo24,
    OccupancyGrid,
    ParticipantEntitiesInfo16,
    ParticipantEntitiesInfo24,
    Point,
    Pose,
    Quaternion,
    Time,
    dds_topic,
    latched_qos,
)
from wsnav.ros_bridge.zone_feed import ZoneFeed
from wsnav.ros_bridge.zone_grid import ZoneGridCodec
from wsnav.runtime.cli_support import CliError
from wsnav.zones.geometry import GridFrame

GRID_TOPIC = "zone_grid"
FILTER_INFO_TOPIC = "costmap_filter_info"
ENCLAVE_USER_DATA = b"enclave=/;"
"""The participant's USER_DATA as rmw sets it: ROS 2's graph reads the participant's security enclave from it."""
GID_SIZE = {"humble": 24, "jazzy": 16}
"""rmw_dds_common's Gid: 24 bytes in Humble (the GUID and 8 zero bytes), 16 from Iron on."""
ENTITIES_INFO_TYPES: dict[int, tuple[type[Any], type[Any], type[Any]]] = {
    24: (Gid24, NodeEntitiesInfo24, ParticipantEntitiesInfo24),
    16: (Gid16, NodeEntitiesInfo16, ParticipantEntitiesInfo16),
}
"""Gid, NodeEntitiesInfo and ParticipantEntitiesInfo for a Gid size."""


@dataclass(frozen=True)
class Ros2Names:
    """The ROS 2 topic names under a namespace (`/wsn` -> `/wsn/zone_grid`)."""

    namespace: str

    @property
    def grid(self) -> str:
        return f"{self.namespace}/{GRID_TOPIC}"

    @property
    def filter_info(self) -> str:
        return f"{self.namespace}/{FILTER_INFO_TOPIC}"


def ros_time(t: float) -> Time:
    """builtin_interfaces/Time of a Unix time."""
    ns = round(t * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


class ZoneGridWriter:
    """Writes the zone feed's grid, encoded by the ROS 1 bridge's codec, as nav_msgs/msg/OccupancyGrid."""

    def __init__(
        self,
        domain: int,
        names: Ros2Names,
        frame_id: str,
        frame: GridFrame,
        origin_yaw: float,
        codec: ZoneGridCodec,
        config: str = "",
        distro: str = "humble",
    ) -> None:
        """`config`: the Cyclone DDS configuration (ros2_bridge.discovery.cyclone_config); "" is Cyclone's own
        (CYCLONEDDS_URI). `distro`: whose rmw_dds_common layout ros_discovery_info is written in."""
        self.names = names
        self.frame_id = frame_id
        self.frame = frame
        self.origin_yaw = origin_yaw
        self.codec = codec
        try:
            self.domain = Domain(domain, config) if config else None  # kept: the participant lives in it
            self.participant = DomainParticipant(domain, qos=Qos(Policy.Userdata(ENCLAVE_USER_DATA)))
            qos = latched_qos()
            self._grid = DataWriter(
                self.participant, Topic(self.participant, dds_topic(names.grid), OccupancyGrid), qos=qos
            )
            self._info = DataWriter(
                self.participant,
                Topic(self.participant, dds_topic(names.filter_info), CostmapFilterInfo),
                qos=qos,
            )
            self._write_entities_info(distro, qos)
        except DDSException as exc:
            raise CliError(f"cannot start DDS on ROS 2 domain {domain}: {exc}") from None

    def _write_entities_info(self, distro: str, qos: Qos) -> None:
        """The participant's node and its two publishers on ros_discovery_info, as rmw publishes them (reliable,
        transient_local, depth 1): what `ros2 node list` and `ros2 topic info -v` read. Written once: they never
        change while the bridge runs."""
        size = GID_SIZE[distro]

        def gid(entity: DomainParticipant | DataWriter) -> list[int]:
            return list(entity.guid.bytes.ljust(size, b"\0"))

        gid_type, node_type, info_type = ENTITIES_INFO_TYPES[size]
        writers = [gid_type(gid(self._grid)), gid_type(gid(self._info))]
        node = node_type(NODE_NAMESPACE, NODE_NAME, [], writers)
        self._entities = DataWriter(
            self.participant, Topic(self.participant, DISCOVERY_TOPIC, info_type), qos=qos
        )
        self._entities.write(info_type(gid_type(gid(self.participant)), [node]))

    def grid_message(self, feed: ZoneFeed, now: float) -> OccupancyGrid:
        stamp = ros_time(now)
        half = self.origin_yaw / 2
        return OccupancyGrid(
            header=Header(stamp=stamp, frame_id=self.frame_id),
            info=MapMetaData(
                map_load_time=stamp,
                resolution=self.frame.resolution,
                width=self.frame.width,
                height=self.frame.height,
                origin=Pose(
                    position=Point(x=self.frame.origin_x, y=self.frame.origin_y, z=0.0),
                    orientation=Quaternion(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)),
                ),
            ),
            data=self.codec.encode(feed.costs).ravel().tolist(),
        )

    def write_grid(self, feed: ZoneFeed) -> None:
        """Raises DDSException when a reliable reader held the write up for longer than WRITE_BLOCK_S."""
        self._grid.write(self.grid_message(feed, time.time()))

    def write_filter_info(self) -> None:
        """The KeepoutFilter's info: keepout type, this grid as the mask, base 0 and multiplier 1 (as it wants)."""
        self._info.write(
            CostmapFilterInfo(
                header=Header(stamp=ros_time(time.time()), frame_id=self.frame_id),
                type=KEEPOUT_FILTER,
                filter_mask_topic=self.names.grid,
                base=0.0,
                multiplier=1.0,
            )
        )
