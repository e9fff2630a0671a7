"""Which login a copy of an operator tool uses, so that several copies (two consoles, two `wsnav watch`) run at once.

Mosquitto makes a client id of the login (`use_username_as_clientid`): two copies under one login took each other
over without end. Each tool has TOOL_COPIES logins (schemas.credentials.tool_copies). A copy takes the first one no
other process on this host holds (a lock file each, which the kernel releases when the process ends), counting
from a place set by the host's name, so copies on two hosts seldom start on the same one; and after every lost
connection it moves on to the next free one, so a copy taken over by one on another host moves away instead of
taking its login back (the ping-pong of one shared login).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import socket
import tempfile
import zlib
from collections.abc import Sequence
from pathlib import Path

log = logging.getLogger(__name__)


def lock_dir() -> Path:
    """Where this host's copies hold their logins: per user, beside the other temporary files."""
    return Path(tempfile.gettempdir()) / f"wsnav-logins-{os.getuid()}"


class LoginCopies:
    """The logins of one tool's copies; holds one at a time (`current`), taken with `take` or `move_on`."""

    def __init__(self, logins: Sequence[str], where: Path | None = None) -> None:
        self.logins = list(logins)
        self._dir = where if where is not None else lock_dir()
        self._held: int | None = None
        self._index = zlib.crc32(socket.gethostname().encode()) % len(self.logins)
        self.current = self.logins[self._index]

    def take(self) -> str:
        """The first login from the current place on that no process of this host holds."""
        return self._take_from(self._index)

    def move_on(self) -> str:
        """After a lost connection: the next free login after the one held."""
        return self._take_from(self._index + 1)

    def release(self) -> None:
        if self._held is not None:
            os.close(self._held)
            self._held = None

    def _take_from(self, start: int) -> str:
        self.release()
        with contextlib.suppress(OSError):
            self._dir.mkdir(mode=0o700, exist_ok=True)
        for step in range(len(self.logins)):
            index = (start + step) % len(self.logins)
            fd = self._lock(self.logins[index])
            if fd is not None:
                self._held, self._index = fd, index
                break
        else:  # every copy's login held here (or no lock folder): share one, as before
            self._index = start % len(self.logins)
            log.warning("all %d logins of %s are in use on this host", len(self.logins), self.logins[0])
        self.current = self.logins[self._index]
        return self.current

    def _lock(self, login: str) -> int | None:
        try:
            fd = os.open(self._dir / f"{login}.lock", os.O_RDWR | os.O_CREAT, 0o600)
        except OSError:
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            return None
        return fd
