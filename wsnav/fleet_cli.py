"""`wsnav fleet --sim --site DIR`: every robot of a site, each its own agent, credentials and MQTT connection, on
simulated TurtleBot3s sharing one simulated world, in one process.
`wsnav fleet-experiment --site DIR --out DIR`: the fleet scenario (random goals, raffled zones), with and
without the zone layer: collisions, deadlocks, goals per hour, distances, a picture of the trails.

The work lives in wsnav.fleet_command, imported only when one of these runs, so other commands start fast.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.runtime.cli_support import host_port
from wsnav.site_commands import default_site

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser


def _broker_args(parser: Parser) -> None:
    parser.add_argument(
        "--site",
        type=Path,
        default=default_site(),
        help="site directory (default sites/school, else the installed example)",
    )
    parser.add_argument(
        "--broker", type=host_port, metavar="HOST:PORT", help="use this broker (default: an embedded amqtt)"
    )
    parser.add_argument(
        "--credentials",
        type=Path,
        metavar="DIR",
        help="the site's credentials (one file per robot), with --broker",
    )
    parser.add_argument("--seed", type=int, default=1, help="seed of the simulation's noise and raffles (1)")


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    fleet = sub.add_parser("fleet", help="run all of a site's robots (simulated, --sim) in one process")
    _broker_args(fleet)
    fleet.add_argument("--sim", action="store_true", required=True, help="simulated TurtleBot3s (required)")
    fleet.add_argument(
        "--config", default="full", metavar="FILE", help="agent config: default, full or a YAML file"
    )
    fleet.add_argument("--nodes", action="store_true", help="emulate the site's nodes too (zone states)")
    fleet.add_argument(
        "--duration", type=float, metavar="S", help="stop after S simulated seconds (default: Ctrl-C)"
    )
    fleet.add_argument(
        "--speed", type=float, default=1.0, metavar="X", help="times real time (1; 0: flat out)"
    )
    fleet.add_argument(
        "--goal",
        action="append",
        default=[],
        metavar="ROBOT=POINT",
        help="send a robot to a named point at start",
    )
    fleet.add_argument(
        "--every", type=float, default=10.0, metavar="S", help="print the fleet every S seconds (10)"
    )
    fleet.set_defaults(func=fleet_command)

    exp = sub.add_parser(
        "fleet-experiment",
        help="all robots on random goals with raffled zones, with and without the zone layer",
    )
    _broker_args(exp)
    exp.add_argument("--minutes", type=float, default=10.0, help="simulated minutes per configuration (10)")
    exp.add_argument(
        "--configs", default="full,default", help="agent configs, comma-separated (full,default)"
    )
    exp.add_argument("--out", type=Path, default=Path("out/fleet"), help="output directory (out/fleet)")
    exp.set_defaults(func=fleet_experiment_command)


def fleet_command(args: argparse.Namespace) -> int:
    from wsnav.fleet_command import fleet

    return fleet(args)


def fleet_experiment_command(args: argparse.Namespace) -> int:
    from wsnav.fleet_command import fleet_experiment

    return fleet_experiment(args)
