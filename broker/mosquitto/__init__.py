"""The same security model on Mosquitto 2: its configuration files, and Mosquitto as a child process."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.broker.mosquitto import config, firewall, process, store

__all__ = [
    "config",
    "firewall",
    "process",
    "store",
]
