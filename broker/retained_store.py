"""Retained messages that survive a broker restart, clean or kill -9 (amqtt fact 7), on stdlib sqlite.

amqtt keeps retained messages in a dict and forgets them on restart; its SessionDBPlugin needs SQLAlchemy and
aiosqlite, which we do not ship. This plugin mirrors the dict into `<data>/retained.sqlite3`:
- every retain (or clear, by an empty retained payload) is noted in memory at once;
- a flusher writes the pending changes in one transaction at most `flush_interval_s` later (default 0.2 s),
  in a worker thread so the event loop is never blocked by the SD card;
- the database is in WAL mode with `synchronous=NORMAL`: a committed flush survives kill -9 and a crash of the
  broker process (the data is in the OS by then); after a power cut the last few flushes may be lost but the
  file is never corrupt. `synchronous: FULL` (`--sync full`) also survives power cuts, at one fsync per flush.
So a kill -9 loses at most the retained updates of the last flush interval (a PUBACK is sent by amqtt before
the broker handles the message, so "acknowledged" cannot be made stronger without patching amqtt).
On start the stored messages are loaded before any listener opens; on clean shutdown everything pending is
flushed before exit.
"""

from __future__ import annotations

import asyncio
import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path

from amqtt.broker import BrokerContext, RetainedApplicationMessage
from amqtt.plugins.base import BasePlugin

DB_NAME = "retained.sqlite3"
_SCHEMA = "CREATE TABLE IF NOT EXISTS retained (topic TEXT PRIMARY KEY, payload BLOB NOT NULL, qos INTEGER NOT NULL)"

Pending = dict[str, tuple[bytes, int] | None]
"""topic -> (payload, qos) to store, or None to delete."""


class RetainedDb:
    """The sqlite file; used from one thread at a time (the flusher serialises its calls)."""

    def __init__(self, path: Path, synchronous: str = "NORMAL") -> None:
        self.path = path
        self._conn = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._lock = threading.Lock()
        with self._lock:
            self._conn.execute("PRAGMA journal_mode=WAL")
            self._conn.execute(f"PRAGMA synchronous={'FULL' if synchronous.upper() == 'FULL' else 'NORMAL'}")
            self._conn.execute(_SCHEMA)

    def load(self) -> dict[str, tuple[bytes, int]]:
        with self._lock:
            rows = self._conn.execute("SELECT topic, payload, qos FROM retained").fetchall()
        return {topic: (bytes(payload), int(qos)) for topic, payload, qos in rows}

    def apply(self, pending: Pending) -> None:
        with self._lock:
            self._conn.execute("BEGIN")
            try:
                for topic, value in pending.items():
                    if value is None:
                        self._conn.execute("DELETE FROM retained WHERE topic = ?", (topic,))
                    else:
                        self._conn.execute(
                            "INSERT INTO retained (topic, payload, qos) VALUES (?, ?, ?) "
                            "ON CONFLICT(topic) DO UPDATE SET payload = excluded.payload, qos = excluded.qos",
                            (topic, value[0], value[1]),
                        )
                self._conn.execute("COMMIT")
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise

    def close(self) -> None:
        with self._lock:
            self._conn.close()


def read_retained(data_dir: Path) -> dict[str, tuple[bytes, int]]:
    """What a stopped (or running) broker has stored: for tests, debugging and `wsnav broker` tooling."""
    path = data_dir / DB_NAME
    if not path.exists():
        return {}
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        rows = conn.execute("SELECT topic, payload, qos FROM retained").fetchall()
    except sqlite3.OperationalError:
        return {}
    finally:
        conn.close()
    return {topic: (bytes(payload), int(qos)) for topic, payload, qos in rows}


class RetainedStorePlugin(BasePlugin[BrokerContext]):
    """amqtt plugin: restore retained messages before listening, persist every change within a flush interval."""

    @dataclass
    class Config(BasePlugin.Config):
        data_dir: str = ""
        flush_interval_s: float = 0.2
        synchronous: str = "NORMAL"

    def __init__(self, context: BrokerContext) -> None:
        super().__init__(context)
        config = self.context.config
        assert isinstance(config, RetainedStorePlugin.Config)
        self._interval = max(0.0, config.flush_interval_s)
        directory = Path(config.data_dir)
        directory.mkdir(mode=0o700, parents=True, exist_ok=True)
        self._db = RetainedDb(directory / DB_NAME, config.synchronous)
        self._pending: Pending = {}
        self._wake = asyncio.Event()
        self._flusher: asyncio.Task[None] | None = None
        self._closed = False

    async def on_broker_pre_start(self) -> None:
        stored = await asyncio.to_thread(self._db.load)
        retained = self.context.retained_messages
        for topic, (payload, qos) in stored.items():
            retained[topic] = RetainedApplicationMessage(None, topic, payload, qos)
        self.context.logger.info(f"restored {len(stored)} retained messages from {self._db.path}")
        self._flusher = asyncio.create_task(self._flush_loop())

    async def on_broker_retained_message(
        self, *, client_id: str | None, retained_message: RetainedApplicationMessage
    ) -> None:
        if client_id is not None:
            return  # a message queued for one offline persistent session, not a topic's retained message
        data = retained_message.data
        self._pending[retained_message.topic] = (bytes(data), retained_message.qos or 0) if data else None
        self._wake.set()

    async def on_broker_pre_shutdown(self) -> None:
        await self.flush()

    async def close(self) -> None:
        """Last call of a shutdown (after amqtt's pending events ran): flush and close the file."""
        await self._stop()

    async def flush(self) -> None:
        """Write what is pending now (the flusher does this by itself; tests and shutdown call it too)."""
        if not self._pending:
            return
        pending, self._pending = self._pending, {}
        try:
            await asyncio.to_thread(self._db.apply, pending)
        except sqlite3.Error:
            self._pending = pending | self._pending  # keep them for the next try; newer values win
            raise

    async def _flush_loop(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            if self._interval:
                await asyncio.sleep(self._interval)
            try:
                await self.flush()
            except sqlite3.Error as exc:
                self.context.logger.error(f"cannot store retained messages in {self._db.path}: {exc}")

    async def _stop(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._flusher is not None:
            self._flusher.cancel()
            await asyncio.gather(self._flusher, return_exceptions=True)
        try:
            await self.flush()
        finally:
            self._db.close()
