"""wsnav.broker.amqtt.gc_pacing: what is frozen is skipped by collections, and nothing frozen stays unreclaimed for good."""

from __future__ import annotations

import asyncio
import gc
import time
import weakref
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.config import BrokerOptions
from wsnav.broker.amqtt.gc_pacing import YOUNG_THRESHOLD, freeze_now, pace_collections, refresh
from wsnav.broker.amqtt.server import start_broker
from wsnav.broker.credentials import write_credentials
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.site import load_site


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


def test_the_refresh_waits_for_a_connection_to_end_so_a_steady_site_never_stalls() -> None:
    """The refresh walks every object (240-400 ms at 1000 nodes) and, while the nodes stayed connected, found
    nothing: the cycles it reclaims are what an ended connection leaves. So with the broker's count of ended
    connections it runs only after one ended: none in steady state, then one that reclaims the garbage."""
    full: list[float] = []

    def seen(phase: str, info: dict[str, int]) -> None:
        if phase == "start" and info["generation"] == 2:
            full.append(time.monotonic())

    ended = [0]

    async def run() -> tuple[int, bool, bool]:
        session = Session()
        gone = weakref.ref(session)
        task = asyncio.create_task(pace_collections(every_s=0.01, refresh_s=0.05, ended=lambda: ended[0]))
        await asyncio.sleep(0.02)  # frozen
        del session  # cyclic garbage, as a session is, but no connection ended (say, a parked one expired)
        gc.callbacks.append(seen)
        try:
            await asyncio.sleep(0.4)  # eight refresh periods
            steady = len(full)
            kept = gone() is not None
            ended[0] += 1  # a node's connection ended
            await asyncio.sleep(0.2)
        finally:
            gc.callbacks.remove(seen)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
        return steady, kept, gone() is None

    steady, kept, reclaimed = asyncio.run(run())
    assert steady == 0, f"{steady} full collections while no connection ended"
    assert kept, "the garbage was reclaimed without a refresh?"
    assert reclaimed, "no refresh after a connection ended"
    assert len(full) == 1, f"{len(full)} refreshes for one ended connection"


def test_the_broker_counts_every_connection_that_ends(tmp_path: Path) -> None:
    """The refresh's signal, from the real broker: a node that logs in and leaves, and a socket that never logs
    in, each count once; a connection that stays counts nothing."""
    site = tiny_site(tmp_path / "site")
    spec = load_site(site).spec
    creds = tmp_path / "creds"
    write_credentials(spec, creds)
    node = load_credentials(creds / "n1.json")

    async def run() -> tuple[int, int, int]:
        running = await start_broker(spec, creds, BrokerOptions(bind=("127.0.0.1", 0)))
        try:

            async def ended(count: int) -> int:
                for _ in range(500):
                    if running.broker.connections_ended >= count:
                        break
                    await asyncio.sleep(0.01)
                return running.broker.connections_ended

            staying = await login(running.port, "n1-stays", node.username, node.password)
            left = await login(running.port, "n1", node.username, node.password)
            left.close()
            after_logout = await ended(1)
            _, silent = await asyncio.open_connection("127.0.0.1", running.port)
            silent.close()
            after_silent = await ended(2)
            await asyncio.sleep(0.1)
            final = running.broker.connections_ended
            staying.close()
            return after_logout, after_silent, final
        finally:
            await running.stop()

    assert asyncio.run(run()) == (1, 2, 2)


async def login(port: int, client_id: str, username: str, password: str) -> asyncio.StreamWriter:
    """An MQTT 3.1.1 CONNECT (clean session) answered by a CONNACK: a logged-in connection."""

    def text(value: str) -> bytes:
        return len(value.encode()).to_bytes(2, "big") + value.encode()

    body = text("MQTT") + bytes([4, 0xC2]) + (60).to_bytes(2, "big") + text(client_id)
    body += text(username) + text(password)
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(bytes([0x10, len(body)]) + body)
    assert await reader.readexactly(4) == b"\x20\x02\x00\x00", "no CONNACK accepting the login"
    return writer
