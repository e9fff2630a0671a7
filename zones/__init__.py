"""The zone model every component shares: node messages validated, the one zone rule (fusion, staleness,
operator blocks) that turns them into a cost per zone, zone geometry, and costmap_2d's cost values.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.zones import cost_values, geometry, intake, zone_layer

__all__ = [
    "cost_values",
    "geometry",
    "intake",
    "zone_layer",
]
