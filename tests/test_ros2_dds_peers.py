"""`wsnav ros2 bridge` beside the DDS stacks ROS 2 ships, each peer its own native process (tests/dds_peers/):

- Cyclone DDS 0.10.2 (Debian's libddsc, what Humble's and Jazzy's rmw_cyclonedds run on): a reader WITH XTypes
  type information (idlc's default), a reader WITHOUT it (idlc -t), and a bare participant with no endpoints.
  Before the fix every one of them died with SIGSEGV when the bridge's type objects reached them (Cyclone 11
  writes int8/uint8 as TK_INT8/TK_UINT8, which 0.10 cannot validate: eclipse-cyclonedds/cyclonedds#1554).
- Fast DDS 2.9.1 (Debian's libfastrtps, Humble's default rmw): a reader built as rmw_fastrtps_cpp builds one (its
  own TopicDataType with no type object or type information, PREALLOCATED_WITH_REALLOC history, reliable,
  transient_local).

Each reader must get the grid the ROS 1 bridge would serve, then the new grid after a zone changes over MQTT; a
reader started after both gets exactly the latest grid; no peer may die. The readers report each grid's size,
frame and an FNV-1a hash of its cells. Not here: no rclcpp/rclpy, no ros2 CLI and no Nav2 (none is installed).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from tests.ros2_fixtures import NativePeer, bridge_args, clean_env, domain_id, expected_grid
from tests.ros_fixtures import WsnavChild, slow_heartbeat_school, wait_until
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.ros_bridge.zone_feed import ZoneFeed
from wsnav.ros_bridge.zone_grid import ZoneGridCodec
from wsnav.runtime.bus import Message
from wsnav.runtime.mqtt_bus import connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.messages import ZoneState
from wsnav.schemas.site import Site, load_site
from wsnav.zones.geometry import GridFrame

pytestmark = pytest.mark.slow

GRID = "rt/wsn/zone_grid"


def fnv1a(data: NDArray[np.int8]) -> int:
    """The peers' hash of a grid's cells (FNV-1a, 32 bit, over the int8 cells as bytes)."""
    h = 2166136261
    for b in data.astype(np.uint8).tobytes():
        h = ((h ^ b) * 16777619) & 0xFFFFFFFF
    return h


def start_peers(
    binaries: Path, domain: int, env: dict[str, str], into: list[NativePeer], bare: bool = True
) -> list[NativePeer]:
    """The Cyclone 0.10 readers (with and without type information), a bare Cyclone 0.10 participant (unless not
    `bare`) and the Fast DDS reader, each added to `into` as it starts (so the test stops every one it started);
    readers keep 10 grids, so extra ones would show. Returns the ones started here."""
    d = str(domain)
    specs = [
        ("Cyclone 0.10 reader with type information",
         [str(binaries / "cyclone_peer_typeinfo"), "reader", d, GRID, "10"]),
        ("Cyclone 0.10 reader without type information",
         [str(binaries / "cyclone_peer_no_typeinfo"), "reader", d, GRID, "10"]),
        ("Cyclone 0.10 bare participant", [str(binaries / "cyclone_peer_typeinfo"), "bare", d]),
        ("Fast DDS 2.9 reader as rmw_fastrtps", [str(binaries / "fastdds_peer"), d, GRID, "10"]),
    ]  # fmt: skip
    started: list[NativePeer] = []
    for name, argv in specs:
        if bare or "bare" not in name:
            started.append(NativePeer(name, argv, env))
            into.append(started[-1])
    return started


def readers(peers: list[NativePeer]) -> list[NativePeer]:
    return [p for p in peers if "bare" not in p.name]


def assert_alive(peers: list[NativePeer]) -> None:
    dead = [f"{p.name}: exit {p.proc.returncode} {p.stderr()}" for p in peers if p.proc.poll() is not None]
    assert not dead, "peers died beside the bridge:\n" + "\n".join(dead)


@pytest.fixture
def school_broker(tmp_path: Path) -> Iterator[tuple[Site, BrokerThread]]:
    site_dir = slow_heartbeat_school(tmp_path)
    with BrokerThread(site_dir) as broker:
        yield load_site(site_dir), broker


def test_cyclone_0_10_and_fast_dds_2_9_peers_live_beside_the_bridge_and_get_every_grid(
    school_broker: tuple[Site, BrokerThread], peer_binaries: Path
) -> None:
    site, broker = school_broker
    domain = domain_id() + 2
    frame = GridFrame.of_grid(site.grid)
    codec = ZoneGridCodec()
    reference = ZoneFeed(site.spec, frame)
    reference.take([], 0.0)
    first = fnv1a(expected_grid(codec, reference))
    peers: list[NativePeer] = []
    bridge: WsnavChild | None = None
    try:
        start_peers(peer_binaries, domain, clean_env(), peers)  # early joiners: there before the bridge
        bridge = WsnavChild(
            bridge_args(site, f"{broker.host}:{broker.port}", broker.credentials_dir / "robot1.json", domain),
            clean_env(),
        )
        bridge.wait_for("MQTT broker connected", 60)

        def all_got(h: int, among: list[NativePeer]) -> bool:
            assert_alive(peers)
            return all(p.samples and p.samples[-1]["fnv1a"] == h for p in among)

        wait_until(lambda: all_got(first, readers(peers)), 30, "the first grid at every reader")
        for p in readers(peers):
            g = p.samples[-1]
            assert (g["width"], g["height"], g["length"], g["frame_id"]) == (
                frame.width, frame.height, frame.width * frame.height, "map"
            ), p.name  # fmt: skip

        zone = site.spec.zones[2]
        node = next(n for n in site.spec.nodes if n.zone == zone.id)
        link = connect_with_credentials(broker.host, broker.port, broker.credentials(node.id))
        try:
            topic = topics.zone_state(site.name, zone.id, node.id)
            payload = ZoneState(zone=zone.id, node=node.id, state="blocked", seq=5).to_payload()
            link.publish(topic, payload, qos=1, retain=True)
            reference.take([Message(topic, payload, True, 1.0)], 1.0)
            blocked = fnv1a(expected_grid(codec, reference))
            assert blocked != first
            wait_until(
                lambda: all_got(blocked, readers(peers)), 30, "the blocked zone's grid at every reader"
            )
        finally:
            link.close()

        late = start_peers(peer_binaries, domain, clean_env(), peers, bare=False)
        wait_until(lambda: all_got(blocked, late), 30, "the latest grid at every late reader")
        for p in late:
            assert [g["fnv1a"] for g in p.samples] == [blocked], f"{p.name}: the latest grid only"
        assert_alive(peers)
        assert bridge.proc.poll() is None, "\n".join(bridge.lines)
    finally:
        codes = [(p.name, p.stop()) for p in peers]
        if bridge is not None:
            bridge.stop()
    assert all(code == 0 for _, code in codes), f"exit codes after SIGTERM (-11 is SIGSEGV): {codes}"


@pytest.mark.parametrize(
    ("name", "ours"),
    [
        ("nav_msgs_msg_dds__OccupancyGrid_", "OccupancyGrid"),
        ("nav2_msgs_msg_dds__CostmapFilterInfo_", "CostmapFilterInfo"),
        ("rmw_dds_common_msg_dds__ParticipantEntitiesInfo_", "ParticipantEntitiesInfo24"),
    ],
)
def test_the_bridge_announces_its_types_as_cyclone_0_10_s_idlc_does(
    peer_binaries: Path, name: str, ours: str
) -> None:
    """Same type identifiers as Debian's idlc (0.10.2) gives Humble's messages (int8, uint8, uint8 arrays, bounded
    strings): a 0.10 reader with type information matches the bridge without looking anything up, and nothing
    the bridge announces is a type kind 0.10 cannot read (TK_INT8/TK_UINT8)."""
    import re

    import cyclonedds.idl._typesupport.DDS.XTypes as xt  # pyright: ignore[reportMissingTypeStubs]
    from cyclonedds.idl._support import Endianness

    from wsnav.ros2_bridge import messages

    source = (peer_binaries / "typeinfo" / "ros2_grid.c").read_text()
    block = re.search(rf"#define TYPE_INFO_CDR_{name} \(unsigned char \[\]\)\{{(.*?)\}}", source, re.S)
    assert block is not None
    info = getattr(messages, ours).__idl__.get_type_info()
    header = info.serialize(endianness=Endianness.Little, use_version_2=True)[:4]
    theirs = xt.TypeInformation.deserialize(
        header + bytes(int(x, 16) for x in re.findall(r"0x([0-9a-f]{2})", block.group(1)))
    )
    assert info.minimal.typeid_with_size == theirs.minimal.typeid_with_size
    assert info.complete.typeid_with_size == theirs.complete.typeid_with_size
    deps: list[Any] = [info.complete.dependent_typeids, theirs.complete.dependent_typeids]
    assert sorted(map(repr, deps[0])) == sorted(map(repr, deps[1]))


HUMBLE_LOCALHOST_ONLY = (
    '<CycloneDDS><Domain><General><Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces></General>'
    "</Domain></CycloneDDS>"
)
"""What Humble's rmw_cyclonedds puts before CYCLONEDDS_URI under ROS_LOCALHOST_ONLY=1 (rmw_node.cpp)."""
JAZZY_LOCALHOST = (
    "<CycloneDDS><Domain><General><AllowMulticast>false</AllowMulticast></General><Discovery>"
    "<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>32</MaxAutoParticipantIndex>"
    '<Peers><Peer address="localhost"/></Peers></Discovery></Domain></CycloneDDS>'
)
"""What Jazzy's rmw_cyclonedds puts there for ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (and ROS_LOCALHOST_ONLY=1)."""


