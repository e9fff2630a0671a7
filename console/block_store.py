"""The operator's blocks kept on disk (SQLite, under `--state-dir`): operator intent outlives the broker's store.

Mosquitto lost blocks acknowledged 0.5 to 30 s before a kill -9 and a full disk wiped them all, so the console
keeps every block it has seen in force, and a restarted console publishes again those a broker no longer holds
(`LiveState`). A block lifted or expired while the console ran leaves the file at once, so it never comes back.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
from pathlib import Path


def blocks_path(state_dir: Path, site: str) -> Path:
    return state_dir / f"blocks-{site}.sqlite"


class BlockStore:
    """block id -> its payload as published (the contract's bytes) and its expiry on the site clock."""

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        with contextlib.suppress(OSError):
            os.chmod(path, 0o600)
        self._db.execute(
            "CREATE TABLE IF NOT EXISTS blocks (id TEXT PRIMARY KEY, payload BLOB NOT NULL, expires_at REAL)"
        )

    def keep(self, block_id: str, payload: bytes, expires_at: float | None) -> None:
        self._db.execute(
            "INSERT OR REPLACE INTO blocks (id, payload, expires_at) VALUES (?, ?, ?)",
            (block_id, payload, expires_at),
        )

    def forget(self, block_id: str) -> None:
        self._db.execute("DELETE FROM blocks WHERE id = ?", (block_id,))

    def in_force(self, now: float) -> dict[str, bytes]:
        """The kept blocks that have not expired at `now` (expired ones are deleted here)."""
        self._db.execute("DELETE FROM blocks WHERE expires_at IS NOT NULL AND expires_at <= ?", (now,))
        rows = self._db.execute("SELECT id, payload FROM blocks ORDER BY id").fetchall()
        return {str(block_id): bytes(payload) for block_id, payload in rows}

    def close(self) -> None:
        self._db.close()
