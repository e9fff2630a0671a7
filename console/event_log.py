"""The console's event log on disk (SQLite): blocks set, lifted and expired, nodes going offline and coming back,
robots waiting (stuck: the reason says why), cancelled or arrived, each with the site time it happened; shown on the page and by `wsnav log`.

The console writes it (one file per site under `--state-dir`, next to the login sessions); `wsnav log` reads it
without a broker. At most MAX_EVENTS are kept (the oldest go first).
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path

MAX_EVENTS = 100_000


@dataclass(frozen=True)
class Event:
    t: float
    kind: str
    """block_set, block_extended, block_lifted, block_expired, node_offline, node_online, robot_waiting, robot_cancelled,
    robot_arrived"""
    subject: str
    text: str


def log_path(state_dir: Path, site: str) -> Path:
    return state_dir / f"events-{site}.sqlite"


class EventLog:
    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._db.execute(
            "CREATE TABLE IF NOT EXISTS events (t REAL NOT NULL, kind TEXT NOT NULL, subject TEXT NOT NULL, "
            "text TEXT NOT NULL)"
        )
        self._written = 0

    def add(self, events: list[Event]) -> None:
        if not events:
            return
        self._db.executemany(
            "INSERT INTO events (t, kind, subject, text) VALUES (?, ?, ?, ?)",
            [(e.t, e.kind, e.subject, e.text) for e in events],
        )
        self._written += len(events)
        if self._written >= 1000:
            self._written = 0
            self._db.execute(
                "DELETE FROM events WHERE rowid NOT IN (SELECT rowid FROM events ORDER BY rowid DESC LIMIT ?)",
                (MAX_EVENTS,),
            )

    def recent(self, limit: int) -> list[Event]:
        """The last `limit` events, oldest first."""
        rows = self._db.execute(
            "SELECT t, kind, subject, text FROM events ORDER BY rowid DESC LIMIT ?", (limit,)
        ).fetchall()
        return [Event(*row) for row in reversed(rows)]

    def close(self) -> None:
        self._db.close()


def open_for_reading(path: Path) -> EventLog | None:
    """The log if the file exists (`wsnav log` never creates one)."""
    if not path.is_file():
        return None
    return EventLog(path)
