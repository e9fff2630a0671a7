"""The console's link to the site: one operator MQTT connection feeding a SiteView, changes pushed to pages.

A thread owns the bus and the view (the view is only touched under `lock`). Changes are gathered for
`BATCH_S` and sent to every open page as one event of the changed entries, so a thousand nodes reporting at
once cost one event, not a thousand (heartbeats coalesce; a node's state change is sent before a later message
of the same batch could undo it); once a second the clock alone is checked (a silent node goes stale, a
block expires).
"""

from __future__ import annotations

import asyncio
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Callable
from typing import Any

from wsnav.console.alerts import AlertBoard
from wsnav.console.block_store import BlockStore
from wsnav.console.event_log import EventLog
from wsnav.console.site_view import Key, SiteView
from wsnav.runtime.bus import Bus
from wsnav.runtime.clock import Clock
from wsnav.schemas import topics

log = logging.getLogger(__name__)

BATCH_S = 0.05
TICK_S = 1.0
REPLAY_S = 3.0
"""After a reconnect, how long the broker's retained replay is awaited before an operator block it did not replay
is taken as lost (a broker restarted without its store, a full disk) and published again."""
MAX_PAGE_QUEUE = 200
"""A page that falls this far behind is sent a fresh snapshot instead of the backlog."""


def subscriptions(site: str) -> list[str]:
    return [
        topics.all_zone_states(site),
        topics.all_node_statuses(site),
        topics.all_node_infos(site),
        topics.all_robot_statuses(site),
        topics.all_operator_blocks(site),
    ]


