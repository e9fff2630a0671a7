"""The `wsnav` console script: one entry point whose subcommands come from each component's `cli` module."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence

from wsnav import experiment_cli, fleet_cli, ota_command, plan_command, site_commands
from wsnav.broker import cli as broker_cli
from wsnav.console import cli as console_cli
from wsnav.firmware import cli as firmware_cli
from wsnav.robot_agent import cli as robot_agent_cli
from wsnav.ros2_bridge import cli as ros2_bridge_cli
from wsnav.ros_bridge import cli as ros_bridge_cli
from wsnav.ros_bridge import robot_cli as ros_bridge_robot_cli
from wsnav.runtime.cli_support import CliError, Parser
from wsnav.runtime.logs import add_log_level, setup_logging
from wsnav.zone_sim import cli as zone_sim_cli

Registrar = Callable[["argparse._SubParsersAction[Parser]"], None]

EXTRA_OF: dict[str, str] = {
    "amqtt": "broker",
    "argon2": "broker",
    "numpy": "robot",
    "scipy": "robot",
    "numba": "robot",
    "pyastar2d": "robot",
    "PIL": "robot",
    "matplotlib": "robot",
    "starlette": "console",
    "uvicorn": "console",
    "pandas": "research",
    "dask": "research",
    "distributed": "research",
    "psutil": "research",
    "cyclonedds": "ros2",
}
"""Which install (pyproject's extras, one per role) brings a third-party module: a command run from a smaller
install says what to add in one line instead of a traceback."""

REGISTRARS: list[Registrar] = [
    site_commands.register,
    plan_command.register,
    robot_agent_cli.register,
    broker_cli.register,
    firmware_cli.register,
    ota_command.register,  # under `wsnav firmware`, registered above
    zone_sim_cli.register,
    experiment_cli.register,
    fleet_cli.register,
    ros_bridge_cli.register,
    ros_bridge_robot_cli.register,
    ros2_bridge_cli.register,
    console_cli.register,
]


def build_parser() -> Parser:
    parser = Parser(prog="wsnav", description="Robots that navigate with a wireless sensor network's eyes.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for register in REGISTRARS:
        register(sub)
    for command in leaf_parsers(parser):
        add_log_level(command)
    return parser


def leaf_parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """The parsers that run something (`wsnav robot`, `wsnav broker run`, ...): every one takes --log-level."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return [parser]
    return [leaf for a in subs for p in dict.fromkeys(a.choices.values()) for leaf in leaf_parsers(p)]


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(args.log_level)
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"wsnav: error: {exc}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:
        missing = (exc.name or "").split(".")[0]
        if missing not in EXTRA_OF:
            raise
        print(
            f"wsnav: error: this command needs {missing}, which this install lacks "
            f"(pip install 'wsnav[{EXTRA_OF[missing]}]'; docs/install.md)",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader (e.g. `| head`) went away: stop quietly, and keep Python from complaining at exit.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    raise SystemExit(main())
