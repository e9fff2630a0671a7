"""The layered costmap (costmap_2d's): one list of layers, inflation the last, each one class with the same calls
(update_bounds/update_costs/clear/rebuild), merged by costmap_2d's rules (`merge`).
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.navigation.costmap import inflation, layered_costmap, layers, merge

__all__ = [
    "inflation",
    "layered_costmap",
    "layers",
    "merge",
]
