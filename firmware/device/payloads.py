"""Topic names and payload bytes of the MQTT contract, built exactly as `schemas.messages` serialises them.

Pure logic (MicroPython and CPython). Built by concatenation, not json.dumps, because the contract's bytes are
compact JSON in the models' field order (`{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":3}`) and
MicroPython's json.dumps puts spaces after separators. Ids never need escaping: they match
`[A-Za-z0-9_-]{1,32}` (checked by nodeconfig's `valid_id`, which lives there so that it leaves the heap with the
config loader after boot).
"""

ROOT = "wsn"
VERSION = 1

BLOCKED = "blocked"
CLEAR = "clear"
CAUTION = "caution"
ONLINE = "online"
OFFLINE = "offline"

SEQ_MAX = 2**30 - 1
"""The schema allows 2**31-1; we stay below 2**30 so seq is a small int (no heap) on the ESP8266."""


def zone_state_topic(site: str, zone: str, node: str) -> str:
    return ROOT + "/" + site + "/zones/" + zone + "/state/" + node


def node_status_topic(site: str, node: str) -> str:
    return ROOT + "/" + site + "/nodes/" + node + "/status"


def zone_state_payload(zone: str, node: str, state: str, seq: int) -> bytes:
    """`schemas.messages.ZoneState(...).to_payload()`, byte for byte."""
    return (
        '{"v":1,"zone":"' + zone + '","node":"' + node + '","state":"' + state + '","seq":' + str(seq) + "}"
    ).encode()


def node_status_payload(node: str, status: str) -> bytes:
    """`schemas.messages.NodeStatus(...).to_payload()`, byte for byte."""
    return ('{"v":1,"node":"' + node + '","status":"' + status + '"}').encode()
