"""MQTT intake of the zone layer: every inbound message validated, and dropped and counted when it is bad.

Malformed JSON, wrong types, unknown zones or nodes, a node writing a zone it does not watch, a payload that
disagrees with its topic, an old `seq`, an oversized payload: each is dropped with a reason in `dropped` and a
one-line log, never reaches the zone layer, and never raises (docs/architecture.md, "The message contract"). The log is
rate-limited per reason so a flood of garbage cannot flood the log (wsnav.runtime.drop_log, the rule every reader
shares); `dropped` counts every one.

The `seq` rule, matching the firmware (firmware/device/node_logic.py): a node's seq increases with every state
it publishes and starts from a random base when it boots, and every (re)connect publishes the birth `online`
before the state. So a state is accepted when it is the first state after the node's birth (a reboot restarts
seq), or when its seq lies ahead of the last accepted one by at least 1 and at most MAX_SEQ_STEP, counting
across the counter's wrap from 2**30 - 1 to 0. Replays cannot be cycled: going round the seq space takes more
than a thousand captured states of one boot spread over all of it (2**30 publications, centuries of heartbeats),
where the old rule (any drop of more than 2**29 was a wrap) let two captured states alternate forever.

A QoS 1 redelivery (the broker resending a state whose PUBACK it missed) repeats the last accepted state byte
for byte: it is counted in `duplicates` and ignored, neither dropped nor logged (under load a broker resends
hundreds a second). The same seq with other content is still an old seq.

With a `LastKnownZones` (zones/last_known.py) the intake remembers every accepted state on disk and starts from
what it knew (`restore`): a retained copy of a state it already holds is such a duplicate, and a retained birth of
a node it knows brings no news of when the node last spoke, so neither makes a silent node look fresh.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from typing import TypeVar

from pydantic import ValidationError

from wsnav.runtime.bus import Message
from wsnav.runtime.drop_log import DROP_LOG_INTERVAL, DropLog
from wsnav.schemas import topics
from wsnav.schemas.messages import (
    MAX_OPERATOR_PAYLOAD_BYTES,
    MAX_PAYLOAD_BYTES,
    NodeStatus,
    OperatorBlock,
    PayloadError,
    ZoneState,
    refuse_duplicate_keys,
)
from wsnav.schemas.site_file import SiteFile
from wsnav.zones.last_known import LastKnownZones
from wsnav.zones.zone_rule import ZoneRule

log = logging.getLogger(__name__)

M = TypeVar("M", ZoneState, NodeStatus, OperatorBlock)

SEQ_SPACE = 2**30
"""The firmware's seq runs 0 .. 2**30 - 1 and wraps to 0 (SEQ_MAX in firmware/device/payloads.py)."""
MAX_SEQ_STEP = 2**20
"""How far ahead a new state's seq may be: a year of 30 s heartbeats missed by the agent, far below SEQ_SPACE."""


def seq_is_newer(seq: int, last: int) -> bool:
    """`seq` follows `last` on the firmware's wrapping counter (by 1 to MAX_SEQ_STEP)."""
    return 0 < (seq - last) % SEQ_SPACE <= MAX_SEQ_STEP


