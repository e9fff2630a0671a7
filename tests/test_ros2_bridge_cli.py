"""`wsnav ros2 bridge` without processes: bad arguments are one line each, and the DDS types are ROS 2 Humble's
messages field for field (compared with rosbags' own Humble definitions, and round-tripped through its CDR)."""

from __future__ import annotations

import argparse
from dataclasses import fields
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pytest

from tests.cli_fixtures import error_line
from tests.conftest import SCHOOL
from tests.ros2_fixtures import typestore
from wsnav.ros2_bridge.bridge import ros2_options
from wsnav.ros2_bridge.discovery import Discovery, cyclone_config, discovery_from_env


def argv(*extra: str, site: Path = SCHOOL) -> list[str]:
    return [
        "ros2",
        "bridge",
        "--site",
        str(site),
        "--broker",
        "127.0.0.1:1",
        "--credentials",
        "robot1.json",
        *extra,
    ]


@pytest.mark.parametrize(
    ("extra", "named"),
    [
        (["--domain", "233"], "--domain 233"),
        (["--domain", "-1"], "--domain -1"),
        (["--namespace", "/wsn/9x"], "--namespace '/wsn/9x'"),
        (["--namespace", "/w sn"], "--namespace '/w sn'"),
        (["--frame", "/map"], "--frame '/map'"),
        (["--frame", ""], "--frame ''"),
        (["--broker", "nohost"], "HOST:PORT"),
    ],
)
def test_bad_ros2_arguments_are_one_line(
    capsys: pytest.CaptureFixture[str], extra: list[str], named: str
) -> None:
    assert named in error_line(capsys, argv(*extra))


