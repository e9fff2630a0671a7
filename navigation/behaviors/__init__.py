"""What the navigator does beside following a plan: move_base's recoveries, leaving a blocked zone, right of
way between robots.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.navigation.behaviors import escape, recovery, right_of_way

__all__ = [
    "escape",
    "recovery",
    "right_of_way",
]
