"""`wsnav plan --site DIR --from POINT --to POINT [--block ZONE ...] [--png FILE]`: an offline plan, no broker.
`wsnav robot --site DIR --broker HOST:PORT --credentials FILE --sim --start POINT [--goal POINT]`: the agent.

`plan` prints one JSON object (`reachable`, `length_m`, `path`, `blocked_zones`, `plan_ms`, ...). The work
lives in robot_agent.offline_plan and robot_agent.robot_command, imported only when the command runs, so other
commands start fast.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.cli_support import host_port

if TYPE_CHECKING:
    from wsnav.cli_support import Parser


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    plan = sub.add_parser("plan", help="plan a path on a site offline, some zones blocked; prints JSON")
    plan.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    plan.add_argument(
        "--from", dest="start", required=True, metavar="POINT", help="named point, x,y or x,y,yaw"
    )
    plan.add_argument("--to", dest="goal", required=True, metavar="POINT", help="named point, x,y or x,y,yaw")
    plan.add_argument("--block", action="append", default=[], metavar="ZONE", help="zone to treat as blocked")
    plan.add_argument("--robot", help="robot whose footprint radius inflates the map (default: the first)")
    plan.add_argument("--inflation-radius", type=float, default=1.0, metavar="M", help="default 1.0")
    plan.add_argument("--cost-scaling", type=float, default=3.0, metavar="K", help="default 3.0")
    plan.add_argument("--png", type=Path, help="draw the path over the site")
    plan.set_defaults(func=plan_command)
    # Let `--to -0.5,-2` through: argparse would take "-0.5,-2" for an option. Python 3.13 does this itself.
    plan._negative_number_matcher = re.compile(r"^-\.?\d")

    robot = sub.add_parser(
        "robot", help="run the robot agent (zone layer, planner, controller) against a broker"
    )
    robot.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    robot.add_argument("--broker", type=host_port, required=True, metavar="HOST:PORT")
    robot.add_argument(
        "--credentials", type=Path, required=True, metavar="FILE", help="the robot's <id>.json"
    )
    robot.add_argument("--sim", action="store_true", help="drive a simulated TurtleBot3 in real time")
    robot.add_argument("--start", required=True, metavar="POINT", help="named point, x,y or x,y,yaw")
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
    robot.set_defaults(func=robot_command)
    robot._negative_number_matcher = re.compile(r"^-\.?\d")


def plan_command(args: argparse.Namespace) -> int:
    from robot_agent.offline_plan import plan_command as run

    return run(args)


def robot_command(args: argparse.Namespace) -> int:
    from robot_agent.robot_command import robot_command as run

    return run(args)
