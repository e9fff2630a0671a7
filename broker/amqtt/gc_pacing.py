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
refresh, one full collection. Its walk over everything is the one stall left: 240-400 ms at 1000 nodes (load 9
on the shared 2-core PC). In steady state it found no garbage: the cycles it reclaims are what a connection
leaves when it ends (about 300 objects: its session and their state machine, the protocol handler, streams and
tasks; measured in the broker, 2026-11-28), 64k after the nodes left. So the refresh runs every
`REFRESH_EVERY_S` only if a connection ended since the last one (`ended`, the broker's count): a site whose
nodes stay connected never stalls; one whose nodes come and go stalls at most once every 10 minutes, as before.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import time
from collections.abc import Callable

log = logging.getLogger(__name__)

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


def refresh() -> int:
    """One full collection over everything (frozen garbage included), then freeze what survived; returns the
    number of unreachable objects found."""
    gc.unfreeze()
    found = gc.collect()
    gc.freeze()
    return found


async def pace_collections(
    every_s: float = FREEZE_EVERY_S,
    refresh_s: float = REFRESH_EVERY_S,
    ended: Callable[[], int] | None = None,
) -> None:
    """Run for the broker's life (cancel it at shutdown): freeze now and then every `every_s` without collecting,
    and every `refresh_s` refresh if `ended()` (a count of ended connections; None: always) moved since the last
    refresh; the collector's thresholds are restored at the end."""
    thresholds = gc.get_threshold()
    gc.set_threshold(max(thresholds[0], YOUNG_THRESHOLD), *thresholds[1:])
    freeze_now()
    refreshed = time.monotonic()
    ended_then = ended() if ended is not None else 0
    try:
        while True:
            await asyncio.sleep(every_s)
            if time.monotonic() - refreshed < refresh_s:
                gc.freeze()
                continue
            refreshed = time.monotonic()
            ended_now = ended() if ended is not None else ended_then + 1
            if ended_now != ended_then:
                found = refresh()
                took = time.monotonic() - refreshed
                log.info(
                    f"full garbage collection: {found} unreachable objects from {ended_now - ended_then} "
                    f"ended connection(s), {took * 1000:.0f} ms"
                )
                refreshed, ended_then = time.monotonic(), ended_now
            else:
                gc.freeze()
    finally:
        gc.set_threshold(*thresholds)
