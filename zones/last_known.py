"""The last known zone states kept on disk, for a reader that restarts (the robot agent, the ROS bridges).

Without them a restart with the broker down serves every zone free (nothing heard yet), and a retained state
redelivered on every subscribe (a stopped node's last word) looks fresh at every start. With them the reader
starts from what it knew, aged by the time that passed, under the site's stale policy; a retained copy of a state
already known keeps its true age. One small JSON file per site, replaced atomically (written beside it, synced,
renamed), so a power cut leaves the old file or the new one, never half of one.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from wsnav.runtime.cli_support import CliError
from wsnav.schemas.site_file import SiteFile

log = logging.getLogger(__name__)

FORMAT = 1
WRITE_INTERVAL_S = 2.0
"""At most one write per interval for heartbeats (a change of a node's state is written at once)."""


@dataclass(frozen=True)
class KnownState:
    """One node's last accepted state: as it came (to tell a retained copy of it), and when it was last heard."""

    state: str
    seq: int
    payload: bytes
    heard_unix: float
    """Unix time of the last message from the node (a state or its birth)."""
    online: bool = True


class LastKnownZones:
    """The last accepted state of each node of one site, read at start and written as states arrive."""

    def __init__(
        self,
        path: Path,
        spec: SiteFile,
        *,
        unix_time: Callable[[], float] = time.time,
        write_interval_s: float = WRITE_INTERVAL_S,
    ) -> None:
        self.path = path
        self._site = spec.name
        self._watches = {n.id: n.zone for n in spec.nodes}
        self._unix_time = unix_time
        self._interval = write_interval_s
        self._written_at: float | None = None
        self._dirty = False
        self.known: dict[str, KnownState] = self._read()
        """Node -> its last known state, as read at start and kept up to date."""

    @classmethod
    def in_dir(cls, state_dir: Path, spec: SiteFile) -> LastKnownZones:
        """The site's file in a reader's `--state-dir` (made if missing); a folder that cannot be made or written
        is a one-line CliError."""
        try:
            state_dir.mkdir(parents=True, exist_ok=True)
            probe = tempfile.NamedTemporaryFile(dir=state_dir, prefix=".probe.")  # noqa: SIM115
            probe.close()
        except OSError as exc:
            raise CliError(f"--state-dir {state_dir}: {exc.strerror or exc}") from None
        return cls(state_dir / f"zones-{spec.name}.json", spec)

    def age_s(self, node: str) -> float | None:
        """Seconds since the node was last heard, by the file (never negative), or None if it holds no state."""
        known = self.known.get(node)
        return None if known is None else max(0.0, self._unix_time() - known.heard_unix)

    def accepted(self, node: str, state: str, seq: int, payload: bytes) -> None:
        """A state the intake accepted: remembered now, written at once if the node's word changed."""
        before = self.known.get(node)
        self.known[node] = KnownState(state, seq, bytes(payload), self._unix_time())
        self._dirty = True
        self._write(urgent=before is None or before.state != state or not before.online)

    def status(self, node: str, online: bool) -> None:
        """A birth (`online`: heard now) or will (`offline`) of a node whose state is known."""
        before = self.known.get(node)
        if before is None:
            return
        heard = self._unix_time() if online else before.heard_unix
        self.known[node] = KnownState(before.state, before.seq, before.payload, heard, online)
        self._dirty = True
        self._write(urgent=before.online != online)

    def flush(self) -> None:
        """Write what is not written yet (at exit)."""
        if self._dirty:
            self._write(urgent=True)

    def _write(self, *, urgent: bool) -> None:
        now = self._unix_time()
        if not urgent and self._written_at is not None and now - self._written_at < self._interval:
            return
        doc = {
            "format": FORMAT,
            "site": self._site,
            "nodes": {
                node: {
                    "state": k.state,
                    "seq": k.seq,
                    "payload": k.payload.decode("utf-8", "replace"),
                    "heard_unix": k.heard_unix,
                    "online": k.online,
                }
                for node, k in sorted(self.known.items())
            },
        }
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=self.path.parent)
            try:
                with os.fdopen(fd, "w") as f:
                    json.dump(doc, f, separators=(",", ":"))
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, self.path)
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
        except OSError as exc:  # a full or read-only disk must not stop the reader; it only forgets more
            if self._written_at is None or now - self._written_at >= 60.0:
                log.warning("last known zone states: cannot write %s: %s", self.path, exc)
            self._written_at = now
            return
        self._written_at = now
        self._dirty = False

    def _read(self) -> dict[str, KnownState]:
        """The file's states for this site's nodes; a missing file is none, a bad one is one warning and none."""
        try:
            doc = json.loads(self.path.read_text())
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as exc:
            log.warning("last known zone states: %s unreadable (%s); starting without them", self.path, exc)
            return {}
        if not isinstance(doc, dict) or doc.get("format") != FORMAT or doc.get("site") != self._site:
            log.warning(
                "last known zone states: %s is not this site's (%s); starting without it",
                self.path,
                self._site,
            )
            return {}
        out: dict[str, KnownState] = {}
        nodes = doc.get("nodes")
        for node, entry in nodes.items() if isinstance(nodes, dict) else []:
            try:
                known = KnownState(
                    str(entry["state"]),
                    int(entry["seq"]),
                    str(entry["payload"]).encode(),
                    float(entry["heard_unix"]),
                    bool(entry.get("online", True)),
                )
            except (KeyError, TypeError, ValueError):
                continue
            if node in self._watches and known.state in ("clear", "caution", "blocked"):
                out[node] = known
        return out
