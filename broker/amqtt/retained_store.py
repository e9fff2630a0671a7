"""Retained messages that survive a broker restart, clean or kill -9, on stdlib sqlite.

amqtt keeps retained messages in a dict and forgets them on restart; its SessionDBPlugin needs SQLAlchemy and
aiosqlite, which we do not ship. This plugin mirrors the dict into `<data>/retained.sqlite3`:
- every retain (or clear, by an empty retained payload) is noted in memory at once;
- a flusher writes the pending changes in one transaction at most `flush_interval_s` later (default 0.2 s),
  in a worker thread so the event loop is never blocked by the SD card;
- the database is in WAL mode with `synchronous=NORMAL`: a committed flush survives kill -9 and a crash of the
  broker process (the data is in the OS by then); after a power cut the last few flushes may be lost but the
  file is never corrupt. `synchronous: FULL` (`--sync full`) also survives power cuts, at one fsync per flush.
So a kill -9 loses at most the retained updates of the last flush interval (amqtt sends a PUBACK before the
broker handles the message), except operator blocks: nothing republishes them, so `note(urgent=True)` writes
them at once with an fsync, and the patch (`WsnavProtocolHandler`) holds their PUBACK until `written`.

The storage policy (docs/security.md), so that no state is ever lost silently:
- a damaged file (not a database, malformed pages, or 0 bytes) is moved aside to
  `retained.sqlite3.damaged-<UTC time>` with one ERROR line naming both files, and the broker starts empty
  (nodes republish their state within one heartbeat; operator blocks must be sent again);
- a store that cannot be opened for another reason (disk full, permissions) stops the start with one line
  and leaves the file untouched;
- a flush that fails (disk full) keeps the updates in memory and retries every second, with an ERROR line at
  once and every 30 s while it lasts, and a line when the store is writable again; updates still unwritten
  at shutdown are reported as lost, by count.
On start the stored messages are loaded before any listener opens; on clean shutdown everything pending is
flushed before exit.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sqlite3
import threading
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from amqtt.broker import BrokerContext, RetainedApplicationMessage
from amqtt.plugins.base import BasePlugin

DB_NAME = "retained.sqlite3"
_SCHEMA = "CREATE TABLE IF NOT EXISTS retained (topic TEXT PRIMARY KEY, payload BLOB NOT NULL, qos INTEGER NOT NULL)"

Pending = dict[str, tuple[bytes, int] | None]
"""topic -> (payload, qos) to store, or None to delete."""
RETRY_S = 1.0
REPORT_EVERY_S = 30.0
_DAMAGED = {"SQLITE_CORRUPT", "SQLITE_NOTADB"}

log = logging.getLogger("wsnav.broker")


class StoreError(RuntimeError):
    """The retained store cannot be used and must not be touched; str() is one line for the user."""


class RetainedDb:
    """The sqlite file; used from one thread at a time (the flusher serialises its calls)."""

    def __init__(self, path: Path, synchronous: str = "NORMAL") -> None:
        self.path = path
        self._conn = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._lock = threading.Lock()
        with self._lock:
            self._conn.execute("PRAGMA journal_mode=WAL")
            self.full = synchronous.upper() == "FULL"
            self._conn.execute(f"PRAGMA synchronous={'FULL' if self.full else 'NORMAL'}")
            self._conn.execute(_SCHEMA)

    def check(self) -> None:
        """Raise sqlite3.DatabaseError unless every page reads back (garbage inside pages is found here)."""
        with self._lock:
            result = self._conn.execute("PRAGMA quick_check").fetchone()
        if not result or result[0] != "ok":
            raise sqlite3.DatabaseError(f"quick_check: {result[0] if result else 'no answer'}")

    def load(self) -> dict[str, tuple[bytes, int]]:
        with self._lock:
            rows = self._conn.execute("SELECT topic, payload, qos FROM retained").fetchall()
        return {topic: (bytes(payload), int(qos)) for topic, payload, qos in rows}

    def apply(self, pending: Pending, durable: bool = False) -> None:
        """One transaction; `durable`: fsync'd at its commit (synchronous=FULL for it), for a power cut."""
        with self._lock:
            if durable and not self.full:
                self._conn.execute("PRAGMA synchronous=FULL")
            try:
                self._apply(pending)
            finally:
                if durable and not self.full:
                    self._conn.execute("PRAGMA synchronous=NORMAL")

    def _apply(self, pending: Pending) -> None:
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
            if self._conn.in_transaction:  # SQLite rolls back by itself on a full disk
                self._conn.execute("ROLLBACK")
            raise

    def close(self) -> None:
        with self._lock:
            self._conn.close()


def _damaged(exc: sqlite3.DatabaseError) -> bool:
    """Corruption (the file is not what we wrote), as opposed to a disk or permission problem."""
    name = getattr(exc, "sqlite_errorname", None)
    return name in _DAMAGED or type(exc) is sqlite3.DatabaseError


def set_aside(path: Path) -> Path:
    """Move the database (and its -wal and -shm files) to `<name>.damaged-<UTC time>`; returns the new path."""
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    aside = path.with_name(f"{path.name}.damaged-{stamp}")
    for suffix in ("", "-wal", "-shm"):
        source = path.with_name(path.name + suffix)
        if source.exists():
            source.rename(aside.with_name(aside.name + suffix))
    return aside


