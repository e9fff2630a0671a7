"""`wsnav experiment --site DIR --runs N --out DIR [...]`: the paper's experiment, each configuration, a report.
`wsnav demo [--out DIR]`: its short form, one `full` run of each route, a table and a picture.

The work lives in wsnav.experiment_command, imported only when one of these runs, so other commands start fast.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.runtime.cli_support import host_port
from wsnav.site_commands import default_site

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    exp = sub.add_parser(
        "experiment", help="the paper's experiment: N runs per route and configuration, a report"
    )
    exp.add_argument(
        "--site",
        type=Path,
        default=default_site(),
        help="site directory (default sites/school, else the installed example)",
    )
    exp.add_argument(
        "--runs", type=int, default=50, metavar="N", help="runs per route and configuration (50)"
    )
    exp.add_argument("--out", type=Path, default=Path("out/experiment"), help="output directory")
    exp.add_argument("--seed", type=int, default=1, help="base seed (same seed, same table); default 1")
    exp.add_argument(
        "--configs",
        default="default,zones,full",
        help="agent configs, comma-separated, any of default,zones,full or YAML files (default,zones,full)",
    )
    exp.add_argument(
        "--workers", type=int, default=os.cpu_count() or 1, metavar="K", help="processes (default: the cores)"
    )
    exp.add_argument(
        "--run-broker",
        choices=("amqtt", "mosquitto"),
        default=None,
        help="the broker each run starts for itself: amqtt in the worker (default) or a Mosquitto process "
        "(same results, less wall time; needs mosquitto installed)",
    )
    exp.add_argument("--broker", type=host_port, metavar="HOST:PORT", help="use this broker (one worker)")
    exp.add_argument("--credentials", type=Path, metavar="DIR", help="the site's credentials, with --broker")
    exp.add_argument(
        "--scheduler",
        type=scheduler_address,
        metavar="tcp://HOST:PORT",
        help="run each run as a task on this Dask cluster (docs/cluster.md) instead of the local processes",
    )
    exp.add_argument(
        "--record",
        type=Path,
        metavar="DIR",
        help="keep every run whole: one MCAP file per run in DIR (pose, plans, the agent's messages with their "
        "times, the navigator's states and recoveries; Foxglove opens them); needs the `experiment` extra",
    )
    exp.add_argument(
        "--pictures",
        type=Path,
        metavar="DIR",
        help="draw each run's driven path over the map, one PNG per run in DIR",
    )
    exp.add_argument(
        "--backend",
        choices=("sim", "ros"),
        default="sim",
        help="who navigates: wsnav's navigator on the simulated TurtleBot3 in lock step (sim, the default), or "
        "the ROS 1 navigation installed here (ros: move_base with navfn, DWA and costmap_2d, driving "
        "`wsnav sim --ros --clock` on a roscore of its own, one run at a time; docs/ros.md)",
    )
    exp.add_argument(
        "--move-base-cmd",
        default=None,
        metavar="CMD",
        help="with --backend ros: the command that starts move_base (default `rosrun move_base move_base`)",
    )
    exp.add_argument(
        "--compare",
        type=Path,
        metavar="DIR",
        help="the same plan's output from the other backend (its runs.csv): the report compares them run by run",
    )
    exp.add_argument(
        "--report-only",
        action="store_true",
        help="render the report again from --out's runs.csv and header.md; nothing runs",
    )
    exp.set_defaults(func=experiment_command)

    demo = sub.add_parser("demo", help="one `full` run of each route of the school: a table and a picture")
    demo.add_argument(
        "--site",
        type=Path,
        default=default_site(),
        help="site directory (default sites/school, else the installed example)",
    )
    demo.add_argument(
        "--out", type=Path, default=Path("out/demo"), help="output directory (default out/demo)"
    )
    demo.add_argument("--seed", type=int, default=1, help="base seed of the raffles (default 1)")
    demo.set_defaults(func=demo_command)


def scheduler_address(text: str) -> str:
    """A Dask scheduler's `tcp://HOST:PORT`; argparse turns the error into one line."""
    scheme, sep, rest = text.partition("://")
    if not sep or scheme != "tcp":
        raise argparse.ArgumentTypeError(f"expected tcp://HOST:PORT, got {text!r}")
    try:
        host, port = host_port(rest)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected tcp://HOST:PORT, got {text!r}") from None
    return f"tcp://[{host}]:{port}" if ":" in host else f"tcp://{host}:{port}"


def experiment_command(args: argparse.Namespace) -> int:
    from wsnav.experiment_command import experiment

    return experiment(args)


def demo_command(args: argparse.Namespace) -> int:
    from wsnav.experiment_command import demo

    return demo(args)
