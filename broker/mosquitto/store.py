"""Mosquitto's store (`mosquitto.db`): is it whole, keep the last whole one, put it back before a start.

Mosquitto 2.0.11 saves by writing `mosquitto.db.new` and renaming it over `mosquitto.db`, and it does not check
`fclose`: on a full disk a store smaller than stdio's buffer is renamed into place empty (larger ones cut short),
with nothing logged, and the next start serves no retained message at all (operator blocks included). So the
file's own framing is checked here: a 23-byte header (magic, CRC, version) and then chunks of a 4-byte type and a
4-byte length (big-endian, `persist_write_v5.c`); an empty file, a chunk running past the end or no config chunk
is a store cut short. A whole store is hard-linked as `mosquitto.db.good` (a link needs no room on the full
disk, and Mosquitto's rename leaves the linked file alone); `restore` puts it back before Mosquitto starts.
"""

from __future__ import annotations

import os
import struct
import time
from dataclasses import dataclass
from pathlib import Path

STORE = "mosquitto.db"
GOOD = "mosquitto.db.good"
MAGIC = b"\x00\xb5\x00mosquitto db"
HEADER_BYTES = len(MAGIC) + 8
CHUNK_CFG, CHUNK_RETAIN = 1, 4


@dataclass(frozen=True)
class StoreCheck:
    """What a store file holds: `problem` is None for a whole store, else what is wrong, in a few words."""

    problem: str | None
    retained: int = 0
    saved_at: float = 0.0


def check_store(path: Path) -> StoreCheck:
    """Walk the store's chunks without interpreting them; a missing file is a problem too."""
    try:
        data = path.read_bytes()
        saved_at = path.stat().st_mtime
    except (FileNotFoundError, NotADirectoryError):
        return StoreCheck("missing")
    except OSError as exc:
        return StoreCheck(f"unreadable ({exc.strerror})")
    if not data:
        return StoreCheck("empty (0 bytes)", saved_at=saved_at)
    if len(data) < HEADER_BYTES or not data.startswith(MAGIC):
        return StoreCheck(f"not a Mosquitto store ({len(data)} bytes)", saved_at=saved_at)
    pos, kinds, retained = HEADER_BYTES, set(), 0
    while pos < len(data):
        if pos + 8 > len(data):
            return StoreCheck(
                f"cut short at byte {len(data)} (a chunk header is incomplete)", saved_at=saved_at
            )
        kind, length = struct.unpack_from("!II", data, pos)
        pos += 8 + length
        if pos > len(data):
            return StoreCheck(
                f"cut short at byte {len(data)} (a chunk runs to byte {pos})", saved_at=saved_at
            )
        kinds.add(kind)
        retained += kind == CHUNK_RETAIN
    if CHUNK_CFG not in kinds:
        return StoreCheck("cut short (no config chunk)", saved_at=saved_at)
    return StoreCheck(None, retained=retained, saved_at=saved_at)


def keep_good(data_dir: Path) -> None:
    """Hard-link a whole `mosquitto.db` as `mosquitto.db.good` (atomically replacing the older one).

    Raises OSError when the folder cannot be written."""
    store, good = data_dir / STORE, data_dir / GOOD
    if good.exists() and os.path.samefile(store, good):
        return
    temporary = data_dir / f"{GOOD}.{os.getpid()}"
    temporary.unlink(missing_ok=True)
    os.link(store, temporary)
    os.replace(temporary, good)


def restore(data_dir: Path) -> tuple[bool, str]:
    """Before Mosquitto starts: a store that is not whole is moved aside and the last whole one put back.

    Returns (ok, one line to log): ok is False when the store is not whole and nothing whole was kept."""
    store, good = data_dir / STORE, data_dir / GOOD
    now = check_store(store)
    if now.problem is None:
        return True, f"{store}: whole ({now.retained} retained messages)"
    kept = check_store(good)
    if now.problem == "missing" and kept.problem == "missing":
        return True, f"{store}: none yet (a first start)"
    if kept.problem is not None:
        return False, (
            f"ERROR: {store} is {now.problem} and no whole copy was kept ({good}: {kept.problem}): Mosquitto "
            "starts without retained messages; send the operator blocks again"
        )
    aside = ""
    if now.problem != "missing":
        moved = store.with_name(f"{STORE}.damaged-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}")
        os.replace(store, moved)
        aside = f", it was moved to {moved.name}"
    os.link(good, store)
    saved = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(kept.saved_at))
    return True, (
        f"ERROR: {store} was {now.problem}{aside} (a full disk?): restored the last whole store, saved "
        f"{saved} with {kept.retained} retained messages; what changed after that is lost"
    )
