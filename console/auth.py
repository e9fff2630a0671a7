"""Who may use the console: the operator's username and password, a session cookie, a CSRF token for writes.

Sessions live in memory (a restart logs everybody out). The password is compared in constant time and a
wrong one costs the caller a second, so guessing over HTTP is slow. Nothing secret is ever sent to the page:
the session id is an HttpOnly cookie, the CSRF token is per session and worthless without it.
"""

from __future__ import annotations

import base64
import binascii
import hmac
import secrets
import time
from dataclasses import dataclass, field

COOKIE = "wsnav_console"
SESSION_IDLE_S = 12 * 3600.0
MAX_SESSIONS = 1000


@dataclass
class Session:
    csrf: str
    last_seen: float = field(default_factory=time.monotonic)


class Authenticator:
    def __init__(self, username: str, password: str) -> None:
        self._username = username.encode()
        self._password = password.encode()
        self._sessions: dict[str, Session] = {}

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
        return sid, session

    def session(self, sid: str | None) -> Session | None:
        if not sid:
            return None
        session = self._sessions.get(sid)
        if session is None:
            return None
        now = time.monotonic()
        if now - session.last_seen > SESSION_IDLE_S:
            del self._sessions[sid]
            return None
        session.last_seen = now
        return session

    def close_session(self, sid: str | None) -> None:
        if sid:
            self._sessions.pop(sid, None)

    def _expire(self) -> None:
        now = time.monotonic()
        for sid in [s for s, v in self._sessions.items() if now - v.last_seen > SESSION_IDLE_S]:
            del self._sessions[sid]
