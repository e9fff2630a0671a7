"""`wsnav ros2 bridge` as a real process against the real broker (embedded amqtt), read on DDS by an independent
ROS 2-style subscriber in another process (tests/dds_peer.py: its own copies of the types, raw CDR bytes out).

Checked on the wire: the DDS topic names (`rt/wsn/zone_grid`, `rt/wsn/costmap_filter_info`) and type names
(`nav_msgs::msg::dds_::OccupancyGrid_`, `nav2_msgs::msg::dds_::CostmapFilterInfo_`) as the matched writer
announces them; its QoS (RELIABLE, TRANSIENT_LOCAL, keep-last 1, XCDR1: the peer asks for XCDR1 only, as
Humble's rmw_cyclonedds does); that a subscriber started after the grid was written still gets it, and only the
last one (its own history keeps 10); that the bytes decode with rosbags' ROS 2 Humble definitions
(`nav2_msgs/msg/CostmapFilterInfo` from Nav2's Humble .msg, which rosbags does not ship); and that the grid's
values are the ROS 1 bridge's for the same zone states: a zone layer in the test (ros_bridge's ZoneFeed) fed the
same MQTT messages and encoded by ros_bridge's ZoneGridCodec, which is what `wsnav ros bridge` serves, so a zone
blocked over MQTT shows up lethal in the next grid. Also: the grid is written before the broker answers, and an
unreachable broker is said once.

Also: the bridge as a ROS 2 node on ros_discovery_info, in Humble's and Jazzy's rmw_dds_common bytes.

Not checked here: no ROS 2 and no Nav2 run here. No rclcpp/rclpy subscriber and no StaticLayer or KeepoutFilter
reading the grid: that Nav2 turns these values into the costs docs/ros.md says is read from Nav2's source, not
run. The DDS that ROS 2 ships (Cyclone 0.10, Fast DDS 2.9) is tests/test_ros2_dds_peers.py's.
"""

from __future__ import annotations

import base64
import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.ros2_fixtures import (
    GRID,
    INFO,
    LATCHED,
    DdsPeer,
    bridge_args,
    decode,
    domain_id,
    expected_grid,
    typestore,
)
from tests.ros_fixtures import WsnavChild, slow_heartbeat_school, wait_until
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.ros_bridge.zone_feed import ZoneFeed
from wsnav.ros_bridge.zone_grid import ZoneGridCodec
from wsnav.runtime.bus import Message
from wsnav.runtime.mqtt_bus import connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.messages import ZoneState
from wsnav.schemas.site import Site, load_site
from wsnav.zones.cost_values import LETHAL_OBSTACLE
from wsnav.zones.geometry import GridFrame


@pytest.fixture
def school_broker(tmp_path: Path) -> Iterator[tuple[Site, BrokerThread]]:
    site_dir = slow_heartbeat_school(tmp_path)
    with BrokerThread(site_dir) as broker:
        yield load_site(site_dir), broker


