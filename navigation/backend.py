"""The interface between the agent and a robot: where it is, what its lidar sees, the velocity it is told.

The simulated TurtleBot3 implements it, and so does ros_bridge.robot_backend over ROS (tf/odometry, /scan, /cmd_vel).
The agent never steps a robot: whoever owns the world (a real-time loop, the experiment) advances the simulation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

Pose = tuple[float, float, float]
"""x, y (metres, map frame), yaw (radians)."""


@dataclass(frozen=True)
class LaserScan:
    """One sweep, as sensor_msgs/LaserScan lays it out; ranges beyond `range_max` are +inf (no return)."""

    stamp: float
    pose: Pose
    """Where the sensor was when the sweep was taken (the sim's lidar sits on the robot's centre)."""
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: NDArray[np.float32]


@dataclass(frozen=True)
class DriveLimits:
    """How fast the robot may go and accelerate; defaults are TurtleBot3 Burger's (as its Nav2 configuration)."""

    max_linear: float = 0.22
    max_angular: float = 2.84
    linear_accel: float = 2.5
    angular_accel: float = 3.2


BURGER_RADIUS_M = 0.105
"""TurtleBot3 Burger's footprint radius (m), for a backend that is not told its robot's."""


@dataclass(frozen=True)
class Velocity:
    linear: float
    """m/s, forward positive."""
    angular: float
    """rad/s, counter-clockwise positive."""


class RobotBackend(Protocol):
    @property
    def robot_id(self) -> str: ...

    @property
    def radius(self) -> float:
        """Circular footprint radius (m): the inscribed radius of the costmap."""
        ...

    def pose(self) -> Pose: ...

    def velocity(self) -> Velocity:
        """What the base is doing now (odometry), not what it was told."""
        ...

    def scan(self) -> LaserScan | None:
        """The newest sweep, or None before the first."""
        ...

    def command(self, velocity: Velocity) -> None:
        """Set the velocity; the base clamps it to its limits."""
        ...

    def stop(self) -> None: ...
