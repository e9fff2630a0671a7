"""Pending passwords on Mosquitto: a node's new MQTT password accepted beside its own until it confirms it.

Mosquitto 2.0's password file holds one hash per user (of two lines for one user, the last is taken), so it
alone cannot accept a node's old and new passwords at once. `wsnav broker mosquitto-config --pending-passwords`
builds a small auth plugin (pending_auth.c, pending_plugin.py) into the configuration: it accepts the
`username:$7$...` lines of PENDING (read at each login, no SIGHUP) and defers every other login to the password
file. `wsnav firmware config --new-password --mosquitto-config DIR` adds a node's new password here
before the node tries it; once the node confirms, the password file gets it (the old one is refused after
`systemctl reload mosquitto`) and PENDING keeps just that one line for the node, which is its own password by
then, until its next change or `wsnav broker revoke` (which removes the node's lines).
"""

from __future__ import annotations

import base64
import hmac
import os
from pathlib import Path

from wsnav.broker.credentials import write_private
from wsnav.broker.mosquitto.config import PASSWORDS, mosquitto_hash
from wsnav.broker.mosquitto.pending_plugin import PENDING, PLUGIN
from wsnav.schemas.credentials import CredentialsError


def add(out: Path, user: str, password: str) -> None:
    """`password` accepted for `user` from now on; its earlier lines stay (a change never confirmed may still
    have reached the node)."""
    _write(out, [*_lines(out), (user, mosquitto_hash(password))])


def keep_only(out: Path, user: str, password: str) -> None:
    """`user`'s lines replaced by `password`'s alone (it confirmed it: the password file has it too, but
    Mosquitto reads that file only on SIGHUP)."""
    _write(out, [*((u, d) for u, d in _lines(out) if u != user), (user, mosquitto_hash(password))])


def withdraw(out: Path, user: str, password: str | None = None) -> None:
    """`password` no longer pending for `user` (a change that did not happen; the node's other lines stay: one
    of them may be the password it has, which Mosquitto takes only from here until it reloads), or, without
    `password`, none of `user`'s (a revoked identity)."""
    if (out / PENDING).exists():
        _write(
            out,
            [(u, d) for u, d in _lines(out) if u != user or (password is not None and not _is(d, password))],
        )


def _is(digest: str, password: str) -> bool:
    """Is `digest` (`$7$iterations$salt$hash`) the hash of `password`?"""
    try:
        _, _, iterations, salt, _ = digest.split("$")
        return hmac.compare_digest(mosquitto_hash(password, base64.b64decode(salt), int(iterations)), digest)
    except ValueError:  # (binascii.Error is one)
        return False


def _lines(out: Path) -> list[tuple[str, str]]:
    path = out / PENDING
    if not (out / PLUGIN).exists():
        raise CredentialsError(
            f"{out}: no pending-password plugin in this Mosquitto configuration (run `wsnav broker "
            "mosquitto-config --pending-passwords` again and restart Mosquitto)"
        )
    try:
        text = path.read_text()
    except FileNotFoundError:
        return []
    except OSError as exc:
        raise CredentialsError(f"{path}: cannot read: {exc.strerror}") from None
    lines = []
    for raw in text.splitlines():
        user, sep, digest = raw.strip().partition(":")
        if sep and user and digest.startswith("$7$"):
            lines.append((user, digest))
    return lines


def _write(out: Path, lines: list[tuple[str, str]]) -> None:
    """The file rewritten, keeping the owner of the password file beside it (Mosquitto reads both after
    dropping to its user)."""
    path = out / PENDING
    write_private(path, "".join(f"{u}:{d}\n" for u, d in lines))
    if os.geteuid() == 0:
        owner = (out / PASSWORDS).stat()
        os.chown(path, owner.st_uid, owner.st_gid)
