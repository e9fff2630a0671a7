"""What an operator may ask of the site, checked against it and turned into contract messages.

Shared by the web page's API and the terminal commands, so both refuse the same things with the same words.
"""

from __future__ import annotations

import re
import secrets
from dataclasses import dataclass

from pydantic import ValidationError

from wsnav.schemas import topics
from wsnav.schemas.goal_check import GoalRefused, goal_target
from wsnav.schemas.ids import ID_PATTERN
from wsnav.schemas.messages import (
    MAX_COMMAND_ID,
    MAX_HEARTBEAT_S,
    NodeCommand,
    NodeCommandName,
    OperatorBlock,
    RobotGoal,
)
from wsnav.schemas.site import Site

MAX_BLOCK_S = 7 * 24 * 3600.0
_ID = re.compile(ID_PATTERN)
_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([smhd]?)\s*$")
_UNIT_S = {"": 1.0, "s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}


class CommandError(ValueError):
    """A request that is refused: one line saying why."""


@dataclass(frozen=True)
class Publication:
    topic: str
    payload: bytes
    retain: bool


def parse_duration(text: str) -> float:
    """`90`, `90s`, `10m`, `2h`, `1d` -> seconds."""
    match = _DURATION.match(text)
    if not match:
        raise CommandError(f"not a duration: {text!r} (e.g. 90s, 10m, 2h)")
    return float(match.group(1)) * _UNIT_S[match.group(2)]


def new_block_id() -> str:
    return f"op-{secrets.token_hex(4)}"


def block(
    site: Site,
    *,
    now: float,
    duration_s: float | None,
    zone: str | None = None,
    polygon: list[tuple[float, float]] | None = None,
    reason: str | None = None,
    block_id: str | None = None,
) -> tuple[str, Publication]:
    """A retained operator block on a zone or a polygon for `duration_s` (None: until lifted)."""
    block_id = block_id or new_block_id()
    if not _ID.match(block_id):
        raise CommandError(f"not a valid block id: {block_id!r}")
    if (zone is None) == (polygon is None):
        raise CommandError("give a zone or a polygon (not both)")
    if zone is not None and zone not in {z.id for z in site.spec.zones}:
        raise CommandError(
            f"unknown zone {zone!r} (site {site.name} has {_names(z.id for z in site.spec.zones)})"
        )
    if polygon is not None:
        x0, y0, x1, y1 = site.grid.bounds
        outside = [p for p in polygon if not (x0 <= p[0] <= x1 and y0 <= p[1] <= y1)]
        if outside:
            x, y = outside[0]
            raise CommandError(
                f"polygon vertex [{x:g}, {y:g}] lies outside the map (x {x0:g}..{x1:g}, y {y0:g}..{y1:g})"
            )
    if duration_s is not None and not 0 < duration_s <= MAX_BLOCK_S:
        raise CommandError(
            f"a block lasts more than 0 s and at most {MAX_BLOCK_S / 86400:g} days, not {duration_s:g} s"
        )
    try:
        msg = OperatorBlock(
            zone=zone,
            polygon=polygon,
            expires_at=None if duration_s is None else round(now + duration_s, 3),
            reason=reason or None,
        )
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "block"
        raise CommandError(f"{where}: {str(first['msg']).removeprefix('Value error, ')}") from None
    return block_id, Publication(topics.operator_block(site.name, block_id), msg.to_payload(), True)


def extend(site: Site, block_id: str, current: OperatorBlock, *, now: float, by_s: float) -> Publication:
    """The same block (same id, area and reason) with its expiry `by_s` later: published over the retained one, so
    a robot holds the block throughout (lifting and setting again would clear the area in between)."""
    if not _ID.match(block_id):
        raise CommandError(f"not a valid block id: {block_id!r}")
    if current.expires_at is None:
        raise CommandError(f"block {block_id} lasts until lifted: there is nothing to extend")
    if not 0 < by_s <= MAX_BLOCK_S:
        raise CommandError(
            f"extend by more than 0 s and at most {MAX_BLOCK_S / 86400:g} days, not {by_s:g} s"
        )
    expires_at = round(max(current.expires_at, now) + by_s, 3)
    if expires_at - now > MAX_BLOCK_S:
        raise CommandError(
            f"a block lasts at most {MAX_BLOCK_S / 86400:g} days from now; this one would last "
            f"{(expires_at - now) / 86400:.1f}"
        )
    msg = current.model_copy(update={"expires_at": expires_at})
    return Publication(topics.operator_block(site.name, block_id), msg.to_payload(), True)


def unblock(site: Site, block_id: str) -> Publication:
    """Lifting is an empty retained message: the broker forgets the block, every robot drops it."""
    if not _ID.match(block_id):
        raise CommandError(f"not a valid block id: {block_id!r}")
    return Publication(topics.operator_block(site.name, block_id), b"", True)


def _robot(site: Site, robot: str) -> None:
    if robot not in {r.id for r in site.spec.robots}:
        raise CommandError(
            f"unknown robot {robot!r} (site {site.name} has {_names(r.id for r in site.spec.robots)})"
        )


def goal(site: Site, robot: str, target: str | tuple[float, float, float]) -> Publication:
    """A named point of the site, or a pose [x, y, yaw] on free space of the map (schemas.goal_check)."""
    _robot(site, robot)
    try:
        goal_target(site, target)
    except GoalRefused as refused:
        raise CommandError(str(refused)) from None
    if isinstance(target, str):
        msg = RobotGoal(goal=target)
    else:
        x, y, yaw = target
        msg = RobotGoal(goal=(round(x, 3), round(y, 3), round(yaw, 3)))
    return Publication(topics.robot_goal(site.name, robot), msg.to_payload(), False)


def cancel(site: Site, robot: str) -> Publication:
    _robot(site, robot)
    return Publication(topics.robot_goal(site.name, robot), RobotGoal(cancel=True).to_payload(), False)


def clear_status(site: Site, robot: str) -> Publication:
    """An empty retained message on the robot's status topic: the broker forgets the status it keeps, so a
    robot taken out of service (or a forged status) no longer greets every agent and console that starts."""
    _robot(site, robot)
    return Publication(topics.robot_status(site.name, robot), b"", True)


def node_command(
    site: Site,
    node: str,
    command: NodeCommandName,
    heartbeat_s: float | None = None,
    manifest: str | None = None,
) -> Publication:
    """A command to one node of the site (not retained: a node ignores retained ones), with a fresh random id
    so the node applies it once even if QoS 1 delivers it twice. `manifest`: an update's (`wsnav firmware ota`)."""
    if node not in {n.id for n in site.spec.nodes}:
        raise CommandError(
            f"unknown node {node!r} (site {site.name} has {_names(n.id for n in site.spec.nodes)})"
        )
    if command == "set_heartbeat" and (heartbeat_s is None or not 0 < heartbeat_s <= MAX_HEARTBEAT_S):
        raise CommandError(f"a heartbeat is more than 0 s and at most {MAX_HEARTBEAT_S} s, not {heartbeat_s}")
    msg = NodeCommand(
        id=secrets.randbelow(MAX_COMMAND_ID) + 1, command=command, heartbeat_s=heartbeat_s, manifest=manifest
    )
    return Publication(topics.node_command(site.name, node), msg.to_payload(), False)


def _names(ids: object) -> str:
    names = sorted(ids)  # type: ignore[call-overload]
    return ", ".join(names[:12]) + (" ..." if len(names) > 12 else "") if names else "none"
