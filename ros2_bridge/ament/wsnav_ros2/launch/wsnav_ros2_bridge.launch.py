"""`ros2 launch wsnav_ros2 wsnav_ros2_bridge.launch.py config:=/etc/wsnav/wsnav_ros2_bridge.yaml wsnav:=/opt/wsnav/bin/wsnav`

Runs `wsnav ros2 bridge` (wsnav's own virtual environment: `wsnav:=` names its command) with the options in the
YAML file's `wsnav_ros2_bridge: ros__parameters:` block: each `key: value` becomes `--key-with-dashes value`
(true: a flag; false: left out). The bridge is not an rclpy node, so the launch system runs it as a process and
starts it again 5 s after it ends. The option rule is the catkin package's (ros_bridge/catkin/.../wsnav_bridge.py):
the two run under different Pythons and cannot share a module.
"""

from __future__ import annotations

import os
from typing import Any

NODE = "wsnav_ros2_bridge"


def options(params: dict[str, Any]) -> list[str]:
    args: list[str] = []
    for key, value in sorted(params.items()):
        if value is False:
            continue
        args.append("--" + key.replace("_", "-"))
        if value is not True:
            args.append(str(value))
    return args


def bridge_command(config: str, wsnav: str) -> list[str]:
    """The command line for the YAML file `config`; one line of error for a file without the block."""
    import yaml

    with open(config) as f:
        doc = yaml.safe_load(f) or {}
    params = (doc.get(NODE) or {}).get("ros__parameters") if isinstance(doc, dict) else None
    if not isinstance(params, dict):
        raise RuntimeError(f"{config}: no '{NODE}: ros__parameters:' mapping of wsnav ros2 bridge's options")
    return [wsnav, "ros2", "bridge", *options(params)]


def generate_launch_description() -> Any:
    from ament_index_python.packages import get_package_share_directory  # pyright: ignore[reportMissingImports]
    from launch import LaunchDescription  # pyright: ignore[reportMissingImports, reportAttributeAccessIssue]
    from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction  # pyright: ignore[reportMissingImports]
    from launch.substitutions import LaunchConfiguration  # pyright: ignore[reportMissingImports]

    default = os.path.join(get_package_share_directory("wsnav_ros2"), "config", "wsnav_ros2_bridge.yaml")

    def start(context: Any) -> list[Any]:
        cmd = bridge_command(
            LaunchConfiguration("config").perform(context), LaunchConfiguration("wsnav").perform(context)
        )
        return [ExecuteProcess(cmd=cmd, name=NODE, output="screen", respawn=True, respawn_delay=5.0)]

    return LaunchDescription(
        [
            DeclareLaunchArgument("config", default_value=default, description="the bridge's options (YAML)"),
            DeclareLaunchArgument("wsnav", default_value="wsnav", description="wsnav's command in its venv"),
            OpaqueFunction(function=start),
        ]
    )
