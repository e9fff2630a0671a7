"""The site's broker: access rules and per-identity credentials, served by amqtt (`amqtt/`) or Mosquitto
(`mosquitto/`).
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.broker import acl, amqtt, cli, credentials, ha_discovery, mosquitto

__all__ = [
    "acl",
    "amqtt",
    "cli",
    "credentials",
    "ha_discovery",
    "mosquitto",
]
