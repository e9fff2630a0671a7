"""move_base's global costmap parameters, as costmap_2d (noetic) reads them: the shipped TurtleBot3 set passes,
each silent trap is refused in one line, and the bridge reads them from a real ROS parameter server (loaded with
`rosparam load`, as turtlebot3_navigation's move_base.launch loads its files).

What the model leaves out: it reads parameters only; that the shipped set gives a master costmap with walls,
zones and a working obstacle layer was checked by hand against the real move_base built from its noetic sources
(docs/ros.md), not here (move_base is not packaged for Debian).
"""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.ros_fixtures import RosMaster, WsnavChild, bridge_args
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.ros_bridge.costmap_params import check_global_costmap
from wsnav.ros_bridge.ros_env import stop_process_group
from wsnav.schemas.site import load_site

PACKAGE = Path(__file__).resolve().parent.parent / "ros_bridge" / "catkin" / "wsnav_ros"
CONFIG = PACKAGE / "config"
ZONES = "/wsn/zone_grid"
ROBOTIS_COMMON = {
    "obstacle_range": 3.0,
    "raytrace_range": 3.5,
    "footprint": [[-0.105, -0.105], [-0.105, 0.105], [0.041, 0.105], [0.041, -0.105]],
    "inflation_radius": 1.0,
    "cost_scaling_factor": 3.0,
    "map_type": "costmap",
    "observation_sources": "scan",
    "scan": {"sensor_frame": "base_scan", "data_type": "LaserScan", "topic": "scan", "marking": True},
}
"""turtlebot3_navigation's costmap_common_params_burger.yaml: pre-Hydro, everything at the costmap's root."""


def shipped_global() -> dict[str, Any]:
    """The global costmap's parameters as move_base.launch loads them: the common file, then the global one."""
    common = yaml.safe_load((CONFIG / "costmap_common_params_burger.yaml").read_text())
    own = yaml.safe_load((CONFIG / "global_costmap_params.yaml").read_text())["global_costmap"]
    return {**common, **own}


def test_the_shipped_turtlebot3_set_passes() -> None:
    check = check_global_costmap(shipped_global(), ZONES)
    assert check.errors == [] and check.warnings == []
    assert check.zone_layer == "wsn_zone_layer"


def trap(change: str) -> dict[str, Any]:
    params = copy.deepcopy(shipped_global())
    zone = params["wsn_zone_layer"]
    match change:
        case "robotis_common":  # docs/ros.md's plugins over ROBOTIS' own common file
            params = {
                **copy.deepcopy(ROBOTIS_COMMON),
                **{k: v for k, v in params.items() if k.endswith("layer")},
            }
            params["plugins"] = shipped_global()["plugins"]
            del params["obstacle_layer"]
        case "no_plugins":
            del params["plugins"]
        case "root_map_topic":
            params["map_topic"] = "/map"
        case "no_use_maximum":
            del zone["use_maximum"]
        case "trinary":
            del zone["trinary_costmap"]
        case "threshold":
            zone["lethal_cost_threshold"] = 90
        case "no_updates":
            zone["subscribe_to_updates"] = False
        case "map_after_zones":
            params["plugins"] = [params["plugins"][1], params["plugins"][0], *params["plugins"][2:]]
        case "first_map_only":
            zone["first_map_only"] = True
        case "other_topic":
            zone["map_topic"] = "/zones"
    return params


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ("robotis_common", "obstacle_layer reads no sensor"),
        ("no_plugins", "no `plugins` list"),
        ("root_map_topic", "copies it into every StaticLayer"),
        ("no_use_maximum", "use_maximum must be true"),
        ("trinary", "trinary_costmap must be false"),
        ("threshold", "lethal_cost_threshold must be 100"),
        ("no_updates", "subscribe_to_updates must be true"),
        ("map_after_zones", "overwrites the zones"),
        ("first_map_only", "first_map_only must be false"),
        ("other_topic", f"no StaticLayer of the global costmap reads {ZONES}"),
    ],
)
def test_each_silent_trap_is_named(change: str, words: str) -> None:
    check = check_global_costmap(trap(change), ZONES)
    assert any(words in e for e in check.errors), check.errors


def test_a_zone_layer_after_inflation_is_only_a_warning() -> None:
    params = shipped_global()
    params["plugins"] = [p for p in params["plugins"] if p["name"] != "wsn_zone_layer"] + [
        {"name": "wsn_zone_layer", "type": "costmap_2d::StaticLayer"}
    ]
    check = check_global_costmap(params, ZONES)
    assert check.errors == [] and any("not inflated" in w for w in check.warnings)


def rosparam(roscore: RosMaster, *args: str) -> None:
    subprocess.run(["rosparam", *args], env=roscore.env(), check=True, capture_output=True, timeout=30)


def test_the_bridge_reads_move_bases_parameters_and_refuses_a_wrong_set_in_one_line(
    roscore: RosMaster, tmp_path: Path
) -> None:
    rosparam(roscore, "load", str(CONFIG / "costmap_common_params_burger.yaml"), "/move_base/global_costmap")
    rosparam(roscore, "load", str(CONFIG / "global_costmap_params.yaml"), "/move_base")
    site_dir = Path(__file__).resolve().parent.parent / "sites" / "school"
    try:
        with BrokerThread(site_dir) as broker:
            args = [
                "ros",
                "bridge",
                *bridge_args(site_dir, broker, "--robot", "robot1", "--log-level", "info"),
            ]
            good = WsnavChild(args, roscore.env())
            try:
                good.wait_for("the zone layer is wsn_zone_layer", 60)
            finally:
                good.stop()
            rosparam(roscore, "set", "/move_base/global_costmap/wsn_zone_layer/use_maximum", "false")
            bad = WsnavChild(args, roscore.env())
            assert bad.finish(60) == 2
            errors = [line for line in bad.lines if "error" in line]
            assert len(errors) == 1 and "use_maximum must be true" in errors[0], bad.lines
            assert not any("Traceback" in line for line in bad.lines)
    finally:
        rosparam(roscore, "delete", "/move_base")


def test_roslaunch_starts_the_bridge_with_its_parameters_from_a_yaml(
    roscore: RosMaster, tmp_path: Path
) -> None:
    """The catkin package as a ROS user runs it: `roslaunch wsnav_ros wsnav_bridge.launch config:=...` (the real
    roslaunch, the package found on ROS_PACKAGE_PATH); the zone grid comes out with the site's size."""
    site_dir = Path(__file__).resolve().parent.parent / "sites" / "school"
    with BrokerThread(site_dir) as broker:
        config = tmp_path / "bridge.yaml"
        params = {
            "site": str(site_dir),
            "broker": f"{broker.host}:{broker.port}",
            "credentials": str(broker.credentials_dir / "robot1.json"),
            "map_wait": 0,
            "namespace": "/wsn_launch",
        }
        config.write_text(yaml.safe_dump(params))
        wsnav = Path(sys.executable).parent / "wsnav"
        env = roscore.env(ROS_PACKAGE_PATH=str(PACKAGE.parent))
        launch = subprocess.Popen(
            ["roslaunch", "wsnav_ros", "wsnav_bridge.launch", f"config:={config}", f"wsnav:={wsnav}"],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        )  # fmt: skip
        try:
            width = subprocess.run(
                ["rostopic", "echo", "-n", "1", "/wsn_launch/zone_grid/info/width"],
                env=env, capture_output=True, text=True, timeout=90,
            )  # fmt: skip
            assert width.stdout.split()[0] == str(load_site(site_dir).grid.width), width
        finally:
            stop_process_group(launch)
