"""What `wsnav robot` drives: a robot session (the backend and what the real-time loop does for it), and the
factory another component (ros_bridge's `--ros`) hands the command for its robot.

Its own module, apart from robot_command, so that a backend's component imports this small interface without
loading the agent, the costmap and numba.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from wsnav.navigation.backend import Pose, RobotBackend
from wsnav.schemas.site import Site

if TYPE_CHECKING:
    from wsnav.robot_agent.agent import SimWorldSink


@dataclass
class RobotSession:
    """A robot the real-time loop drives: the backend, and what the loop must do for it besides the agent."""

    robot: RobotBackend
    tick: Callable[[float], float]
    """Called every loop turn with the clock's time; returns when it wants to run next (a simulator steps here)."""
    describe: str
    """What drives the robot, for the banner line."""
    sim_world: SimWorldSink | None = None
    """Where `sim/world` goes (the simulator's lidar and bumper); None for a real robot."""
    close: Callable[[], None] = field(default=lambda: None)
    """Stop the robot and let go of what the session holds; called once, also after an error."""


BackendFactory = Callable[[argparse.Namespace, Site, str, "Pose | None"], RobotSession]
"""(args, site, robot id, --start pose or None) -> a started session; CliError for what the user must fix."""
