"""Global planning: A* over a weighted grid (`astar.py`, pyastar2d with a coarse-to-fine band), the planner the
navigator calls on the costmap (`global_planner.py::GlobalPlanner`), and `wsnav plan`'s offline plan.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.navigation.planning import astar, global_planner, offline_plan

__all__ = [
    "astar",
    "global_planner",
    "offline_plan",
]