def open_store(path: Path, synchronous: str = "NORMAL") -> tuple[RetainedDb, dict[str, tuple[bytes, int]]]:
    """The store and what it holds, under the storage policy of the module docstring; raises StoreError."""
    try:
        try:
            if path.exists() and path.stat().st_size == 0:
                raise sqlite3.DatabaseError("the file is empty (0 bytes)")
            db = RetainedDb(path, synchronous)
            try:
                db.check()
                return db, db.load()
            except BaseException:
                db.close()
                raise
        except sqlite3.DatabaseError as exc:
            if not _damaged(exc):
                raise
            aside = set_aside(path)
            log.error(
                f"retained store {path} is damaged ({exc}): moved to {aside}; starting with NO retained "
                "messages (nodes republish their state within one heartbeat; send operator blocks again)"
            )
            return RetainedDb(path, synchronous), {}
    except (sqlite3.Error, OSError) as exc:
        raise StoreError(
            f"cannot open the retained store {path}: {exc} (the file is left as it is)"
        ) from None


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
        self._db, self._stored = open_store(directory / DB_NAME, config.synchronous)
        self._failing_since: float | None = None
        self._last_report = 0.0
        self._pending: Pending = {}
        self._wake = asyncio.Event()
        self._urgent = asyncio.Event()
        self._noted = 0
        self._written = 0
        self._waiters: list[tuple[int, asyncio.Future[None]]] = []
        self._flush_lock = asyncio.Lock()
        self._flusher: asyncio.Task[None] | None = None
        self._closed = False

    async def on_broker_pre_start(self) -> None:
        stored, self._stored = self._stored, {}
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
        self.note(retained_message.topic)

    def note(self, topic: str, urgent: bool = False) -> int:
        """Mark `topic`'s retained message (or its absence) as to be written, as the broker holds it now: amqtt's
        event runs as a later task, when a newer message may already be retained; returns a number to pass to
        `written`. `urgent`: written at once and fsync'd (an operator block), not within the flush interval."""
        current = self.context.retained_messages.get(topic)
        data = current.data if current is not None else None
        self._pending[topic] = (bytes(data), current.qos or 0) if current is not None and data else None
        self._noted += 1
        if urgent:
            self._urgent.set()
        self._wake.set()
        return self._noted

    @property
    def noted(self) -> int:
        return self._noted

    async def written(self, noted: int) -> None:
        """Until what was noted up to `noted` is on disk, or the store is failing (kept in memory, reported)."""
        if noted <= self._written or self._failing_since is not None or self._closed:
            return
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._waiters.append((noted, waiter))
        await waiter

    def _release(self, everyone: bool = False) -> None:
        waiting = []
        for noted, waiter in self._waiters:
            if everyone or noted <= self._written:
                if not waiter.done():
                    waiter.set_result(None)
            else:
                waiting.append((noted, waiter))
        self._waiters = waiting

    async def on_broker_pre_shutdown(self) -> None:
        """A first try; amqtt runs this as a task nobody awaits, so a failure (a full disk) must not escape it
        ("Task exception was never retrieved" and a traceback at every stop): `close` tries again and reports."""
        with contextlib.suppress(sqlite3.Error):
            await self.flush()

    async def close(self) -> None:
        """Last call of a shutdown (after amqtt's pending events ran): flush and close the file."""
        await self._stop()

    async def flush(self) -> None:
        """Write what is pending now (the flusher does this by itself; tests and shutdown call it too).

        One at a time: a shutdown's flush overtaking the flusher's would count its older write as done."""
        async with self._flush_lock:
            await self._flush()

    async def _flush(self) -> None:
        noted, durable = self._noted, self._urgent.is_set()
        self._urgent.clear()
        if not self._pending:
            self._written = noted
            self._release()
            return
        pending, self._pending = self._pending, {}
        try:
            await asyncio.to_thread(self._db.apply, pending, durable)
        except sqlite3.Error:
            self._pending = pending | self._pending  # keep them for the next try; newer values win
            if durable:
                self._urgent.set()
            raise
        self._written = noted
        self._release()

    async def _flush_loop(self) -> None:
        while True:
            if self._failing_since is None:
                await self._wake.wait()
                self._wake.clear()
                if self._interval and not self._urgent.is_set():
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(self._urgent.wait(), self._interval)
            else:
                await asyncio.sleep(RETRY_S)
            try:
                await self.flush()
            except sqlite3.Error as exc:
                self._report_failure(exc)
            else:
                if self._failing_since is not None:
                    self._failing_since = None
                    log.warning(f"retained store {self._db.path} is writable again: pending updates written")

    def _report_failure(self, exc: sqlite3.Error) -> None:
        self._release(everyone=True)  # kept in memory and served: the acknowledgements wait no longer
        now = time.monotonic()
        if self._failing_since is None:
            self._failing_since = now
        elif now - self._last_report < REPORT_EVERY_S:
            return
        self._last_report = now
        log.error(
            f"cannot store {len(self._pending)} retained update(s) in {self._db.path}: {exc}; kept in memory "
            "and retried every second (lost if the broker stops first)"
        )

    async def _stop(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._flusher is not None:
            self._flusher.cancel()
            await asyncio.gather(self._flusher, return_exceptions=True)
        try:
            await self.flush()
        except sqlite3.Error as exc:
            log.error(
                f"{len(self._pending)} retained update(s) could not be written to {self._db.path} and are LOST: {exc}"
            )
        finally:
            self._release(everyone=True)
            self._db.close()
