"""`wsnav zones --site DIR --broker HOST:PORT --credentials DIR (--scenario FILE | --block ZONE ...)`.

Emulates every node of the site (the firmware's own logic, each with its own credentials) on a simulated world,
in real time, and prints what happens (obstacles placed and removed, nodes killed, links lost). The work lives
in zone_sim.simulator, imported only when the command runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.runtime.cli_support import host_port

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    zones = sub.add_parser(
        "zones", help="emulate the site's zone nodes on a simulated world (scenario or --block)"
    )
    zones.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    zones.add_argument("--broker", type=host_port, required=True, metavar="HOST:PORT")
    zones.add_argument(
        "--credentials", type=Path, required=True, metavar="DIR", help="folder of `wsnav broker credentials`"
    )
    what = zones.add_mutually_exclusive_group(required=True)
    what.add_argument(
        "--scenario", type=Path, metavar="FILE", help="scenario YAML (see sites/school/scenarios)"
    )
    what.add_argument("--block", action="append", metavar="ZONE", help="zone blocked for the whole run")
    zones.add_argument(
        "--seed", type=int, help="seed of raffles, sensor misses and seq bases (default: file's or 0)"
    )
    zones.add_argument(
        "--duration", type=_positive, metavar="S", help="stop after S seconds (default: file's or never)"
    )
    zones.add_argument("--detection-delay", type=_non_negative, metavar="S", help="sensor detection delay")
    zones.add_argument(
        "--miss-rate", type=_rate, metavar="P", help="probability a reading misses an obstacle"
    )
    zones.add_argument("--nodes", nargs="+", metavar="NODE", help="run only these nodes")
    zones.add_argument("--quiet", action="store_true", help="print only the summary")
    zones.set_defaults(func=zones_command)


def _positive(text: str) -> float:
    value = _float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _non_negative(text: str) -> float:
    value = _float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def _rate(text: str) -> float:
    value = _float(text)
    if not 0 <= value < 1:
        raise argparse.ArgumentTypeError(f"expected a probability in [0, 1), got {text!r}")
    return value


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def zones_command(args: argparse.Namespace) -> int:
    from wsnav.zone_sim.run import run_zones

    return run_zones(args)
