"""`wsnav robot --site DIR --broker HOST:PORT --credentials FILE --sim --start POINT [--goal POINT]`: the agent.

The work lives in robot_agent.robot_command, imported only when the command runs, so other commands start fast.
Other robots are added to the command by the component that knows them (`robot_parser` below): ros_bridge adds
`--ros`, so this component stays free of ROS.
(`wsnav plan` is wsnav.plan_command: it draws a picture, which is the CLI's job, over wsnav.navigation.planning.offline_plan.)
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.runtime.cli_support import add_broker_arguments, add_state_dir_argument

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    robot = sub.add_parser(
        "robot", help="run the robot agent (zone layer, planner, controller) against a broker"
    )
    robot.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    add_broker_arguments(robot)
    robot.add_argument(
        "--credentials", type=Path, required=True, metavar="FILE", help="the robot's <id>.json"
    )
    robot.add_argument("--sim", action="store_true", help="drive a simulated TurtleBot3 in real time")
    robot.add_argument(
        "--start",
        metavar="POINT",
        help="named point, x,y or x,y,yaw: where the robot starts (needed with --sim)",
    )
    robot.add_argument("--goal", metavar="POINT", help="go there at once (more goals come over MQTT)")
    robot.add_argument(
        "--config",
        default="full",
        metavar="FILE",
        help="agent config: default, full (the default) or a YAML file",
    )
    robot.add_argument(
        "--exit-on-arrival", action="store_true", help="exit when the goal is reached (0) or cancelled (1)"
    )
    robot.add_argument("--connect-timeout", type=float, default=10.0, metavar="S", help="default 10")
    add_state_dir_argument(robot)
    robot.set_defaults(func=robot_command)
    robot._negative_number_matcher = re.compile(r"^-\.?\d")


def robot_parser(sub: argparse._SubParsersAction[Parser]) -> Parser:
    """The `wsnav robot` parser, for a component that adds a robot backend to it: its flag stores a
    robot_session.BackendFactory in `args.backend`."""
    parser = sub.choices.get("robot")
    if parser is None:
        raise RuntimeError("robot_agent.cli.register must run before a backend is added to `wsnav robot`")
    return parser


def robot_command(args: argparse.Namespace) -> int:
    from wsnav.robot_agent.robot_command import robot_command as run

    return run(args)
