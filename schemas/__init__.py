"""The wsnav message contract and site file: the one vocabulary every component shares.

Depends on nothing else of ours, so firmware tooling, broker, robot agent and zone simulator can all import it.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.schemas import (
        credentials,
        export,
        ids,
        messages,
        ros_map,
        site,
        site_file,
        site_render,
        topics,
        yaml_file,
    )

__all__ = [
    "credentials",
    "export",
    "ids",
    "messages",
    "ros_map",
    "site",
    "site_file",
    "site_render",
    "topics",
    "yaml_file",
]
