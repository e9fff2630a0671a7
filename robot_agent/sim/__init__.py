"""The simulated TurtleBot3 the agent drives without a robot: its drive, lidar and world."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.robot_agent.sim import lidar, turtlebot3, world_grid

__all__ = [
    "lidar",
    "turtlebot3",
    "world_grid",
]
