"""ros2_bridge/ament/wsnav_ros2, the ROS 2 package, without ROS 2 (none is installed here, so no colcon build and
no `ros2 launch` ran it): its launch file's command line is one `wsnav ros2 bridge` accepts with the shipped
options, a YAML without the block is one line, and the Nav2 costmap YAML reads the bridge's grid as docs/ros.md
says (a second StaticLayer on /wsn/zone_grid, the merge parameters costmap-wide)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType
from xml.etree import ElementTree

import pytest
import yaml

from tests.conftest import REPO
from wsnav.cli import build_parser

PACKAGE = REPO / "ros2_bridge" / "ament" / "wsnav_ros2"


def launch_file() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "wsnav_ros2_launch", PACKAGE / "launch" / "wsnav_ros2_bridge.launch.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_launch_file_runs_the_bridge_with_the_shipped_options() -> None:
    argv = launch_file().bridge_command(
        str(PACKAGE / "config" / "wsnav_ros2_bridge.yaml"), "/opt/wsnav/bin/wsnav"
    )
    assert argv[:3] == ["/opt/wsnav/bin/wsnav", "ros2", "bridge"]
    args = build_parser().parse_args(argv[1:])
    assert (args.site, args.broker, args.namespace, args.frame, args.ros_distro) == (
        Path("/etc/wsnav/site"), ("192.168.1.10", 1883), "/wsn", "map", "humble"
    )  # fmt: skip
    assert args.credentials == Path("/etc/wsnav/creds/robot1.json")


def test_flags_and_a_yaml_without_the_block(tmp_path: Path) -> None:
    module = launch_file()
    assert module.options({"tls_ca": "/ca.pem", "verbose": True, "quiet": False}) == [
        "--tls-ca", "/ca.pem", "--verbose"
    ]  # fmt: skip
    bad = tmp_path / "bad.yaml"
    bad.write_text("site: /etc/wsnav/site\n")
    with pytest.raises(RuntimeError, match="no 'wsnav_ros2_bridge: ros__parameters:'"):
        module.bridge_command(str(bad), "wsnav")


def test_the_package_installs_its_launch_and_config_and_names_its_dependencies() -> None:
    package = ElementTree.parse(PACKAGE / "package.xml").getroot()
    assert package.findtext("name") == "wsnav_ros2"
    assert {e.text for e in package.findall("exec_depend")} >= {
        "launch",
        "ament_index_python",
        "python3-yaml",
    }
    cmake = (PACKAGE / "CMakeLists.txt").read_text()
    assert "project(wsnav_ros2" in cmake and "install(DIRECTORY launch config" in cmake


def test_the_nav2_costmap_reads_the_zone_grid_as_a_second_static_layer() -> None:
    params = yaml.safe_load((PACKAGE / "config" / "nav2_global_costmap.yaml").read_text())
    costmap = params["global_costmap"]["global_costmap"]["ros__parameters"]
    plugins = costmap["plugins"]
    assert plugins.index("static_layer") < plugins.index("wsn_zone_layer") < plugins.index("inflation_layer")
    zone = costmap["wsn_zone_layer"]
    assert zone["plugin"] == "nav2_costmap_2d::StaticLayer"
    assert zone["map_topic"] == "/wsn/zone_grid" and zone["map_subscribe_transient_local"] is True
    assert zone["subscribe_to_updates"] is False
    for name in ("use_maximum", "trinary_costmap", "track_unknown_space", "lethal_cost_threshold"):
        assert name not in zone, f"{name} is costmap-wide in Nav2: under the layer it is ignored"
    assert (costmap["use_maximum"], costmap["trinary_costmap"], costmap["track_unknown_space"]) == (
        True,
        False,
        True,
    )
    assert costmap["lethal_cost_threshold"] == 100