def test_the_zone_grid_reaches_a_late_ros2_subscriber_with_ros2_names_qos_and_the_ros1_bridges_values(
    school_broker: tuple[Site, BrokerThread],
) -> None:
    site, broker = school_broker
    store = typestore()
    domain = domain_id()
    frame = GridFrame.of_grid(site.grid)
    codec = ZoneGridCodec()
    reference = ZoneFeed(site.spec, frame)
    reference.take([], 0.0)
    bridge = WsnavChild(
        bridge_args(site, f"{broker.host}:{broker.port}", broker.credentials_dir / "robot1.json", domain),
        dict(os.environ),
    )
    peers: list[DdsPeer] = []
    try:
        bridge.wait_for("MQTT broker connected", 60)
        peer = DdsPeer(
            domain, GRID, INFO
        )  # started after the bridge wrote both: transient_local must carry them
        peers.append(peer)
        wait_until(lambda: bool(peer.of(GRID)) and bool(peer.of(INFO)), 30, "the grid and the filter info")

        first = peer.of(GRID)[0]
        assert first["writer_topic"] == GRID
        assert first["type_name"] == "nav_msgs::msg::dds_::OccupancyGrid_"
        assert first["qos"] == LATCHED, first["qos"]
        raw = base64.b64decode(first["cdr"])
        assert raw[:2] == b"\x00\x01", "CDR_LE, XCDR1: what ROS 2 Humble writes and reads"

        grid = decode(store, first, "nav_msgs/msg/OccupancyGrid")
        assert grid.header.frame_id == "map"
        assert (grid.info.width, grid.info.height) == (frame.width, frame.height)
        assert grid.info.resolution == np.float32(frame.resolution)
        assert (grid.info.origin.position.x, grid.info.origin.position.y) == (frame.origin_x, frame.origin_y)
        assert grid.info.origin.orientation.w == pytest.approx(np.cos(site.grid.origin[2] / 2))
        assert grid.info.map_load_time.sec > 0 and grid.header.stamp.sec > 0
        assert np.array_equal(grid.data, expected_grid(codec, reference))

        info_sample = peer.of(INFO)[0]
        assert info_sample["writer_topic"] == INFO
        assert info_sample["type_name"] == "nav2_msgs::msg::dds_::CostmapFilterInfo_"
        assert info_sample["qos"] == LATCHED, info_sample["qos"]
        info = decode(store, info_sample, "nav2_msgs/msg/CostmapFilterInfo")
        assert (info.type, info.filter_mask_topic, info.base, info.multiplier) == (
            0,
            "/wsn/zone_grid",
            0.0,
            1.0,
        )
        assert info.header.frame_id == "map"

        # a zone blocked over MQTT by its node: lethal in the next grid, as in the ROS 1 bridge's
        zone = site.spec.zones[2]
        node = next(n for n in site.spec.nodes if n.zone == zone.id)
        assert [n.id for n in site.spec.nodes if n.zone == zone.id] == [node.id], (
            "one node: no fusion to wait for"
        )
        link = connect_with_credentials(broker.host, broker.port, broker.credentials(node.id))
        try:
            topic = topics.zone_state(site.name, zone.id, node.id)
            payload = ZoneState(zone=zone.id, node=node.id, state="blocked", seq=5).to_payload()
            link.publish(topic, payload, qos=1, retain=True)
            assert reference.take([Message(topic, payload, True, 1.0)], 1.0), "the reference saw the change"
            blocked = expected_grid(codec, reference)
            wait_until(lambda: len(peer.of(GRID)) >= 2, 30, "a new grid after the zone was blocked")
            latest = decode(store, peer.of(GRID)[-1], "nav_msgs/msg/OccupancyGrid")
            assert np.array_equal(latest.data, blocked)
            lethal = codec.decode(np.asarray(latest.data, dtype=np.int8)) == LETHAL_OBSTACLE
            was_lethal = codec.decode(np.asarray(grid.data, dtype=np.int8)) == LETHAL_OBSTACLE
            assert lethal.sum() > was_lethal.sum(), "the blocked zone's cells read lethal"

            # a second change, seen written; then a subscriber that comes later gets exactly the last grid
            payload = ZoneState(zone=zone.id, node=node.id, state="caution", seq=6).to_payload()
            link.publish(topic, payload, qos=1, retain=True)
            reference.take([Message(topic, payload, True, 2.0)], 2.0)
            caution = expected_grid(codec, reference)
            wait_until(lambda: len(peer.of(GRID)) >= 3, 30, "a new grid after the zone turned caution")
            assert np.array_equal(
                decode(store, peer.of(GRID)[-1], "nav_msgs/msg/OccupancyGrid").data, caution
            )
            peer.stop()
            late = DdsPeer(domain, GRID)
            peers.append(late)

            def has_caution() -> bool:
                got = late.of(GRID)
                return bool(got) and np.array_equal(
                    decode(store, got[-1], "nav_msgs/msg/OccupancyGrid").data, caution
                )

            wait_until(has_caution, 30, "the caution grid for a late subscriber")
            assert len(late.of(GRID)) == 1, "depth 1: a late subscriber gets the last grid only"
        finally:
            link.close()
        assert bridge.proc.poll() is None, "\n".join(bridge.lines)
        assert not any("Traceback" in line for line in bridge.lines), "\n".join(bridge.lines)
    finally:
        for p in peers:
            if p.proc.poll() is None:
                p.stop()
        bridge.stop()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_with_the_broker_unreachable_the_grid_is_written_from_the_site_and_the_outage_said_once(
    tmp_path: Path,
) -> None:
    site_dir = slow_heartbeat_school(tmp_path)
    site = load_site(site_dir)
    with BrokerThread(site_dir) as broker:  # only for its credentials; the bridge is sent to a dead port
        creds = broker.credentials_dir / "robot1.json"
        domain = domain_id() + 1
        bridge = WsnavChild(bridge_args(site, f"127.0.0.1:{free_port()}", creds, domain), dict(os.environ))
        try:
            bridge.wait_for("zone bridge for site school", 60)
            peer = DdsPeer(domain, GRID)
            try:
                wait_until(lambda: bool(peer.of(GRID)), 30, "the grid with no broker")
            finally:
                peer.stop()
            reference = ZoneFeed(site.spec, GridFrame.of_grid(site.grid))
            reference.take([], 0.0)
            grid = decode(typestore(), peer.of(GRID)[0], "nav_msgs/msg/OccupancyGrid")
            assert np.array_equal(grid.data, expected_grid(ZoneGridCodec(), reference))
            bridge.wait_for("MQTT broker unreachable", 30)
            assert bridge.proc.poll() is None
        finally:
            bridge.stop()
    said = [line for line in bridge.lines if "MQTT broker unreachable" in line]
    assert len(said) == 1, "\n".join(bridge.lines)
    assert not any("Traceback" in line for line in bridge.lines), "\n".join(bridge.lines)


