"""`wsnav ros2 bridge ...`: the zone layer for ROS 2 / Nav2, published straight on DDS (no rclpy). The bridge's
code, and cyclonedds, load only when it runs."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.runtime.cli_support import add_broker_arguments, add_state_dir_argument

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    ros2 = sub.add_parser("ros2", help="wsnav on ROS 2: the zone grid for Nav2, straight on DDS (no rclpy)")
    ros2_sub = ros2.add_subparsers(dest="ros2_command", required=True, parser_class=type(ros2))
    bridge = ros2_sub.add_parser(
        "bridge",
        help="publish the zone layer as a nav_msgs/msg/OccupancyGrid and a nav2_msgs/msg/CostmapFilterInfo",
        description="ROS 2 topics on DDS through Cyclone DDS (rt/<topic>, reliable, transient_local, depth 1). "
        "See docs/ros.md.",
    )
    bridge.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    add_broker_arguments(bridge)
    bridge.add_argument(
        "--credentials", type=Path, required=True, metavar="FILE", help="the robot's <id>.json"
    )
    bridge.add_argument(
        "--namespace",
        default="/wsn",
        help="topic namespace (default /wsn: /wsn/zone_grid, /wsn/costmap_filter_info)",
    )
    bridge.add_argument("--frame", default="map", help="frame_id of the zone grid (default map)")
    bridge.add_argument(
        "--domain",
        type=int,
        metavar="N",
        help="ROS 2 domain id (default: $ROS_DOMAIN_ID, else 0)",
    )
    bridge.add_argument(
        "--ros-distro",
        choices=["humble", "jazzy"],
        help="whose rmw_dds_common layout ros_discovery_info is written in (jazzy: Iron and later; "
        "default: $ROS_DISTRO, else humble)",
    )
    bridge.add_argument(
        "--robot",
        metavar="ID",
        help="supervise this robot's Nav2 (navigate_to_pose on rmw_cyclonedds or rmw_fastrtps): cancel goals in "
        "blocked zones, drive out of a zone blocked around it, MQTT goals and status (the credentials must be its own)",
    )
    bridge.add_argument(
        "--nav2-action", default="/navigate_to_pose", help="Nav2's NavigateToPose action (with --robot)"
    )
    bridge.add_argument(
        "--pose-topic",
        default="/amcl_pose",
        help="the robot's PoseWithCovarianceStamped in the map frame (with --robot; default /amcl_pose)",
    )
    bridge.add_argument(
        "--plan-topic", default="/plan", help="Nav2's global plan (with --robot; default /plan)"
    )
    bridge.add_argument(
        "--nav2-resend",
        action="store_true",
        help="re-send the goal when a zone on the plan changes (for a behaviour tree that does not replan by "
        "itself; Nav2's default trees replan at 1 Hz, and a re-send aborts the sender's goal)",
    )
    bridge.add_argument("--connect-timeout", type=float, default=10.0, metavar="S", help="MQTT, default 10")
    add_state_dir_argument(bridge)
    bridge.set_defaults(func=bridge_command)


def bridge_command(args: argparse.Namespace) -> int:
    from wsnav.ros2_bridge.bridge import bridge_command as run

    return run(args)
