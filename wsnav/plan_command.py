"""`wsnav plan --site DIR --from POINT --to POINT [--block ZONE ...] [--png FILE]`: an offline plan, no broker.

Prints one JSON object (`reachable`, `length_m`, `path`, `blocked_zones`, `plan_ms`, ...). The plan is
wsnav.navigation.planning.offline_plan's; the picture is drawn here, since components do not import wsnav (the site drawing is
schemas.site_render). Planner and matplotlib are imported only when the command runs, so other commands start fast.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.runtime.cli_support import CliError

if TYPE_CHECKING:
    from wsnav.navigation.planning.offline_plan import OfflinePlan
    from wsnav.runtime.cli_support import Parser


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
    from wsnav.navigation.planning.offline_plan import offline_plan

    result = offline_plan(
        args.site, args.start, args.goal, args.block, args.robot, args.inflation_radius, args.cost_scaling
    )
    out = dict(result.json)
    if args.png is not None:
        draw_plan(result, args.png, f"{args.start} -> {args.goal}")
        out["png"] = str(args.png)
    print(json.dumps(out))
    return 0


def draw_plan(result: OfflinePlan, png: Path, title: str) -> None:
    """The site with the blocked zones hatched and the planned path (or why there is none) in the title."""
    from wsnav.schemas.site_render import draw_site, figure_for

    site, plan, blocked = result.site, result.plan, result.blocked
    fig, ax = figure_for(site)
    draw_site(ax, site, blocked=blocked, show_routes=False)
    if plan.reachable:
        ax.plot(plan.path[:, 0], plan.path[:, 1], color="blue", linewidth=2.2, label="plan")
        status = f"{plan.length_m:.2f} m"
    else:
        status = f"unreachable ({plan.reason})"
    ax.set_title(f"site {site.name}: {title}, blocked: {', '.join(blocked) or 'none'}: {status}")
    fig.tight_layout()
    try:
        png.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(png, dpi=110)
    except OSError as exc:
        raise CliError(f"{png}: cannot write picture: {exc.strerror or exc}") from None
