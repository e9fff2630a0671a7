"""Short garbage-collection pauses for a broker holding many sessions.

A full (generation 2) collection walks every object the collector tracks and holds the event loop meanwhile.
With 1000 connected nodes amqtt keeps ~460k such objects (sessions, handlers, queues), and at 1000 messages/s
the objects that survive the young collections reach the collector's 25 % threshold every 3-5 s: each time
every delivery waits for one full walk (bench.zone_fanin, BENCHMARKS.md). `gc.freeze()` moves the objects
alive now to a permanent generation that collections skip, so they walk only what is new. A young collection
runs first, so garbage that is already garbage is not frozen. Cycles that become garbage after being frozen
(the session of a node that reconnects later) are reclaimed by one full collection every `refresh_s`.
"""

from __future__ import annotations

import asyncio
import gc
import time

FREEZE_EVERY_S = 10.0
REFRESH_EVERY_S = 600.0


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
    """Run for the broker's life (cancel it at shutdown): freeze every `every_s`, refresh every `refresh_s`."""
    refreshed = time.monotonic()
    while True:
        await asyncio.sleep(every_s)
        if time.monotonic() - refreshed >= refresh_s:
            refresh()
            refreshed = time.monotonic()
        else:
            freeze_now()
