"""The operator's commands: `wsnav console` (the web page) and
`wsnav status|watch|block|unblock|goal|cancel|clear-status|node-command`.

Each takes the site, the broker and the operator's credentials file; the work lives in console.terminal and
console.serve, imported only when a command runs.
"""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.runtime.cli_support import add_broker_arguments, host_port

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser


def operator_arguments(p: argparse.ArgumentParser) -> None:
    """What every command that acts as the site's operator takes (also `wsnav firmware ota`)."""
    p.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    add_broker_arguments(p)
    p.add_argument(
        "--credentials", type=Path, required=True, metavar="FILE", help="the operator's operator.json"
    )
    p.add_argument("--connect-timeout", type=float, default=10.0, metavar="S", help="default 10")


def _state_dir() -> Path:
    """Where the console keeps its sessions and event log unless told: $XDG_STATE_HOME/wsnav."""
    return Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state") / "wsnav"


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    console = sub.add_parser(
        "console", help="the operator's live web page: map, nodes, robots, blocks; steering"
    )
    operator_arguments(console)
    console.add_argument(
        "--bind",
        type=host_port,
        default=("127.0.0.1", 8080),
        metavar="HOST:PORT",
        help="default 127.0.0.1:8080",
    )
    console.add_argument(
        "--state-dir",
        type=Path,
        default=_state_dir(),
        metavar="DIR",
        help="where login sessions are kept, so a restart keeps pages logged in (default ~/.local/state/wsnav)",
    )
    console.set_defaults(func=_run("serve", "console_command"))

    log = sub.add_parser(
        "log", help="the console's event log: blocks, nodes offline/online, robots arrived or waiting"
    )
    log.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    log.add_argument(
        "--state-dir", type=Path, default=_state_dir(), metavar="DIR", help="the console's --state-dir"
    )
    log.add_argument(
        "--last", type=int, default=50, metavar="N", help="how many of the newest events (default 50)"
    )
    log.add_argument("--json", action="store_true", help="one JSON object per line")
    log.set_defaults(func=_run("terminal", "log_command"))

    status = sub.add_parser("status", help="one table of the site's nodes, zones, robots and operator blocks")
    operator_arguments(status)
    status.add_argument("--json", action="store_true", help="the same as JSON (what GET /api/state returns)")
    status.add_argument(
        "--wait",
        type=float,
        default=5.0,
        metavar="S",
        help="the longest wait for the broker's retained replay (default 5 s; it answers once the replay is over)",
    )
    status.set_defaults(func=_run("terminal", "status_command"))

    watch = sub.add_parser("watch", help="the status table, redrawn live")
    operator_arguments(watch)
    watch.add_argument("--every", type=float, default=1.0, metavar="S", help="redraw period, default 1")
    watch.set_defaults(func=_run("terminal", "watch_command"))

    block = sub.add_parser("block", help="block a zone or a polygon for a while (an operator block)")
    operator_arguments(block)
    block.add_argument("zone", nargs="?", metavar="ZONE")
    block.add_argument("--polygon", nargs="+", metavar="X,Y", help="at least 3 corners in metres (map frame)")
    block.add_argument(
        "--for", dest="duration", metavar="TIME", help="90s, 10m, 2h (default: until unblocked)"
    )
    block.add_argument("--reason", help="shown to operators and in the robots' status")
    block.add_argument("--id", dest="block_id", help="the block's id (default: a new one)")
    block.add_argument(
        "--extend",
        metavar="ID",
        help="extend block ID by --for TIME instead (same id: robots hold the block throughout)",
    )
    block.set_defaults(func=_run("terminal", "block_command"))
    block._negative_number_matcher = re.compile(r"^-\.?\d")

    unblock = sub.add_parser("unblock", help="lift an operator block")
    operator_arguments(unblock)
    unblock.add_argument("block_id", metavar="ID")
    unblock.set_defaults(func=_run("terminal", "unblock_command"))

    goal = sub.add_parser("goal", help="send a robot to a named point or a pose")
    operator_arguments(goal)
    goal.add_argument("robot", metavar="ROBOT")
    goal.add_argument("point", metavar="POINT", help="a named point of the site, or x,y[,yaw]")
    goal.set_defaults(func=_run("terminal", "goal_command"))
    goal._negative_number_matcher = re.compile(r"^-\.?\d")

    cancel = sub.add_parser("cancel", help="cancel a robot's goal: it stops")
    operator_arguments(cancel)
    cancel.add_argument("robot", metavar="ROBOT")
    cancel.set_defaults(func=_run("terminal", "cancel_command"))

    clear = sub.add_parser(
        "clear-status",
        help="make the broker forget a robot's retained status (a robot gone, or a forged status)",
    )
    operator_arguments(clear)
    clear.add_argument("robot", metavar="ROBOT")
    clear.set_defaults(func=_run("terminal", "clear_status_command"))

    node = sub.add_parser(
        "node-command",
        help="command a zone node over the network: restart it, have it send its info, set its heartbeat (RAM)",
    )
    operator_arguments(node)
    node.add_argument("node", metavar="NODE")
    node.add_argument("action", choices=["restart", "send-info", "heartbeat"])
    node.add_argument(
        "seconds", nargs="?", metavar="SECONDS", help="heartbeat only: the new period, (0, 3600]"
    )
    node.set_defaults(func=_run("terminal", "node_command_command"))


def _run(module: str, name: str):
    def run(args: argparse.Namespace) -> int:
        import importlib

        return int(getattr(importlib.import_module(f"wsnav.console.{module}"), name)(args) or 0)

    return run
