"""MQTT topic names of the contract: build them here, parse them here, nowhere else.

Every topic sits under `wsn/<site>/`; ids never contain topic separators or wildcards (schemas.ids).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from wsnav.schemas.ids import ID_PATTERN

ROOT = "wsn"
_ID = re.compile(ID_PATTERN)

TopicKind = Literal[
    "zone_state",
    "node_status",
    "node_info",
    "node_command",
    "node_log",
    "node_ota_request",
    "node_ota_chunk",
    "robot_status",
    "robot_goal",
    "operator_block",
    "sim_world",
]


def _check(*ids: str) -> None:
    for value in ids:
        if not _ID.match(value):
            raise ValueError(f"not a valid id for a topic level: {value!r}")


def zone_state(site: str, zone: str, node: str) -> str:
    _check(site, zone, node)
    return f"{ROOT}/{site}/zones/{zone}/state/{node}"


def node_status(site: str, node: str) -> str:
    _check(site, node)
    return f"{ROOT}/{site}/nodes/{node}/status"


def node_info(site: str, node: str) -> str:
    """A node's diagnostics (schemas.messages.NodeInfo), retained."""
    _check(site, node)
    return f"{ROOT}/{site}/nodes/{node}/info"


def node_command(site: str, node: str) -> str:
    """The operator's commands to one node (schemas.messages.NodeCommand): QoS 1, never retained."""
    _check(site, node)
    return f"{ROOT}/{site}/nodes/{node}/command"


def node_log(site: str, node: str) -> str:
    """A node's last log lines (schemas.messages.NodeLog), its answer to a `log` command: only that node writes it."""
    _check(site, node)
    return f"{ROOT}/{site}/nodes/{node}/log"


def node_ota_request(site: str, node: str) -> str:
    """A node in update mode asks for the next chunk (schemas.messages.OtaRequest): only that node writes it."""
    _check(site, node)
    return f"{ROOT}/{site}/nodes/{node}/ota/request"


def node_ota_chunk(site: str, node: str) -> str:
    """The operator's answer to an OtaRequest (schemas.messages.ota_chunk, binary): only the operator writes it."""
    _check(site, node)
    return f"{ROOT}/{site}/nodes/{node}/ota/chunk"


def all_node_ota_chunks(site: str) -> str:
    _check(site)
    return f"{ROOT}/{site}/nodes/+/ota/chunk"


def robot_status(site: str, robot: str) -> str:
    _check(site, robot)
    return f"{ROOT}/{site}/robots/{robot}/status"


def robot_goal(site: str, robot: str) -> str:
    _check(site, robot)
    return f"{ROOT}/{site}/robots/{robot}/goal"


def operator_block(site: str, block_id: str) -> str:
    _check(site, block_id)
    return f"{ROOT}/{site}/operator/blocks/{block_id}"


def sim_world(site: str) -> str:
    """Simulation only: where the zone simulator publishes the obstacles it placed, for simulated lidars."""
    _check(site)
    return f"{ROOT}/{site}/sim/world"


def all_zone_states(site: str) -> str:
    _check(site)
    return f"{ROOT}/{site}/zones/+/state/+"


def all_node_statuses(site: str) -> str:
    _check(site)
    return f"{ROOT}/{site}/nodes/+/status"


def all_node_infos(site: str) -> str:
    _check(site)
    return f"{ROOT}/{site}/nodes/+/info"


def all_node_commands(site: str) -> str:
    _check(site)
    return f"{ROOT}/{site}/nodes/+/command"


def all_operator_blocks(site: str) -> str:
    _check(site)
    return f"{ROOT}/{site}/operator/blocks/+"


def all_robot_statuses(site: str) -> str:
    _check(site)
    return f"{ROOT}/{site}/robots/+/status"


@dataclass(frozen=True)
class Topic:
    """A parsed contract topic; fields that do not apply to its kind are None."""

    kind: TopicKind
    site: str
    zone: str | None = None
    node: str | None = None
    robot: str | None = None
    block_id: str | None = None


def parse(topic: str) -> Topic | None:
    """The contract topic this name denotes, or None if it is not one (wrong root, shape or ids)."""
    parts = topic.split("/")
    if len(parts) < 3 or parts[0] != ROOT or not all(_ID.match(p) for p in parts[1:]):
        return None
    site, rest = parts[1], parts[2:]
    match rest:
        case ["zones", zone, "state", node]:
            return Topic("zone_state", site, zone=zone, node=node)
        case ["nodes", node, "status"]:
            return Topic("node_status", site, node=node)
        case ["nodes", node, "info"]:
            return Topic("node_info", site, node=node)
        case ["nodes", node, "command"]:
            return Topic("node_command", site, node=node)
        case ["nodes", node, "log"]:
            return Topic("node_log", site, node=node)
        case ["nodes", node, "ota", "request"]:
            return Topic("node_ota_request", site, node=node)
        case ["nodes", node, "ota", "chunk"]:
            return Topic("node_ota_chunk", site, node=node)
        case ["robots", robot, "status"]:
            return Topic("robot_status", site, robot=robot)
        case ["robots", robot, "goal"]:
            return Topic("robot_goal", site, robot=robot)
        case ["operator", "blocks", block_id]:
            return Topic("operator_block", site, block_id=block_id)
        case ["sim", "world"]:
            return Topic("sim_world", site)
        case _:
            return None


def topic_matches(topic_filter: str, topic: str) -> bool:
    """MQTT 3.1.1 filter matching of a concrete topic name (`+` one level, `#` the rest, incl. the parent level).

    The one matcher of the project: buses deliver by it and the broker's ACL allows by it.
    """
    f_levels = topic_filter.split("/")
    t_levels = topic.split("/")
    for i, level in enumerate(f_levels):
        if level == "#":
            return True
        if i >= len(t_levels) or level not in ("+", t_levels[i]):
            return False
    return len(f_levels) == len(t_levels)
