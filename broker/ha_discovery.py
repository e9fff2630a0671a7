"""Home Assistant MQTT discovery for a site, generated on the Pi side from the site file (nodes spend no RAM).

One retained config per entity under `<prefix>/binary_sensor/wsnav_<site>/<object>/config` (Home Assistant's
`<discovery_prefix>/<component>/[<node_id>/]<object_id>/config`; our ids already fit its [a-zA-Z0-9_-]):
- per zone and watching node, an occupancy sensor on `zones/<zone>/state/<node>`: on when the node says
  `blocked` or `caution`; a binary sensor reads one topic, so a zone watched by two nodes gets two sensors;
- per node, a connectivity sensor on `nodes/<node>/status` (its birth `online` and will `offline`), with the
  node's diagnostics (`nodes/<node>/info`) as attributes.
The zone sensors take their availability from the node's status topic, so a node that lost its link shows as
unavailable rather than as an old word. Payloads use Home Assistant's full key names (each has a documented
abbreviation; both are accepted); tests/test_broker_ha_discovery.py checks them against the documented schema.
"""

from __future__ import annotations

import json
from typing import Any

from wsnav.schemas import topics
from wsnav.schemas.site_file import SiteFile

DEFAULT_PREFIX = "homeassistant"
ORIGIN = {"name": "wsnav"}


def _device(site: str, ident: str, name: str, model: str) -> dict[str, Any]:
    return {"identifiers": [f"wsnav_{site}_{ident}"], "name": name, "model": model, "manufacturer": "wsnav"}


def _availability(site: str, node: str) -> list[dict[str, str]]:
    return [
        {
            "topic": topics.node_status(site, node),
            "value_template": "{{ value_json.status }}",
            "payload_available": "online",
            "payload_not_available": "offline",
        }
    ]


def discovery_messages(spec: SiteFile, prefix: str = DEFAULT_PREFIX) -> list[tuple[str, bytes]]:
    """(topic, payload) of every discovery config of the site, in site-file order; publish them retained."""
    site = spec.name
    base = f"{prefix}/binary_sensor/wsnav_{site}"
    out: list[tuple[str, dict[str, Any]]] = []
    zone_names = {z.id: z.name or z.id for z in spec.zones}
    for node in spec.nodes:
        zone = node.zone
        out.append(
            (
                f"{base}/{zone}_{node.id}/config",
                {
                    "name": f"{zone_names[zone]} occupied ({node.id})",
                    "unique_id": f"wsnav_{site}_{zone}_{node.id}",
                    "state_topic": topics.zone_state(site, zone, node.id),
                    "value_template": "{{ 'ON' if value_json.state in ('blocked', 'caution') else 'OFF' }}",
                    "payload_on": "ON",
                    "payload_off": "OFF",
                    "json_attributes_topic": topics.zone_state(site, zone, node.id),
                    "device_class": "occupancy",
                    "availability": _availability(site, node.id),
                    "device": _device(site, f"zone_{zone}", f"wsnav {site} {zone_names[zone]}", "zone"),
                    "origin": ORIGIN,
                },
            )
        )
        out.append(
            (
                f"{base}/{node.id}_link/config",
                {
                    "name": f"{node.id} link",
                    "unique_id": f"wsnav_{site}_{node.id}_link",
                    "state_topic": topics.node_status(site, node.id),
                    "value_template": "{{ 'ON' if value_json.status == 'online' else 'OFF' }}",
                    "payload_on": "ON",
                    "payload_off": "OFF",
                    "json_attributes_topic": topics.node_info(site, node.id),
                    "device_class": "connectivity",
                    "entity_category": "diagnostic",
                    "device": _device(site, node.id, f"wsnav {site} {node.id}", "ESP8266 zone node"),
                    "origin": ORIGIN,
                },
            )
        )
    return [(topic, json.dumps(config, separators=(",", ":")).encode()) for topic, config in out]
