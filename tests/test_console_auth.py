"""The console's login sessions on disk: kept across a restart, ended by a changed password or logout, and the
file holds no session id."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from wsnav.console.auth import Authenticator, open_store


def test_sessions_survive_a_restart_but_not_a_new_password_or_a_logout(tmp_path: Path) -> None:
    path = tmp_path / "state" / "console-site.sqlite"
    first = Authenticator("operator", "pw-1", open_store(path, "pw-1"))
    sid, session = first.open_session()
    other, _ = first.open_session()
    restarted = Authenticator("operator", "pw-1", open_store(path, "pw-1"))
    again = restarted.session(sid)
    assert again is not None and again.csrf == session.csrf, "a restart logged the page out"
    restarted.close_session(other)
    assert Authenticator("operator", "pw-1", open_store(path, "pw-1")).session(other) is None
    assert Authenticator("operator", "pw-2", open_store(path, "pw-2")).session(sid) is None, (
        "a session outlived the password it was opened with"
    )
    rows = sqlite3.connect(path).execute("SELECT key, csrf FROM sessions").fetchall()
    assert rows and all(sid not in key for key, _ in rows)
    assert path.stat().st_mode & 0o077 == 0


def test_an_unusable_session_file_keeps_sessions_in_memory_with_one_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert open_store(blocker / "sub" / "console.sqlite", "pw") is None
    assert len(caplog.records) == 1 and "in memory" in caplog.records[0].getMessage()
