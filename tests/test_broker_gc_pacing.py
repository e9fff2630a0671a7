"""wsnav.broker.amqtt.gc_pacing: what is frozen is skipped by collections, and nothing frozen stays unreclaimed for good."""

from __future__ import annotations

import asyncio
import gc
import weakref
from collections.abc import Iterator

import pytest

from wsnav.broker.amqtt.gc_pacing import YOUNG_THRESHOLD, freeze_now, pace_collections, refresh


class Session:
    """Stands for a broker session: an object in a reference cycle, as amqtt's sessions and handlers are."""

    def __init__(self) -> None:
        self.me = self


@pytest.fixture(autouse=True)
def thawed() -> Iterator[None]:
    gc.unfreeze()
    yield
    gc.unfreeze()
    gc.collect()


def test_frozen_objects_are_skipped_until_the_refresh_reclaims_them() -> None:
    session = Session()
    gone = weakref.ref(session)
    assert freeze_now() > 0
    del session  # the node reconnects: its old session is now cyclic garbage, but frozen
    gc.collect()
    assert gone() is not None, "a frozen object was walked by a collection"
    refresh()
    assert gone() is None, "the refresh left frozen garbage in memory"


def test_garbage_is_collected_before_freezing() -> None:
    session = Session()
    gone = weakref.ref(session)
    del session
    freeze_now()
    assert gone() is None, "garbage was frozen (it would stay until the next refresh)"


def test_the_pacer_freezes_on_its_period_and_refreshes() -> None:
    async def run() -> tuple[int, bool]:
        session = Session()
        gone = weakref.ref(session)
        task = asyncio.create_task(pace_collections(every_s=0.02, refresh_s=0.15))
        await asyncio.sleep(0.07)
        frozen = gc.get_freeze_count()
        del session
        await asyncio.sleep(0.3)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return frozen, gone() is None

    frozen, reclaimed = asyncio.run(run())
    assert frozen > 0
    assert reclaimed


def test_the_pacer_spaces_young_collections_out_and_gives_the_thresholds_back() -> None:
    """The broker's young collections found no garbage at 1000 messages/s and took 8-13 % of its loop."""
    before = gc.get_threshold()

    async def run() -> tuple[int, ...]:
        task = asyncio.create_task(pace_collections(every_s=10.0))
        await asyncio.sleep(0.01)
        during = gc.get_threshold()
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return during

    during = asyncio.run(run())
    assert during[0] >= YOUNG_THRESHOLD > before[0]
    assert during[1:] == before[1:]
    assert gc.get_threshold() == before


def test_the_pacer_freezes_what_is_alive_without_a_collection() -> None:
    """Every collection holds the broker's loop for its walk: at 1000 nodes its young collections (20-44 ms each,
    every 0.6 s) and the collection before each freeze (65-110 ms) found no garbage, and each delayed every
    delivery. Objects made between two freezes are frozen by the next one, with no collection run meanwhile."""
    collections: list[int] = []

    def seen(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            collections.append(info["generation"])

    async def run() -> int:
        task = asyncio.create_task(pace_collections(every_s=0.01, refresh_s=3600.0))
        await asyncio.sleep(0)  # the pacer's start (one collection, before the broker serves)
        kept: list[list[list[int]]] = []
        gc.callbacks.append(seen)
        try:
            for _ in range(30):  # 150,000 objects that stay alive, 5,000 between two freezes
                kept.append([[] for _ in range(5000)])
                await asyncio.sleep(0.01)
        finally:
            gc.callbacks.remove(seen)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
        return gc.get_freeze_count()

    frozen = asyncio.run(run())
    assert collections == [], f"collections ran while the pacer froze: generations {collections}"
    assert frozen >= 140_000, "the objects made while the pacer ran were not frozen"
