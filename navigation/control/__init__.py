"""Local control: regulated pure pursuit over the global plan, checked against the local costmap."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.navigation.control import controller

__all__ = [
    "controller",
]
