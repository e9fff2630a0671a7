"""`wsnav ros bridge ...`: the zone layer into ROS navigation. The node's code (and rospy) loads only when it runs."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.runtime.cli_support import add_broker_arguments, add_state_dir_argument

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    ros = sub.add_parser(
        "ros", help="wsnav on ROS 1: the zone grid for costmap_2d / Nav2, Algorithm 3 on move_base"
    )
    ros_sub = ros.add_subparsers(dest="ros_command", required=True, parser_class=type(ros))
    bridge = ros_sub.add_parser(
        "bridge",
        help="publish the zone layer as an OccupancyGrid (+ updates); with --robot, supervise move_base",
        description="ROS master from ROS_MASTER_URI (default http://localhost:11311). See docs/ros.md.",
    )
    bridge.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    add_broker_arguments(bridge)
    bridge.add_argument(
        "--credentials", type=Path, required=True, metavar="FILE", help="the robot's <id>.json"
    )
    bridge.add_argument("--frame", default="map", help="frame of the zone grid and of goals (default map)")
    bridge.add_argument("--namespace", default="/wsn", help="topic namespace (default /wsn: /wsn/zone_grid)")
    bridge.add_argument(
        "--map-topic", default="/map", help="the robot's map, checked against the site's when published"
    )
    bridge.add_argument(
        "--map-wait", type=float, default=3.0, metavar="S", help="wait this long for it (0: do not check)"
    )
    bridge.add_argument(
        "--update-hold",
        type=float,
        default=1.0,
        metavar="S",
        help="each update also covers cells changed this long before (>= the costmap's update period)",
    )
    bridge.add_argument("--robot", metavar="ID", help="supervise this robot's move_base (Algorithm 3)")
    bridge.add_argument("--move-base", default="/move_base", help="move_base's action namespace")
    bridge.add_argument(
        "--no-costmap-check",
        action="store_true",
        help="with --robot: do not check move_base's global costmap parameters for the zone layer",
    )
    bridge.add_argument(
        "--plan-topic", default="/move_base/NavfnROS/plan", help="the global planner's nav_msgs/Path"
    )
    bridge.add_argument("--base-frame", default="base_footprint", help="the robot's frame for its pose")
    bridge.add_argument(
        "--master-costmap",
        default="/move_base/global_costmap/costmap",
        help="move_base's global costmap (and its _updates): a replan waits until it shows the zone change",
    )
    bridge.add_argument(
        "--relay",
        metavar="ACTION",
        help="with --robot: serve move_base's action interface here (e.g. /wsnav/move_base) and relay to move_base, "
        "so a script's goal survives the bridge's re-sends and ends as the robot's drive ends",
    )
    bridge.add_argument("--connect-timeout", type=float, default=10.0, metavar="S", help="MQTT, default 10")
    add_state_dir_argument(bridge)
    bridge.set_defaults(func=bridge_command)


def bridge_command(args: argparse.Namespace) -> int:
    from wsnav.ros_bridge.bridge_node import bridge_command as run

    return run(args)
