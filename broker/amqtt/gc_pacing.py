"""Garbage collections that do not stall a broker holding many sessions.

Every collection holds the event loop while it walks the objects of the generations it collects. With 1000
connected nodes amqtt keeps ~300k long-lived objects (sessions, handlers, queues) and, at 1000 messages/s,
~150k more that each live about a second (the read task, its timer and coroutines a connection makes per
packet): too long-lived for the young generations, which promote them and walk them again. Measured in the
broker at 1000 nodes (bench.zone_fanin): with young collections every 50,000 allocations, each took 20-44 ms,
one ran every 0.6 s, and each tenth (the middle generation) 65-110 ms; freezing every 10 s after a young
collection walked the same 150k objects once more. Every one of them found no garbage: at this rate the
broker's objects are freed by their reference counts, not by the collector.

So `gc.freeze()` runs every `FREEZE_EVERY_S` without a collection: it moves every tracked object to a
permanent generation that collections skip (in constant time, and it resets the count that triggers them),
so the objects of the last quarter second are all a collection could ever walk, and at 1000 messages/s they
never reach `YOUNG_THRESHOLD`: no collection runs at all. Frozen objects are still freed by their reference
counts; only cyclic garbage (a reconnecting node's old session, an exception's traceback) waits for the
refresh, one full collection every `REFRESH_EVERY_S`. Its walk over everything is the one stall left: 240-400 ms
at 1000 nodes (load 9 on the shared 2-core PC), and in steady state it found no garbage; only after the nodes
left (64k objects of their sessions).
"""

from __future__ import annotations

import asyncio
import gc
import time

FREEZE_EVERY_S = 0.25
REFRESH_EVERY_S = 600.0
YOUNG_THRESHOLD = 50_000
"""Net allocations that trigger a young collection while the pacer runs (CPython's default: 700): reached only by
more than 200,000 new objects a second, so it is a backstop, not the rhythm."""


def freeze_now() -> int:
    """Collect the young generations, then freeze everything alive; returns the frozen count (at start: garbage
    made while starting is not frozen)."""
    gc.collect(1)
    gc.freeze()
    return gc.get_freeze_count()


def refresh() -> None:
    """One full collection over everything (frozen garbage included), then freeze what survived."""
    gc.unfreeze()
    gc.collect()
    gc.freeze()


async def pace_collections(every_s: float = FREEZE_EVERY_S, refresh_s: float = REFRESH_EVERY_S) -> None:
    """Run for the broker's life (cancel it at shutdown): freeze now and then every `every_s` without collecting,
    refresh every `refresh_s`; the collector's thresholds are restored at the end."""
    thresholds = gc.get_threshold()
    gc.set_threshold(max(thresholds[0], YOUNG_THRESHOLD), *thresholds[1:])
    freeze_now()
    refreshed = time.monotonic()
    try:
        while True:
            await asyncio.sleep(every_s)
            if time.monotonic() - refreshed >= refresh_s:
                refresh()
                refreshed = time.monotonic()
            else:
                gc.freeze()
    finally:
        gc.set_threshold(*thresholds)
