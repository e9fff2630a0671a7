"""Short garbage-collection pauses for a broker holding many sessions.

A full (generation 2) collection walks every object the collector tracks and holds the event loop meanwhile.
With 1000 connected nodes amqtt keeps ~460k such objects (sessions, handlers, queues), and at 1000 messages/s
the objects that survive the young collections reach the collector's 25 % threshold every 3-5 s: each time
every delivery waits for one full walk (bench.zone_fanin, BENCHMARKS.md). `gc.freeze()` moves the objects
alive now to a permanent generation that collections skip, so they walk only what is new. A young collection
runs first, so garbage that is already garbage is not frozen. Cycles that become garbage after being frozen
(the session of a node that reconnects later) are reclaimed by one full collection every `refresh_s`.

The young collections are spaced out too (`YOUNG_THRESHOLD` allocations instead of CPython's 700): at 1000
messages/s the broker ran 20-30 of them a second, each walking the messages in flight, and over 15 s they found
no garbage at all while taking 8-13 % of the loop's time (3-5x more with a backlog, whose objects they walk
again and again: a backlog made its own collections longer).
"""

from __future__ import annotations

import asyncio
import gc
import time

FREEZE_EVERY_S = 10.0
REFRESH_EVERY_S = 600.0
YOUNG_THRESHOLD = 50_000
"""Net allocations between two young collections while the pacer runs (CPython's default: 700)."""


def freeze_now() -> int:
    """Collect the young generations, then freeze everything alive; returns the frozen count."""
    gc.collect(1)
    gc.freeze()
    return gc.get_freeze_count()


def refresh() -> None:
    """One full collection over everything (frozen garbage included), then freeze what survived."""
    gc.unfreeze()
    gc.collect()
    gc.freeze()


async def pace_collections(every_s: float = FREEZE_EVERY_S, refresh_s: float = REFRESH_EVERY_S) -> None:
    """Run for the broker's life (cancel it at shutdown): young collections every `YOUNG_THRESHOLD` allocations,
    freeze every `every_s`, refresh every `refresh_s`; the collector's thresholds are restored at the end."""
    thresholds = gc.get_threshold()
    gc.set_threshold(max(thresholds[0], YOUNG_THRESHOLD), *thresholds[1:])
    refreshed = time.monotonic()
    try:
        while True:
            await asyncio.sleep(every_s)
            if time.monotonic() - refreshed >= refresh_s:
                refresh()
                refreshed = time.monotonic()
            else:
                freeze_now()
    finally:
        gc.set_threshold(*thresholds)
