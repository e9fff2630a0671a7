"""The small interfaces components meet at besides the message contract: a clock and a publish/subscribe bus.

Depends on nothing of ours but `schemas`; `robot_agent` and `zone_sim` both build on it and never on each other.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.runtime import bus, cli_support, clock, logs, mqtt_bus, timers

__all__ = [
    "bus",
    "cli_support",
    "clock",
    "logs",
    "mqtt_bus",
    "timers",
]