class PageFeed:
    """One open page's queue of events (JSON text), filled from the bus thread."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.queue: asyncio.Queue[str] = asyncio.Queue()
        self.resync = False

    def push(self, text: str) -> None:
        """Called on the event loop."""
        if self.queue.qsize() >= MAX_PAGE_QUEUE:
            self.resync = True
            return
        self.queue.put_nowait(text)


class LiveState:
    def __init__(
        self,
        view: SiteView,
        bus: Bus,
        clock: Clock,
        events: EventLog | None = None,
        alerts: AlertBoard | None = None,
        blocks: BlockStore | None = None,
    ) -> None:
        self.view = view
        self.bus = bus
        self.clock = clock
        self.lock = threading.Lock()
        self._feeds: set[PageFeed] = set()
        self._feeds_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="console-mqtt", daemon=True)
        self.connected = bus.connected
        self.events = events
        self.alerts = alerts if alerts is not None else AlertBoard()
        """Node offline, robot stuck or given up, block expiring: under `lock`, like the view."""
        self._sent: dict[Key, object] = {}
        """What the pages were last sent of each zone and node (its look, without times)."""
        self.failed: str | None = None
        """Why the bus thread stopped, if it did: the page then says the console is blind."""
        self.messages = 0
        self.blocks = blocks
        if blocks is not None:  # the blocks in force when the console last ran: shown at once, checked below
            now = clock.now()
            for block_id, payload in self._stored_blocks(blocks, now).items():
                view.apply(topics.operator_block(view.site.name, block_id), payload, now, retained=True)
        for flt in subscriptions(view.site.name):
            bus.subscribe(flt)

    @staticmethod
    def _stored_blocks(blocks: BlockStore, now: float) -> dict[str, bytes]:
        try:
            return blocks.in_force(now)
        except sqlite3.Error as exc:
            log.warning("operator blocks not read from the store: %s", exc)
            return {}

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

    # -- pages ---------------------------------------------------------------------------------------------

    @property
    def link_up(self) -> bool:
        """The broker is connected and the thread that reads it still runs: what the page's banner shows."""
        started = self._thread.ident is not None
        return self.connected and self.failed is None and (not started or self._thread.is_alive())

    def snapshot(self) -> dict[str, Any]:
        with self.lock:
            snap = self.view.snapshot(self.clock.now())
            snap["alerts"] = self.alerts.entries()
        snap["broker_connected"] = self.link_up
        snap["events"] = self.recent_events()
        if self.failed is not None:
            snap["link_error"] = self.failed
        return snap

    def open_feed(self, loop: asyncio.AbstractEventLoop) -> PageFeed:
        feed = PageFeed(loop)
        with self._feeds_lock:
            self._feeds.add(feed)
        return feed

    def close_feed(self, feed: PageFeed) -> None:
        with self._feeds_lock:
            self._feeds.discard(feed)

    def _broadcast(self, event: dict[str, Any]) -> None:
        text = json.dumps(event, separators=(",", ":"))
        with self._feeds_lock:
            feeds = list(self._feeds)
        for feed in feeds:
            try:
                feed.loop.call_soon_threadsafe(feed.push, text)
            except RuntimeError:  # the page's loop is closed: the server is stopping
                self.close_feed(feed)

    # -- the bus thread ------------------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            self._loop()
        except (
            BaseException
        ) as exc:  # a bug of ours: say so on every page at once rather than freeze silently
            self.failed = f"the console stopped reading the broker ({type(exc).__name__}: {exc}); restart it"
            log.exception("console-mqtt: %s", self.failed)
            self._broadcast({"type": "link", "broker_connected": False, "link_error": self.failed})

    def _loop(self) -> None:
        dirty: set[Key] = set()
        zone_states: dict[str, tuple[str, tuple[str, ...]]] = {}
        fresh: dict[str, bool] = {}
        next_tick = 0.0
        flush_at: float | None = None
        replayed: set[str] = set()
        # at start too: a block kept from the last run that the broker does not replay was lost by it
        reconcile_at: float | None = time.monotonic() + REPLAY_S
        while not self._stop.is_set():
            if flush_at is None:
                self.bus.wait(BATCH_S)  # idle: wake on the first message
            else:  # a batch is open: let it fill, then take it whole (one wake-up per batch, not per message)
                self._stop.wait(max(0.0, flush_at - time.monotonic()))
            messages = self.bus.poll()
            changed: set[Key] = set()
            for msg in messages:
                parsed = topics.parse(msg.topic)
                if parsed is not None and parsed.kind == "zone_state" and self._unsent_change(parsed.node):
                    # this node's last change has not reached the pages yet and this message may undo it within
                    # the batch: send it first (heartbeats are coalesced, state changes never)
                    self._flush(dirty | changed)
                    dirty, changed, flush_at = set(), set(), None
                with self.lock:
                    changed |= self.view.apply(msg.topic, msg.payload, msg.received_at, msg.retain)
                if msg.retain and msg.payload and parsed is not None and parsed.block_id:
                    replayed.add(parsed.block_id)
            dirty |= changed
            self._keep_blocks(changed)
            self.messages += len(messages)
            mono = time.monotonic()
            if messages and flush_at is None:
                flush_at = mono + BATCH_S
            if self.bus.connected != self.connected:
                self.connected = self.bus.connected
                self._broadcast({"type": "link", "broker_connected": self.connected})
                if self.connected:  # back: see which of our blocks the broker still holds
                    replayed, reconcile_at = set(), mono + REPLAY_S
            if reconcile_at is not None and mono >= reconcile_at and self.bus.connected:
                reconcile_at = None
                self._republish_lost(replayed)
            if mono >= next_tick:
                next_tick = mono + TICK_S
                with self.lock:
                    now = self.clock.now()
                    expired = self.view.expire(now)
                    self.alerts.on_clock(self.view, now)
                dirty |= expired
                self._forget_expired(expired)
                self._keep_blocks(expired)
                with self.lock:
                    states = self.view.zone_looks(now)
                    now_fresh = {n: self.view.node_fresh(v, now) for n, v in self.view.nodes.items()}
                dirty |= {("zone", z) for z, s in states.items() if zone_states.get(z) != s}
                dirty |= {("node", n) for n, f in now_fresh.items() if fresh.get(n) != f}
                zone_states, fresh = states, now_fresh
                flush_at = mono
            if (self.view.events or self.alerts.changed) and flush_at is None:
                flush_at = mono  # an acknowledgement from a page, too, reaches the other pages at once
            if (
                (dirty or self.view.events or self.alerts.changed)
                and flush_at is not None
                and mono >= flush_at
            ):
                self._flush(dirty)
                dirty = set()
                flush_at = None

    def _republish_lost(self, replayed: set[str]) -> None:
        """The operator's blocks are operator intent: one the broker did not replay after a reconnect, or after
        this console started with it in its store, was lost by the broker (restarted without its store, a full
        disk) and is published again, retained, as it was. A block lifted while this console was cut off or
        down cannot be told from a lost one: it comes back, on the safe side."""
        with self.lock:
            now = self.clock.now()
            lost = [
                (block_id, view.block)
                for block_id, view in self.view.blocks.items()
                if block_id not in replayed and (view.block.expires_at is None or view.block.expires_at > now)
            ]
        for block_id, block in lost:
            log.warning("operator block %s was lost by the broker: published again", block_id)
            self.bus.publish(
                topics.operator_block(self.view.site.name, block_id), block.to_payload(), qos=1, retain=True
            )

    def _unsent_change(self, node_id: str | None) -> bool:
        """The node's state differs from what the pages were last sent of it (a change waiting for the flush)."""
        node = self.view.nodes.get(node_id) if node_id is not None else None
        sent = self._sent.get(("node", node_id)) if node_id is not None else None
        return node is not None and isinstance(sent, tuple) and sent[0] != node.state

    def _keep_blocks(self, keys: set[Key]) -> None:
        """The store follows the view's blocks: set or changed ones are kept, lifted or expired ones forgotten."""
        ids = [ident for kind, ident in keys if kind == "block"]
        if self.blocks is None or not ids:
            return
        with self.lock:
            now = {i: self.view.blocks[i].block for i in ids if i in self.view.blocks}
        try:
            for block_id in ids:
                block = now.get(block_id)
                if block is None:
                    self.blocks.forget(block_id)
                else:
                    self.blocks.keep(block_id, block.to_payload(), block.expires_at)
        except sqlite3.Error as exc:  # a full disk must not stop the console's intake
            log.warning("operator blocks not kept on disk: %s", exc)

    def _forget_expired(self, expired: set[Key]) -> None:
        """An expired block is cleared from the broker's retained store too, so it is not replayed forever."""
        for kind, ident in expired:
            if kind == "block" and self.bus.connected:
                self.bus.publish(topics.operator_block(self.view.site.name, ident), b"", qos=1, retain=True)

    def _take_events(self) -> list[dict[str, Any]]:
        """What happened since the last flush: written to the log, and sent to the pages."""
        with self.lock:
            happened, self.view.events = self.view.events, []
            self.alerts.on_events(happened, self.view)
        if happened and self.events is not None:
            try:
                self.events.add(happened)
            except Exception as exc:  # a full disk must not stop the console's intake
                log.warning("event log not written: %s", exc)
        return [{"t": e.t, "kind": e.kind, "subject": e.subject, "text": e.text} for e in happened]

    def recent_events(self, limit: int = 50) -> list[dict[str, Any]]:
        if self.events is None:
            return []
        return [
            {"t": e.t, "kind": e.kind, "subject": e.subject, "text": e.text}
            for e in self.events.recent(limit)
        ]

    def _flush(self, dirty: set[Key]) -> None:
        """One event of the entries whose look changed; a node heartbeat that changes nothing but its time and
        seq goes in `heard` ({node: [seq, heard_at]}) rather than as a whole entry: a thousand nodes' heartbeats
        coalesce into a small map, while every change of a state, link or staleness is sent as an entry."""
        event: dict[str, Any] = {
            "type": "update",
            "zones": [],
            "nodes": [],
            "robots": [],
            "blocks": [],
            "gone": [],
            "heard": {},
            "events": self._take_events(),
        }
        with self.lock:
            now = self.clock.now()
            event["now"] = now
            self.alerts.on_clock(self.view, now)
            if self.alerts.changed:
                self.alerts.changed = False
                event["alerts"] = self.alerts.entries()
            for kind, ident in sorted(dirty):
                if kind == "zone":
                    look = self.view.zone_look(ident, now)
                    if self._sent.get((kind, ident)) == look:
                        continue
                    self._sent[(kind, ident)] = look
                elif kind == "node":
                    node = self.view.nodes[ident]
                    look = (node.state, node.online, self.view.node_fresh(node, now), node.info_at)
                    if self._sent.get((kind, ident)) == look:
                        event["heard"][ident] = [node.seq, node.heard_at]
                        continue
                    self._sent[(kind, ident)] = look
                entry = self.view.entry((kind, ident), now)
                if entry is None:
                    event["gone"].append(ident)
                else:
                    event[f"{kind}s"].append(entry)
        self._broadcast(event)


def resync_event(live: LiveState) -> Callable[[], str]:
    """A full snapshot as an event, for a page that connects or fell behind."""

    def make() -> str:
        return json.dumps({"type": "snapshot", **live.snapshot()}, separators=(",", ":"))

    return make
