"""What the operator sees of a site, kept from MQTT messages: zones, nodes, robots and operator blocks.

Pure state (no bus, no threads): `apply` takes one message with the time it arrived and says which entries
changed; `entry` and `snapshot` render entries as JSON-able dicts, with ages computed at the time asked. Times
are the site clock (Unix time in a real deployment), so a robot status's `t` gives its age directly.
"""

from __future__ import annotations

import collections
import logging
import math
from dataclasses import dataclass, field
from typing import Any, Literal

from wsnav.console.event_log import Event
from wsnav.schemas import topics
from wsnav.schemas.messages import (
    MAX_OPERATOR_PAYLOAD_BYTES,
    NodeInfo,
    NodeStatus,
    OperatorBlock,
    PayloadError,
    RobotStatus,
    ZoneState,
    is_yielding,
    parse_payload,
)
from wsnav.schemas.site import Site
from wsnav.zones.geometry import GridFrame
from wsnav.zones.zone_rule import ZoneRule

Kind = Literal["zone", "node", "robot", "block"]
Key = tuple[Kind, str]

TRAIL_S = 300.0
"""How much of each robot's way the console keeps (and the page draws)."""
TRAIL_STEP_M = 0.05
TRAIL_POINTS = 1500
"""At most this many points per trail (5 per second for TRAIL_S): a robot credential sending statuses as fast
as it can cannot grow the page's state without limit."""
DROP_LOG_INTERVAL_S = 10.0
"""At most one log line per drop reason in this many seconds; every drop is counted in `dropped`."""
log = logging.getLogger(__name__)


@dataclass
class NodeView:
    zone: str
    heartbeat_s: float
    state: str | None = None
    seq: int | None = None
    heard_at: float | None = None
    online: bool | None = None
    status_at: float | None = None
    info: dict[str, Any] | None = None
    info_at: float | None = None


@dataclass
class RobotView:
    status: RobotStatus | None = None
    heard_at: float | None = None
    trail: collections.deque[tuple[float, float, float]] = field(
        default_factory=lambda: collections.deque(maxlen=TRAIL_POINTS)
    )


@dataclass
class BlockView:
    block: OperatorBlock
    set_at: float


