"""`wsnav robot --ros` and `wsnav sim --ros`: wsnav's navigator on a ROS robot, and the simulated TurtleBot3 as a
ROS node. Registered apart from `wsnav ros ...` (ros_bridge.cli); rospy and the nodes load only when they run."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.robot_agent.cli import robot_parser
from wsnav.runtime.cli_support import host_port

if TYPE_CHECKING:
    from wsnav.navigation.backend import Pose
    from wsnav.robot_agent.robot_session import RobotSession
    from wsnav.runtime.cli_support import Parser
    from wsnav.schemas.site import Site

MASTER = "ROS master from ROS_MASTER_URI (default http://localhost:11311). See docs/ros.md."


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    _add_ros_backend(robot_parser(sub))
    sim = sub.add_parser(
        "sim",
        help="the simulated TurtleBot3 as a ROS node (--ros): /scan, /odom, tf in, /cmd_vel out",
        description="A Gazebo-free TurtleBot3 on the site's map, for any ROS software to drive. " + MASTER,
    )
    sim.add_argument("--ros", action="store_true", help="run it as a ROS 1 node (the only way so far)")
    sim.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    sim.add_argument("--start", required=True, metavar="POINT", help="named point, x,y or x,y,yaw")
    sim.add_argument(
        "--broker",
        type=host_port,
        metavar="HOST:PORT",
        help="take the obstacles from sim/world (else: the map alone)",
    )
    sim.add_argument("--credentials", type=Path, metavar="FILE", help="the robot's <id>.json, with --broker")
    sim.add_argument(
        "--rate", type=float, default=30.0, metavar="HZ", help="odometry and tf rate (default 30)"
    )
    sim.add_argument(
        "--cmd-timeout", type=float, default=0.5, metavar="S", help="stop when /cmd_vel is silent this long"
    )
    sim.add_argument(
        "--clock",
        action="store_true",
        help="publish simulated time on /clock and stamp with it (for nodes with /use_sim_time true)",
    )
    sim.add_argument("--connect-timeout", type=float, default=10.0, metavar="S", help="MQTT, default 10")
    sim.set_defaults(func=sim_command)


def _add_ros_backend(robot: Parser) -> None:
    robot.add_argument(
        "--ros",
        dest="backend",
        action="store_const",
        const=ros_session,
        help="drive a robot on ROS 1 (/scan, /odom, tf in; /cmd_vel out); --start: where odometry began on the map",
    )
    ros = robot.add_argument_group("with --ros", MASTER)
    ros.add_argument("--scan-topic", default="/scan", metavar="TOPIC")
    ros.add_argument("--odom-topic", default="/odom", metavar="TOPIC")
    ros.add_argument("--cmd-vel-topic", default="/cmd_vel", metavar="TOPIC")
    ros.add_argument("--map-frame", default="map", metavar="FRAME", help="default map (none on tf: odometry)")
    ros.add_argument("--base-frame", default="base_footprint", metavar="FRAME")
    ros.add_argument(
        "--ros-timeout",
        type=float,
        default=30.0,
        metavar="S",
        help="wait this long for odometry (default 30)",
    )


def ros_session(args: argparse.Namespace, site: Site, robot_id: str, start: Pose | None) -> RobotSession:
    from wsnav.ros_bridge.robot_backend import ros_session as start_session

    return start_session(args, site, robot_id, start)


def sim_command(args: argparse.Namespace) -> int:
    from wsnav.ros_bridge.sim_node import sim_command as run

    return run(args)
