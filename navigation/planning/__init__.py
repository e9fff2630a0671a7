"""Global planning: A* over the costmap (pyastar2d), the planner the navigator calls, and `wsnav plan`'s
offline plan.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.navigation.planning import costmap_planner, global_planner, offline_plan

__all__ = [
    "costmap_planner",
    "global_planner",
    "offline_plan",
]
