"""Who may use the console: the operator's username and password, a session cookie, a CSRF token for writes.

Sessions are kept in a small SQLite file when one is given (`wsnav console --state-dir`), so a restarted or
upgraded console keeps its pages logged in (a wall display needs nobody after an upgrade); the file holds a hash
of each session id with the operator's password, never the id itself, so a changed password ends every session.
The password is compared in constant time and a wrong one costs the caller a second, so guessing over HTTP is
slow. Nothing secret is ever sent to the page: the session id is an HttpOnly cookie, the CSRF token is per
session and worthless without it.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import hashlib
import hmac
import logging
import os
import secrets
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

COOKIE = "wsnav_console"
SESSION_IDLE_S = 12 * 3600.0
MAX_SESSIONS = 1000
TOUCH_EVERY_S = 60.0
"""A session's last use is written to the file at most this often (not on every request)."""


@dataclass
class Session:
    csrf: str
    last_seen: float = field(default_factory=time.time)
    stored_at: float = 0.0


class SessionStore:
    """Sessions on disk: (hash of id and password) -> CSRF token and last use, in one SQLite table."""

    def __init__(self, path: Path, password: bytes) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._password = password
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        with contextlib.suppress(OSError):
            os.chmod(path, 0o600)
        self._db.execute(
            "CREATE TABLE IF NOT EXISTS sessions (key TEXT PRIMARY KEY, csrf TEXT NOT NULL, last_seen REAL NOT NULL)"
        )
        self._db.execute("DELETE FROM sessions WHERE last_seen < ?", (time.time() - SESSION_IDLE_S,))

    def _key(self, sid: str) -> str:
        return hashlib.sha256(self._password + b"\0" + sid.encode()).hexdigest()

    def load(self, sid: str) -> Session | None:
        row = self._db.execute(
            "SELECT csrf, last_seen FROM sessions WHERE key = ?", (self._key(sid),)
        ).fetchone()
        return None if row is None else Session(csrf=row[0], last_seen=row[1], stored_at=row[1])

    def save(self, sid: str, session: Session) -> None:
        self._db.execute(
            "INSERT OR REPLACE INTO sessions (key, csrf, last_seen) VALUES (?, ?, ?)",
            (self._key(sid), session.csrf, session.last_seen),
        )
        session.stored_at = session.last_seen

    def delete(self, sid: str) -> None:
        self._db.execute("DELETE FROM sessions WHERE key = ?", (self._key(sid),))

    def trim(self, keep: int) -> None:
        self._db.execute(
            "DELETE FROM sessions WHERE key NOT IN (SELECT key FROM sessions ORDER BY last_seen DESC LIMIT ?)",
            (keep,),
        )


def open_store(path: Path | None, password: str) -> SessionStore | None:
    """The session file, or None (sessions in memory) with one warning line when it cannot be used."""
    if path is None:
        return None
    try:
        return SessionStore(path, password.encode())
    except (OSError, sqlite3.Error) as exc:
        log.warning("console sessions kept in memory only (a restart logs pages out): %s: %s", path, exc)
        return None


class Authenticator:
    def __init__(self, username: str, password: str, store: SessionStore | None = None) -> None:
        self._username = username.encode()
        self._password = password.encode()
        self._sessions: dict[str, Session] = {}
        self._store = store

    def check_password(self, username: str, password: str) -> bool:
        user_ok = hmac.compare_digest(username.encode(), self._username)
        return hmac.compare_digest(password.encode(), self._password) and user_ok

    def check_basic(self, header: str | None) -> bool:
        """An `Authorization: Basic ...` header with the operator's username and password."""
        if not header or not header.lower().startswith("basic "):
            return False
        try:
            user, sep, password = base64.b64decode(header[6:].strip(), validate=True).decode().partition(":")
        except (binascii.Error, UnicodeDecodeError, ValueError):
            return False
        return bool(sep) and self.check_password(user, password)

    def open_session(self) -> tuple[str, Session]:
        self._expire()
        if len(self._sessions) >= MAX_SESSIONS:
            oldest = min(self._sessions, key=lambda k: self._sessions[k].last_seen)
            del self._sessions[oldest]
        sid = secrets.token_urlsafe(32)
        session = Session(csrf=secrets.token_urlsafe(32))
        self._sessions[sid] = session
        if self._store is not None:
            self._store.save(sid, session)
            self._store.trim(MAX_SESSIONS)
        return sid, session

    def session(self, sid: str | None) -> Session | None:
        if not sid:
            return None
        session = self._sessions.get(sid)
        if session is None and self._store is not None:
            session = self._store.load(sid)  # opened before this console (re)started
            if session is not None:
                self._sessions[sid] = session
        if session is None:
            return None
        now = time.time()
        if now - session.last_seen > SESSION_IDLE_S:
            self.close_session(sid)
            return None
        session.last_seen = now
        if self._store is not None and now - session.stored_at > TOUCH_EVERY_S:
            self._store.save(sid, session)
        return session

    def close_session(self, sid: str | None) -> None:
        if sid:
            self._sessions.pop(sid, None)
            if self._store is not None:
                self._store.delete(sid)

    def _expire(self) -> None:
        now = time.time()
        for sid in [s for s, v in self._sessions.items() if now - v.last_seen > SESSION_IDLE_S]:
            del self._sessions[sid]