@pytest.mark.parametrize(("distro", "gid_size"), [("humble", 24), ("jazzy", 16)])
def test_the_bridge_is_a_ros2_node_on_ros_discovery_info_in_rmw_dds_commons_bytes(
    tmp_path: Path, distro: str, gid_size: int
) -> None:
    """What `ros2 node list` and `ros2 topic info -v` read: one ParticipantEntitiesInfo on ros_discovery_info
    (no rt/ prefix, reliable, transient_local, depth 1, as rmw writes it), its participant's gid, one node
    (/wsnav_ros2_bridge) whose writers are the two topics' writers; decoded with rosbags' rmw_dds_common of that
    distribution (Humble's Gid is 24 bytes, the GUID and 8 zeros; Jazzy's 16)."""
    from rosbags.typesys import Stores, get_typestore

    site_dir = slow_heartbeat_school(tmp_path)
    site = load_site(site_dir)
    domain = domain_id() + (4 if distro == "humble" else 5)
    with BrokerThread(site_dir) as broker:  # only for its credentials; the bridge is sent to a dead port
        creds = broker.credentials_dir / "robot1.json"
        args = [*bridge_args(site, f"127.0.0.1:{free_port()}", creds, domain), "--ros-distro", distro]
        bridge = WsnavChild(args, dict(os.environ))
        try:
            bridge.wait_for("zone bridge for site school", 60)
            peer = DdsPeer(domain, "ros_discovery_info", GRID, INFO, gid_bytes=gid_size)
            try:
                wait_until(
                    lambda: all(peer.of(t) for t in ("ros_discovery_info", GRID, INFO)),
                    30,
                    "all three topics",
                )
            finally:
                peer.stop()
        finally:
            bridge.stop()
    sample = peer.of("ros_discovery_info")[0]
    assert sample["writer_topic"] == "ros_discovery_info"
    assert sample["type_name"] == "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"
    assert sample["qos"] == LATCHED, sample["qos"]
    store = get_typestore(Stores.ROS2_HUMBLE if distro == "humble" else Stores.ROS2_JAZZY)
    info = decode(store, sample, "rmw_dds_common/msg/ParticipantEntitiesInfo")

    def gid(guid: str) -> bytes:
        return uuid.UUID(guid).bytes.ljust(gid_size, b"\0")

    assert bytes(info.gid.data) == gid(sample["participant_guid"])
    [node] = info.node_entities_info_seq
    assert (node.node_namespace, node.node_name) == ("/", "wsnav_ros2_bridge")
    assert node.reader_gid_seq == []
    writers = {gid(peer.of(t)[0]["writer_guid"]) for t in (GRID, INFO)}
    assert {bytes(g.data) for g in node.writer_gid_seq} == writers
    assert all(peer.of(t)[0]["participant_guid"] == sample["participant_guid"] for t in (GRID, INFO))
    assert f"node /wsnav_ros2_bridge as {distro} sees it" in bridge.wait_for("zone bridge for site", 1)
