"""The robot agent: MQTT in, the costmap and navigator, status out; its configurations and `wsnav robot`."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.robot_agent import agent, agent_config, cli, robot_command, robot_session, sim

__all__ = [
    "agent",
    "agent_config",
    "cli",
    "robot_command",
    "robot_session",
    "sim",
]
