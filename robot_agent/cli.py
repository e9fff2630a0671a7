"""`wsnav plan --site DIR --from POINT --to POINT [--block ZONE ...] [--png FILE]`: an offline plan, no broker.

Prints one JSON object (`reachable`, `length_m`, `path`, `blocked_zones`, `plan_ms`, ...). The work lives in
robot_agent.offline_plan, imported only when the command runs, so other commands start fast.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import TYPE_CHECKING

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


def plan_command(args: argparse.Namespace) -> int:
    from robot_agent.offline_plan import plan_command as run

    return run(args)
