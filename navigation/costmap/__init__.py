"""The layered costmap (costmap_2d's): a list of layers, each one class with updateBounds/updateCosts, merged
by costmap_2d's rules, then inflation.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.navigation.costmap import inflation, layered_costmap, layers

__all__ = [
    "inflation",
    "layered_costmap",
    "layers",
]