def test_a_bad_ros_domain_id_and_a_missing_site_are_one_line(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", "robot")
    assert "ROS_DOMAIN_ID='robot'" in error_line(capsys, argv())
    monkeypatch.setenv("ROS_DOMAIN_ID", "7")
    assert str(tmp_path / "nowhere") in error_line(capsys, argv(site=tmp_path / "nowhere"))


def test_names_are_normalized_as_ros2_reads_them(monkeypatch: pytest.MonkeyPatch) -> None:
    def options(namespace: str, domain: int | None = None) -> tuple[str, int]:
        o = ros2_options(argparse.Namespace(namespace=namespace, frame="map", domain=domain))
        return o.namespace, o.domain

    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert options("/wsn") == ("/wsn", 0)
    assert options("wsn/") == ("/wsn", 0)
    assert options("/") == ("", 0)
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert options("/a/b_c") == ("/a/b_c", 42)
    assert options("/a", domain=3) == ("/a", 3)


@pytest.mark.parametrize(
    ("variable", "value"),
    [
        ("ROS_LOCALHOST_ONLY", "yes"),
        ("ROS_AUTOMATIC_DISCOVERY_RANGE", "localhost"),
        ("ROS_STATIC_PEERS", "a b;c"),
        ("ROS_STATIC_PEERS", 'x"/><Peer address="evil'),
    ],
)
def test_bad_ros2_discovery_variables_are_one_line(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, variable: str, value: str
) -> None:
    for name in ("ROS_LOCALHOST_ONLY", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv(variable, value)
    assert variable in error_line(capsys, argv())


def test_discovery_follows_rcl_and_rmw_cyclonedds() -> None:
    """rcl's reading of the variables and rmw_cyclonedds's fragment for each range (Jazzy's check_create_domain;
    Humble's loopback interface for ROS_LOCALHOST_ONLY), the user's CYCLONEDDS_URI last so that it wins."""
    assert discovery_from_env({}) == Discovery("SUBNET")
    only = discovery_from_env(
        {"ROS_LOCALHOST_ONLY": "1", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "ROS_STATIC_PEERS": "a"}
    )
    assert only == Discovery("LOCALHOST", (), localhost_only=True), "localhost-only overrides range and peers"
    assert discovery_from_env({"ROS_LOCALHOST_ONLY": "0", "ROS_STATIC_PEERS": "a; 10.0.0.2;"}) == Discovery(
        "SUBNET", ("a", "10.0.0.2")
    )
    assert discovery_from_env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF", "ROS_STATIC_PEERS": "a"}) == Discovery(
        "OFF"
    )

    def parsed(config: str) -> ElementTree.Element:
        ours, _, user = config.partition(",")
        assert user == "file:///etc/robot.xml"
        return ElementTree.fromstring(ours)

    uri = "file:///etc/robot.xml"
    loopback = parsed(cyclone_config(only, uri, 7))
    assert [i.get("address") for i in loopback.iter("NetworkInterface")] == ["127.0.0.1"]
    assert [p.get("address") for p in loopback.iter("Peer")] == ["localhost"]
    local = parsed(cyclone_config(Discovery("LOCALHOST", ("10.0.0.2",)), uri, 7))
    assert local.findtext("Domain/General/AllowMulticast") == "false"
    assert local.findtext("Domain/Discovery/ParticipantIndex") == "auto"
    assert local.findtext("Domain/Discovery/MaxAutoParticipantIndex") == "32"
    assert [p.get("address") for p in local.iter("Peer")] == ["localhost", "10.0.0.2"]
    off = parsed(cyclone_config(Discovery("OFF"), uri, 7))
    assert (off.findtext("Domain/Discovery/ParticipantIndex"), off.findtext("Domain/Discovery/Tag")) == (
        "none",
        "ros_discovery_off_7",
    )
    subnet = parsed(cyclone_config(Discovery("SUBNET"), uri, 7))
    assert subnet.findtext("Domain/General/AllowMulticast") is None and not list(subnet.iter("Peer"))
    system = parsed(cyclone_config(Discovery("SYSTEM_DEFAULT", ("a",)), uri, 7))
    assert system.find("Domain/Discovery") is None and system.find("Domain/General") is None
    for tree in (loopback, local, off, subnet, system):
        assert tree.findtext("Domain/Compatibility/IgnoreTypeInformation") == "1.16"
    assert "," not in cyclone_config(Discovery("SUBNET"), "", 7), "no user file: ours alone"


CDR_TYPES = {
    "Time": "builtin_interfaces/msg/Time",
    "Header": "std_msgs/msg/Header",
    "Point": "geometry_msgs/msg/Point",
    "Quaternion": "geometry_msgs/msg/Quaternion",
    "Pose": "geometry_msgs/msg/Pose",
    "MapMetaData": "nav_msgs/msg/MapMetaData",
    "OccupancyGrid": "nav_msgs/msg/OccupancyGrid",
    "CostmapFilterInfo": "nav2_msgs/msg/CostmapFilterInfo",
}


def test_the_dds_types_have_ros2_humbles_fields_in_order_and_round_trip_through_rosbags() -> None:
    from wsnav.ros2_bridge import messages

    store = typestore()
    for name, msgtype in CDR_TYPES.items():
        cls = getattr(messages, name)
        pkg, _, leaf = msgtype.split("/")
        assert cls.__idl_typename__ == f"{pkg}::msg::dds_::{leaf}_"
        ours = [f.name for f in fields(cls)]
        theirs = [field_name for field_name, _ in store.fielddefs[msgtype][1]]
        assert ours == theirs, msgtype
    grid = messages.OccupancyGrid(
        header=messages.Header(stamp=messages.Time(sec=7, nanosec=9), frame_id="map"),
        info=messages.MapMetaData(
            resolution=0.05,
            width=3,
            height=1,
            origin=messages.Pose(
                position=messages.Point(x=-1.5, y=2.25), orientation=messages.Quaternion(z=0.5)
            ),
        ),
        data=[-1, 0, 100],
    )
    back = store.deserialize_cdr(grid.serialize(), "nav_msgs/msg/OccupancyGrid")
    assert (back.header.stamp.sec, back.header.stamp.nanosec, back.header.frame_id) == (7, 9, "map")
    assert back.info.resolution == np.float32(0.05) and (back.info.width, back.info.height) == (3, 1)
    assert (back.info.origin.position.x, back.info.origin.position.y, back.info.origin.orientation.z) == (
        -1.5,
        2.25,
        0.5,
    )
    assert back.data.tolist() == [-1, 0, 100]
    info = messages.CostmapFilterInfo(filter_mask_topic="/wsn/zone_grid")
    back_info = store.deserialize_cdr(info.serialize(), "nav2_msgs/msg/CostmapFilterInfo")
    assert (back_info.type, back_info.filter_mask_topic, back_info.base, back_info.multiplier) == (
        0,
        "/wsn/zone_grid",
        0.0,
        1.0,
    )


def test_the_ros_discovery_info_layout_follows_ros_distro_or_the_option(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def distro(option: str | None = None) -> str:
        args = argparse.Namespace(namespace="/wsn", frame="map", domain=0, ros_distro=option)
        return ros2_options(args).distro

    monkeypatch.delenv("ROS_DISTRO", raising=False)
    assert distro() == "humble"
    for name, layout in (("humble", "humble"), ("iron", "jazzy"), ("jazzy", "jazzy"), ("rolling", "jazzy")):
        monkeypatch.setenv("ROS_DISTRO", name)
        assert distro() == layout
    assert distro("humble") == "humble", "the option wins"
    monkeypatch.setenv("ROS_DISTRO", "foxy")
    assert "ROS_DISTRO='foxy'" in error_line(capsys, argv())
    monkeypatch.delenv("ROS_DISTRO")
    assert "--ros-distro" in error_line(capsys, argv("--ros-distro", "foxy"))


@pytest.mark.parametrize(
    ("extra", "named"),
    [
        (["--robot", "robot2"], "--robot robot2: the credentials are robot 'robot1'"),
        (["--robot", "robot1", "--pose-topic", "amcl_pose"], "--pose-topic 'amcl_pose'"),
        (["--robot", "robot1", "--nav2-action", "/nav 2"], "--nav2-action '/nav 2'"),
        (["--robot", "robot1", "--plan-topic", "/plan/"], "--plan-topic '/plan/'"),
    ],
)
def test_bad_nav2_arguments_are_one_line(extra: list[str], named: str) -> None:
    """Checked before DDS starts: a typo in a Nav2 name would otherwise wait for a server that never comes."""
    from wsnav.cli import build_parser
    from wsnav.ros2_bridge.bridge import check_robot_arguments
    from wsnav.runtime.cli_support import CliError

    args = build_parser().parse_args(argv(*extra))
    with pytest.raises(CliError) as refused:
        check_robot_arguments(args, "robot1")
    assert named in str(refused.value) and "\n" not in str(refused.value)
