"""The robot's navigation along Nav2's seams: costmap, planning, control, behaviors, the navigator that runs
them (the paper's Algorithm 3) and the robot backend protocol they drive. Pure logic: no bus, no clock.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.navigation import backend, behaviors, control, costmap, navigator, planning

__all__ = [
    "backend",
    "behaviors",
    "control",
    "costmap",
    "navigator",
    "planning",
]
