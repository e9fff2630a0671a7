"""The wiring layer: the `wsnav` command line, site pictures, and (later) the demo and experiment harness.

Only this layer may import several components at once; the components meet at the message contract.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav import (
        broker,
        cli,
        console,
        experiment_cli,
        experiment_command,
        experiments,
        firmware,
        fleet_cli,
        fleet_command,
        healthcheck,
        navigation,
        plan_command,
        robot_agent,
        ros2_bridge,
        ros_bridge,
        runtime,
        schemas,
        site_commands,
        zone_sim,
        zones,
    )

__all__ = [
    "broker",
    "cli",
    "console",
    "experiment_cli",
    "experiment_command",
    "experiments",
    "firmware",
    "fleet_cli",
    "fleet_command",
    "healthcheck",
    "navigation",
    "plan_command",
    "robot_agent",
    "ros2_bridge",
    "ros_bridge",
    "runtime",
    "schemas",
    "site_commands",
    "zone_sim",
    "zones",
]
