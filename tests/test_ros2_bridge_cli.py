"""`wsnav ros2 bridge` without processes: bad arguments are one line each, and the DDS types are ROS 2 Humble's
messages field for field (compared with rosbags' own Humble definitions, and round-tripped through its CDR)."""

from __future__ import annotations

import argparse
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from tests.cli_fixtures import error_line
from tests.conftest import SCHOOL
from tests.test_ros2_bridge import typestore
from wsnav.ros2_bridge.bridge import ros2_options


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