class SiteView:
    def __init__(self, site: Site) -> None:
        self.site = site
        spec = site.spec
        self.stale_after = spec.policy.stale_after_heartbeats
        self.zones = {z.id: z for z in spec.zones}
        self.nodes: dict[str, NodeView] = {n.id: NodeView(n.zone, spec.heartbeat_of(n)) for n in spec.nodes}
        self.zone_nodes: dict[str, list[str]] = {z: [] for z in self.zones}
        for n in spec.nodes:
            self.zone_nodes[n.zone].append(n.id)
        self.robots: dict[str, RobotView] = {r.id: RobotView() for r in spec.robots}
        self.blocks: dict[str, BlockView] = {}
        self.rule = ZoneRule(spec, GridFrame.of_grid(site.grid))
        """The robots' own zone layer, fed the same messages: a zone's state is what the robots make of it."""
        self.events: list[Event] = []
        """What happened (live messages only, never a broker's replay), for the event log; its reader empties it."""
        self.dropped: collections.Counter[str] = collections.Counter()
        self.last_drop: str | None = None
        self._logged_at: dict[str, float] = {}
        """reason -> when a drop of it was last logged (receipt time): one line per reason and interval."""
        self._unlogged: collections.Counter[str] = collections.Counter()

    # -- intake --------------------------------------------------------------------------------------------

    def apply(self, topic: str, payload: bytes, received_at: float, retained: bool = False) -> set[Key]:
        """Take one message in; the entries it changed (none for a message that is dropped, counted why).

        Never raises: whatever one message does (nested JSON, a zone the site lacks, a bug of ours), it is
        dropped, counted and logged, and the next message is read (no message may stop the console's intake).
        A `retained` message is one the broker replays on subscribing: it says what a node last said, not that
        the node spoke now, so it does not make the node "last heard" (its age comes from live messages only)."""
        try:
            return self._apply(topic, payload, received_at, retained)
        except PayloadError as exc:
            return self._drop("invalid", f"{topic}: {exc}", received_at)
        except Exception as exc:  # the intake boundary: one message must not stop the reader
            return self._drop("internal_error", f"{topic}: {type(exc).__name__}: {exc}"[:300], received_at)

    def _apply(self, topic: str, payload: bytes, received_at: float, retained: bool) -> set[Key]:
        parsed = topics.parse(topic)
        if parsed is None or parsed.site != self.site.name:
            return self._drop("wrong_topic", f"not a topic of site {self.site.name}: {topic}", received_at)
        if parsed.kind == "node_info" and parsed.node is not None:
            return self._node_info(parsed.node, payload, received_at)
        if parsed.kind == "zone_state" and parsed.node is not None:
            return self._zone_state(parsed.node, parse_payload(ZoneState, payload), received_at, retained)
        if parsed.kind == "node_status" and parsed.node is not None:
            return self._node_status(parsed.node, payload, received_at, retained)
        if parsed.kind == "robot_status" and parsed.robot is not None:
            status = parse_payload(RobotStatus, payload, max_bytes=MAX_OPERATOR_PAYLOAD_BYTES)
            return self._robot_status(parsed.robot, status, received_at, retained)
        if parsed.kind == "operator_block" and parsed.block_id is not None:
            return self._block(parsed.block_id, payload, received_at, retained)
        return set()

    def _event(self, at: float, kind: str, subject: str, text: str) -> None:
        self.events.append(Event(at, kind, subject, text))
        del self.events[:-1000]  # nobody reading: keep the newest

    def _drop(self, reason: str, why: str, at: float) -> set[Key]:
        """Count a dropped message by reason; log the first of a reason at once, then at most one line per
        reason every DROP_LOG_INTERVAL_S (with how many went unlogged), so a flood cannot flood the log."""
        self.dropped[reason] += 1
        self.last_drop = why
        since = self._logged_at.get(reason)
        if since is not None and at - since < DROP_LOG_INTERVAL_S:
            self._unlogged[reason] += 1
            return set()
        unlogged = self._unlogged.pop(reason, 0)
        more = (
            f" (and {unlogged} more of this kind in the last {at - since:.0f} s)"
            if unlogged and since
            else ""
        )
        self._logged_at[reason] = at
        log.warning("dropped (%s) %s%s", reason, why, more)
        return set()

    def _zone_state(self, node_id: str, msg: ZoneState, at: float, retained: bool) -> set[Key]:
        node = self.nodes.get(node_id)
        if node is None or msg.node != node_id or msg.zone != node.zone:
            return self._drop("unknown_node", f"zone state of unknown node or wrong zone: {node_id}", at)
        node.state, node.seq = msg.state, msg.seq
        if not retained:
            node.heard_at = at
        self.rule.on_zone_state(msg, at)  # the robots' rule, fed as the robots' intake feeds it
        if node.online is None and not retained:
            node.online = True  # a node that speaks is connected, even before its retained birth arrives
        return {("node", node_id), ("zone", node.zone)}

    def _node_status(self, node_id: str, payload: bytes, at: float, retained: bool) -> set[Key]:
        node = self.nodes.get(node_id)
        if node is None:
            return self._drop("unknown_node", f"status of unknown node: {node_id}", at)
        msg = parse_payload(NodeStatus, payload)
        if msg.node != node_id:
            return self._drop("mismatch", f"status of {msg.node} on {node_id}'s topic", at)
        online = msg.status == "online"
        if not retained and node.online is not None and online != node.online:
            self._event(at, f"node_{msg.status}", node_id, f"node {node_id} ({node.zone}) {msg.status}")
        node.online, node.status_at = online, at
        self.rule.on_node_status(msg, at)
        return {("node", node_id), ("zone", node.zone)}

    def _node_info(self, node_id: str, payload: bytes, at: float) -> set[Key]:
        """A node's diagnostics (schemas.messages.NodeInfo), shown field by field; an empty payload clears them."""
        node = self.nodes.get(node_id)
        if node is None:
            return self._drop("unknown_node", f"info of unknown node: {node_id}", at)
        if not payload:
            node.info, node.info_at = None, None
            return {("node", node_id)}
        msg = parse_payload(NodeInfo, payload)
        if msg.node != node_id:
            return self._drop("mismatch", f"info of {msg.node} on {node_id}'s topic", at)
        node.info, node.info_at = msg.model_dump(exclude={"v", "node"}, exclude_none=True), at
        return {("node", node_id)}

    def _robot_status(self, robot_id: str, msg: RobotStatus, at: float, retained: bool) -> set[Key]:
        robot = self.robots.setdefault(robot_id, RobotView())
        if msg.robot != robot_id:
            return self._drop("mismatch", f"status of {msg.robot} on {robot_id}'s topic", at)
        before = robot.status.state if robot.status is not None else None
        before_reason = robot.status.reason if robot.status is not None else None
        # a new goal cancelled again for another reason (the operator's cancel, then a goal in a blocked zone) is
        # another event, though the state word did not change
        again = msg.state == before == "cancelled" and msg.reason != before_reason
        # a robot that gave way to another and then finds no way on (or the reverse) waits anew, for another cause
        again = again or (
            msg.state == before == "waiting"
            and is_yielding(msg.state, msg.reason) != is_yielding(before, before_reason)
        )
        if (
            not retained
            and (msg.state != before or again)
            and msg.state in ("waiting", "arrived", "cancelled")
        ):
            why = f": {msg.reason}" if msg.reason else ""
            self._event(at, f"robot_{msg.state}", robot_id, f"robot {robot_id} {msg.state}{why}")
        robot.status, robot.heard_at = msg, at
        x, y, _ = msg.pose
        trail = robot.trail  # by the console's own receipt time: a status's `t` is the sender's word
        if not trail or math.hypot(x - trail[-1][1], y - trail[-1][2]) >= TRAIL_STEP_M:
            trail.append((at, x, y))
        while trail and trail[0][0] < at - TRAIL_S:
            trail.popleft()
        return {("robot", robot_id)}

    def _block(self, block_id: str, payload: bytes, at: float, retained: bool = False) -> set[Key]:
        msg = parse_payload(OperatorBlock, payload, max_bytes=MAX_OPERATOR_PAYLOAD_BYTES) if payload else None
        if msg is not None and msg.zone is not None and msg.zone not in self.zones:
            # the robots' intake drops it too (zones.intake): a zone removed from the site, or a typo
            return self._drop(
                "unknown_zone", f"operator block {block_id} on zone {msg.zone!r}, not in the site", at
            )
        before = self.blocks.pop(block_id, None)
        keys: set[Key] = {("block", block_id)}
        if before is not None and before.block.zone is not None:
            keys.add(("zone", before.block.zone))
        if msg is not None:
            self.blocks[block_id] = BlockView(msg, at)
            if msg.zone is not None:
                keys.add(("zone", msg.zone))
            if not retained and before is not None and _extended(before.block, msg):
                left = "" if msg.expires_at is None else f", {msg.expires_at - at:.0f} s left"
                self._event(at, "block_extended", block_id, f"block {block_id} extended: {_where(msg)}{left}")
            elif not retained and (before is None or before.block != msg):
                self._event(at, "block_set", block_id, f"block {block_id} set: {_where(msg)}")
        elif before is not None and not retained:
            self._event(at, "block_lifted", block_id, f"block {block_id} lifted: {_where(before.block)}")
        self.rule.on_operator_block(block_id, msg, at)
        return keys

    # -- time ----------------------------------------------------------------------------------------------

    def expire(self, now: float) -> set[Key]:
        """Blocks past their expiry leave the view (the robots drop them by the same rule)."""
        keys: set[Key] = set()
        for block_id, view in list(self.blocks.items()):
            if view.block.expires_at is not None and now >= view.block.expires_at:
                del self.blocks[block_id]
                keys.add(("block", block_id))
                self._event(now, "block_expired", block_id, f"block {block_id} expired: {_where(view.block)}")
                if view.block.zone is not None:
                    keys.add(("zone", view.block.zone))
        return keys

    def node_fresh(self, node: NodeView, now: float) -> bool:
        return node.heard_at is not None and now - node.heard_at <= self.stale_after * node.heartbeat_s

    def zone_state(self, zone_id: str, now: float) -> str:
        """What the robots make of the zone (blocked, caution, clear, unknown), by the site's policy: fusion
        of its nodes, and what a stale node counts as. `stale_nodes` in the entry says who is silent."""
        self.rule.refresh(now)
        return self.rule.zone_word(zone_id)

    def stale_nodes(self, zone_id: str, now: float) -> list[str]:
        self.rule.refresh(now)
        return self.rule.stale_nodes(zone_id)

    def zone_states(self, now: float) -> dict[str, str]:
        return {z: self.zone_state(z, now) for z in self.zones}

    def zone_looks(self, now: float) -> dict[str, tuple[str, tuple[str, ...]]]:
        """Per zone what the page draws from the rule: its word and its stale nodes (under `stale: keep` a
        silent node's zone keeps its word but is drawn stale: the page must follow that change too)."""
        self.rule.refresh(now)
        return {z: (self.rule.zone_word(z), tuple(self.rule.stale_nodes(z))) for z in self.zones}

    def zone_look(self, zone_id: str, now: float) -> tuple[str, tuple[str, ...], tuple[str, ...]]:
        """One zone's look: word, stale nodes and operator blocks on it."""
        self.rule.refresh(now)
        blocks = tuple(sorted(b for b, v in self.blocks.items() if v.block.zone == zone_id))
        return self.rule.zone_word(zone_id), tuple(self.rule.stale_nodes(zone_id)), blocks

    # -- rendering -----------------------------------------------------------------------------------------

    def entry(self, key: Key, now: float) -> dict[str, Any] | None:
        """One entry as the page and `--json` show it; None once it is gone (a lifted block)."""
        kind, ident = key
        if kind == "zone":
            blocks = sorted(b for b, v in self.blocks.items() if v.block.zone == ident)
            return {
                "id": ident,
                "state": self.zone_state(ident, now),
                "stale_nodes": self.stale_nodes(ident, now),
                "nodes": self.zone_nodes[ident],
                "operator_blocks": blocks,
            }
        if kind == "node":
            n = self.nodes[ident]
            return {
                "id": ident,
                "zone": n.zone,
                "state": n.state,
                "seq": n.seq,
                "online": n.online,
                "heard_at": n.heard_at,
                "age_s": None if n.heard_at is None else round(now - n.heard_at, 1),
                "fresh": self.node_fresh(n, now),
                "info": n.info,
            }
        if kind == "robot":
            r = self.robots.get(ident)
            if r is None or r.status is None:
                return {"id": ident, "state": None}
            s = r.status
            return {
                "id": ident,
                **s.model_dump(exclude={"v", "robot"}),
                "heard_at": r.heard_at,
                "age_s": round(now - (s.t if s.t is not None else r.heard_at or now), 1),
            }
        view = self.blocks.get(ident)
        if view is None:
            return None
        b = view.block
        return {
            "id": ident,
            "zone": b.zone,
            "polygon": b.polygon,
            "expires_at": b.expires_at,
            "left_s": None if b.expires_at is None else max(0.0, round(b.expires_at - now, 1)),
            "reason": b.reason,
        }

    def robot_trail(self, robot_id: str) -> list[tuple[float, float, float]]:
        robot = self.robots.get(robot_id)
        return list(robot.trail) if robot is not None else []

    def snapshot(self, now: float) -> dict[str, Any]:
        """Everything, as `GET /api/state` returns it."""
        robots = []
        for r in sorted(self.robots):
            entry = self.entry(("robot", r), now) or {"id": r}
            entry["trail"] = [[round(x, 2), round(y, 2)] for _, x, y in self.robot_trail(r)]
            robots.append(entry)
        return {
            "site": self.site.name,
            "now": now,
            "zones": [self.entry(("zone", z), now) for z in self.zones],
            "nodes": [self.entry(("node", n), now) for n in self.nodes],
            "robots": robots,
            "blocks": [self.entry(("block", b), now) for b in sorted(self.blocks)],
        }


def _extended(before: OperatorBlock, after: OperatorBlock) -> bool:
    """The same block with a later expiry (`wsnav block --extend`, the page's Extend)."""
    if before.expires_at is None or after.expires_at is None or after.expires_at <= before.expires_at:
        return False
    return before.model_copy(update={"expires_at": after.expires_at}) == after


def _where(block: OperatorBlock) -> str:
    where = (
        f"zone {block.zone}" if block.zone is not None else f"a polygon of {len(block.polygon or [])} corners"
    )
    return where + (f" ({block.reason})" if block.reason else "")
