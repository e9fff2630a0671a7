"""One logging set-up for every command: a level chosen with `--log-level`, one line per record on stderr.

Components only ever call `logging.getLogger(__name__)` (names under `wsnav.`); the command that runs them
sets the level here, once. The ROS bridge also forwards its records to rospy (ros_bridge), so they reach /rosout.
"""

from __future__ import annotations

import argparse
import logging

LEVELS = ("debug", "info", "warning", "error")
FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def add_log_level(parser: argparse.ArgumentParser) -> None:
    """`--log-level` on a command's parser (warning by default: problems only)."""
    parser.add_argument(
        "--log-level", choices=LEVELS, default="warning", help="which log records to print (default: warning)"
    )


def setup_logging(level: str = "warning") -> None:
    """Configure the root logger once per process (a second call changes only the level)."""
    root = logging.getLogger()
    if not root.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter(FORMAT))
        root.addHandler(handler)
    root.setLevel(level.upper())