class ZoneIntake:
    """Validates zone states, node statuses and operator blocks of one site and feeds them to a ZoneRule."""

    def __init__(
        self,
        spec: SiteFile,
        layer: ZoneRule,
        drop_log_interval: float = DROP_LOG_INTERVAL,
        memory: LastKnownZones | None = None,
    ) -> None:
        self.spec = spec
        self.layer = layer
        self.memory = memory
        """The last known states on disk, or None to keep nothing across restarts."""
        self._zones = {z.id for z in spec.zones}
        self._watches = {n.id: n.zone for n in spec.nodes}
        self._last_seq: dict[str, int] = {}
        self._last_payload: dict[str, bytes] = {}
        """Per node: the last accepted state as it came, to tell a QoS 1 redelivery from a replay."""
        self.duplicates = 0
        self._reborn: set[str] = set()
        self._drops = DropLog(log, "zone intake", "zone messages", drop_log_interval)
        self.dropped: Counter[str] = self._drops.counts
        self.accepted = 0
        self.cleared = 0
        """Empty retained messages on a node's topics: the broker forgot its word (`wsnav broker revoke`); the
        layer keeps what it knew until the stale policy says otherwise."""

    def restore(self, now: float) -> bool:
        """Start from the last known states (if kept), each aged by the time since it was heard; True if zone
        costs changed. Call once, before the first message."""
        if self.memory is None:
            return False
        changed = False
        for node, known in self.memory.known.items():
            age = self.memory.age_s(node) or 0.0
            self._last_seq[node] = known.seq
            self._last_payload[node] = known.payload
            changed |= self.layer.restore(node, known.state, now - age, known.online, now)
        return changed

    def subscriptions(self) -> list[str]:
        """Topic filters to subscribe: every zone state, node status and operator block of the site."""
        site = self.spec.name
        return [
            topics.all_zone_states(site),
            topics.all_node_statuses(site),
            topics.all_operator_blocks(site),
        ]

    def handle(self, message: Message) -> bool:
        """Validate and apply one message; True if effective zone costs changed. Never raises."""
        self._drops.flush(message.received_at)
        try:
            return self._handle(message)
        except Exception as exc:  # a bug here must not stop the robot; count it and keep going
            if self._drops.logs_at_once("internal_error"):  # its traceback as rate-limited as its drops
                log.exception("zone intake: %s: internal error", message.topic)
            return self._drop("internal_error", message, f"{type(exc).__name__}: {exc}")

    def _handle(self, message: Message) -> bool:
        topic = topics.parse(message.topic)
        if topic is None:
            return self._drop("unknown_topic", message, "not a contract topic")
        if topic.site != self.spec.name:
            return self._drop("wrong_site", message, f"site {topic.site!r} is not {self.spec.name!r}")
        match topic.kind:
            case "zone_state":
                assert topic.zone is not None and topic.node is not None
                return self._zone_state(message, topic.zone, topic.node)
            case "node_status":
                assert topic.node is not None
                return self._node_status(message, topic.node)
            case "operator_block":
                assert topic.block_id is not None
                return self._operator_block(message, topic.block_id)
            case _:
                return self._drop("unknown_topic", message, f"not a zone-layer topic ({topic.kind})")

    def _zone_state(self, message: Message, zone: str, node: str) -> bool:
        if zone not in self._zones:
            return self._drop("unknown_zone", message, f"no zone {zone!r} in the site")
        if node not in self._watches:
            return self._drop("unknown_node", message, f"no node {node!r} in the site")
        if self._watches[node] != zone:
            return self._drop(
                "wrong_node", message, f"node {node!r} watches {self._watches[node]!r}, not {zone!r}"
            )
        if not message.payload:
            self.cleared += 1
            return False
        msg = self._parse(ZoneState, message, MAX_PAYLOAD_BYTES)
        if msg is None:
            return False
        if msg.zone != zone or msg.node != node:
            return self._drop("mismatch", message, f"payload says zone {msg.zone!r} node {msg.node!r}")
        last = self._last_seq.get(node)
        if last is not None and msg.seq == last and message.payload == self._last_payload.get(node):
            self.duplicates += 1  # a redelivery, or the retained copy of a state already known: no news
            return False
        if last is not None and node not in self._reborn and not seq_is_newer(msg.seq, last):
            return self._drop("old_seq", message, f"seq {msg.seq} after {last}")
        self._last_seq[node] = msg.seq
        self._last_payload[node] = bytes(message.payload)
        self._reborn.discard(node)
        self.accepted += 1
        if self.memory is not None:
            self.memory.accepted(node, msg.state, msg.seq, message.payload)
        return self.layer.on_zone_state(msg, message.received_at)

    def _node_status(self, message: Message, node: str) -> bool:
        if node not in self._watches:
            return self._drop("unknown_node", message, f"no node {node!r} in the site")
        if not message.payload:
            self.cleared += 1
            return False
        msg = self._parse(NodeStatus, message, MAX_PAYLOAD_BYTES)
        if msg is None:
            return False
        if msg.node != node:
            return self._drop("mismatch", message, f"payload says node {msg.node!r}")
        if msg.status == "online":
            self._reborn.add(node)
        self.accepted += 1
        received_at = message.received_at
        age = self.memory.age_s(node) if self.memory is not None else None
        if message.retain and age is not None and msg.status == "online":
            received_at -= (
                age  # a stored birth of a node known here: it says nothing of when the node last spoke
            )
        elif self.memory is not None:
            self.memory.status(node, msg.status == "online")
        return self.layer.on_node_status(msg, received_at)

    def _operator_block(self, message: Message, block_id: str) -> bool:
        if not message.payload:
            self.accepted += 1
            return self.layer.on_operator_block(block_id, None, message.received_at)
        msg = self._parse(OperatorBlock, message, MAX_OPERATOR_PAYLOAD_BYTES)
        if msg is None:
            return False
        if msg.zone is not None and msg.zone not in self._zones:
            return self._drop("unknown_zone", message, f"no zone {msg.zone!r} in the site")
        self.accepted += 1
        return self.layer.on_operator_block(block_id, msg, message.received_at)

    def _parse(self, model: type[M], message: Message, max_bytes: int) -> M | None:
        payload = message.payload
        if len(payload) > max_bytes:
            self._drop("oversized", message, f"{len(payload)} bytes exceed {max_bytes}")
            return None
        try:
            json.loads(payload, object_pairs_hook=refuse_duplicate_keys)
        except PayloadError as exc:  # one key twice: two parsers could read two different messages
            self._drop("malformed", message, str(exc))
            return None
        except (ValueError, UnicodeDecodeError):
            self._drop("malformed", message, "not JSON")
            return None
        try:
            # strict: a node that sends "seq": "9" or "state": 1 has a bug worth seeing, not a value to coerce
            return model.model_validate_json(payload, strict=True)
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first.get("loc", ())) or "payload"
            self._drop("invalid", message, f"{model.__name__}: {where}: {first.get('msg', 'invalid')}")
            return None

    def _drop(self, reason: str, message: Message, detail: str) -> bool:
        self._drops.drop(reason, message.received_at, message.topic, detail)
        return False
