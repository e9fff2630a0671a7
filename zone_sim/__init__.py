"""Emulated zone nodes on a simulated world, running the firmware's own logic, driven by a scenario."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.zone_sim import (
        cli,
        emulated_node,
        firmware_modules,
        links,
        raffle,
        run,
        scenario,
        sensor_model,
        simulator,
        world,
    )

__all__ = [
    "cli",
    "emulated_node",
    "firmware_modules",
    "links",
    "raffle",
    "run",
    "scenario",
    "sensor_model",
    "simulator",
    "world",
]