@pytest.mark.parametrize(
    ("bridge_env", "robot"),
    [
        ({"ROS_LOCALHOST_ONLY": "1"}, "humble"),
        ({"ROS_LOCALHOST_ONLY": "1"}, "humble, Fast DDS"),
        ({"ROS_LOCALHOST_ONLY": "1"}, "jazzy"),
        ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, "jazzy"),
    ],
)
def test_a_localhost_only_robot_gets_the_grid_from_the_bridge_with_no_cyclonedds_uri_of_its_own(
    tmp_path: Path, peer_binaries: Path, bridge_env: dict[str, str], robot: str
) -> None:
    """The robot's DDS is a Cyclone 0.10 reader configured as its rmw_cyclonedds configures it, or a Fast DDS 2.9
    reader with the transports Humble's rmw_fastrtps sets for ROS_LOCALHOST_ONLY=1; the bridge gets only ROS 2's
    variables (ROS_DOMAIN_ID too: no --domain). With Cyclone's default configuration (before) no robot found
    the bridge. Not checked: that a host elsewhere cannot (one machine here; "localhost" means any process on it)."""
    site_dir = slow_heartbeat_school(tmp_path)
    site = load_site(site_dir)
    domain = domain_id() + 3
    reference = ZoneFeed(site.spec, GridFrame.of_grid(site.grid))
    reference.take([], 0.0)
    first = fnv1a(expected_grid(ZoneGridCodec(), reference))
    if robot == "humble, Fast DDS":  # Humble's default rmw reads ROS_LOCALHOST_ONLY itself (fastdds_peer.cpp)
        robot_env = {**clean_env(), "ROS_LOCALHOST_ONLY": "1"}
        reader = [str(peer_binaries / "fastdds_peer"), str(domain), GRID, "10"]
    else:
        uri = HUMBLE_LOCALHOST_ONLY if robot == "humble" else JAZZY_LOCALHOST
        robot_env = {**clean_env(), "CYCLONEDDS_URI": uri}
        reader = [str(peer_binaries / "cyclone_peer_typeinfo"), "reader", str(domain), GRID, "10"]
    with BrokerThread(site_dir) as broker:  # for the credentials; the bridge is sent to a dead port
        args = bridge_args(site, "127.0.0.1:9", broker.credentials_dir / "robot1.json", domain)
        args = args[: args.index("--domain")] + args[args.index("--domain") + 2 :]
        peers = [NativePeer(f"{robot} robot, localhost only", reader, robot_env)]
        bridge = WsnavChild(args, {**clean_env(), **bridge_env, "ROS_DOMAIN_ID": str(domain)})
        try:
            line = bridge.wait_for("zone bridge for site school", 60)
            assert f"domain {domain}" in line, line
            assert ("this host only" if "ROS_LOCALHOST_ONLY" in bridge_env else "range LOCALHOST") in line, (
                line
            )
            wait_until(lambda: bool(peers[0].samples), 30, f"the grid at the {robot} robot")
            assert peers[0].samples[-1]["fnv1a"] == first
            assert_alive(peers)
        finally:
            codes = {p.name: p.stop() for p in peers}
            bridge.stop()
    assert set(codes.values()) == {0}, codes
