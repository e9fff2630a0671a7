"""The operator's alerts: a node offline, a robot stuck (waiting) or given up (cancelled, not by the operator), an
operator block expiring within EXPIRING_S. Each can be acknowledged.

An alert is raised by what the console saw happen live (`SiteView.events`, never a broker's replay on connect)
or, for an expiring block, by the console's own clock; it leaves the list once its condition is over. Its id
names the occurrence (who, and when it began), so a condition that comes back is a new alert, unacknowledged.
Acknowledgements are kept in SQLite under `--state-dir` (the event log's file), so a page reload, another page
or a console restart sees the same ones.
"""

from __future__ import annotations

import logging
import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from wsnav.console.event_log import Event
from wsnav.console.site_view import SiteView
from wsnav.schemas.messages import OPERATOR_CANCEL_REASON, is_yielding

log = logging.getLogger(__name__)

EXPIRING_S = 60.0
"""An operator block this close to its expiry raises an alert: extend it, or let it go."""
ACK_KEEP_S = 30 * 86400.0
"""Acknowledgements older than this are forgotten when the console starts (their alerts are long over)."""


@dataclass
class Alert:
    id: str
    kind: str
    """node_offline, robot_stuck, robot_aborted, block_expiring"""
    subject: str
    text: str
    since: float
    until: float | None = None
    """For block_expiring: when the block expires (the page counts down to it)."""
    acknowledged: bool = False
    cause: tuple[str | None, str | None] | None = None
    """For a robot's alert: its status's (state, reason) that raised it; another one ends it."""

    def entry(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "kind": self.kind,
            "subject": self.subject,
            "text": self.text,
            "since": self.since,
            "until": self.until,
            "acknowledged": self.acknowledged,
        }


def alert_id(kind: str, subject: str, at: float) -> str:
    """One occurrence of a condition: the same condition beginning again later is another alert."""
    return f"{kind}-{subject}-{round(at * 1000)}"


class AckStore:
    """The acknowledged alert ids, in a table of the console's SQLite file."""

    def __init__(self, path: Path, now: float) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._db.execute("CREATE TABLE IF NOT EXISTS alert_acks (id TEXT PRIMARY KEY, t REAL NOT NULL)")
        self._db.execute("DELETE FROM alert_acks WHERE t < ?", (now - ACK_KEEP_S,))

    def add(self, alert: str, at: float) -> None:
        """Kept if the disk allows: a full disk must neither stop the console's intake nor fail the request (the
        acknowledgement then holds in memory, until a restart)."""
        try:
            self._db.execute("INSERT OR REPLACE INTO alert_acks (id, t) VALUES (?, ?)", (alert, at))
        except sqlite3.Error as exc:
            log.warning("acknowledgement of %s not kept: %s", alert, exc)

    def has(self, alert: str) -> bool:
        try:
            return self._db.execute("SELECT 1 FROM alert_acks WHERE id = ?", (alert,)).fetchone() is not None
        except sqlite3.Error as exc:
            log.warning("acknowledgements not read: %s", exc)
            return False

    def close(self) -> None:
        self._db.close()


class AlertBoard:
    """The alerts in force. Touched only under the LiveState's lock (the bus thread and the web app share it)."""

    def __init__(self, acks: AckStore | None = None) -> None:
        self.acks = acks
        self.alerts: dict[str, Alert] = {}
        self.changed = False
        """Set when the list changed since the pages were last sent it."""

    def _raise(
        self,
        kind: str,
        subject: str,
        text: str,
        at: float,
        *,
        key_t: float | None = None,
        until: float | None = None,
        cause: tuple[str | None, str | None] | None = None,
    ) -> None:
        ident = alert_id(kind, subject, at if key_t is None else key_t)
        if ident in self.alerts:
            return
        for old in [a for a in self.alerts.values() if a.kind == kind and a.subject == subject]:
            del self.alerts[old.id]  # the same condition begun anew replaces its older occurrence
        acked = self.acks is not None and self.acks.has(ident)
        self.alerts[ident] = Alert(ident, kind, subject, text, at, until, acked, cause)
        self.changed = True

    def _clear(self, kind: str, subject: str) -> None:
        for old in [a for a in self.alerts.values() if a.kind == kind and a.subject == subject]:
            del self.alerts[old.id]
            self.changed = True

    def on_events(self, events: list[Event], view: SiteView) -> None:
        """What happened live: raises node and robot alerts."""
        for e in events:
            if e.kind == "node_offline":
                self._raise("node_offline", e.subject, e.text, e.t)
            elif e.kind in ("robot_waiting", "robot_cancelled"):
                cause = _robot_cause(view, e.subject)
                if cause[0] != e.kind.removeprefix("robot_") or cause[1] == OPERATOR_CANCEL_REASON:
                    continue  # over already, or the operator's own cancel
                if is_yielding(*cause):
                    continue  # giving way to a robot with right of way: waiting on purpose, not stuck
                kind = "robot_stuck" if cause[0] == "waiting" else "robot_aborted"
                self._raise(kind, e.subject, e.text, e.t, cause=cause)

    def on_clock(self, view: SiteView, now: float) -> None:
        """Conditions that end (a node back, a robot moving again) and blocks that come close to expiring."""
        for alert in list(self.alerts.values()):
            over = False
            if alert.kind == "node_offline":
                over = view.nodes[alert.subject].online is not False
            elif alert.kind in ("robot_stuck", "robot_aborted"):
                now_cause, was = _robot_cause(view, alert.subject), alert.cause or (None, None)
                # stuck: while it waits, whatever it waits for; given up: until that goal's end is replaced
                over = (
                    now_cause[0] != was[0]
                    or (alert.kind == "robot_aborted" and now_cause != was)
                    or is_yielding(*now_cause)
                )
            elif alert.kind == "block_expiring":
                block = view.blocks.get(alert.subject)
                over = block is None or block.block.expires_at != alert.until
            if over:
                del self.alerts[alert.id]
                self.changed = True
        for block_id, block in view.blocks.items():
            expires = block.block.expires_at
            if expires is not None and 0 < expires - now <= EXPIRING_S:
                where = f"zone {block.block.zone}" if block.block.zone else "a drawn area"
                # the id is the block's expiry, not this instant: a console restarted meanwhile finds its ack
                self._raise(
                    "block_expiring",
                    block_id,
                    f"block {block_id} on {where} expires soon",
                    now,
                    key_t=expires,
                    until=expires,
                )

    def acknowledge(self, ident: str, now: float) -> bool:
        alert = self.alerts.get(ident)
        if alert is None:
            return False
        if not alert.acknowledged:
            alert.acknowledged = True
            self.changed = True
            if self.acks is not None:
                self.acks.add(ident, now)
        return True

    def entries(self) -> list[dict[str, Any]]:
        return [a.entry() for a in sorted(self.alerts.values(), key=lambda a: (a.since, a.id))]


def _robot_cause(view: SiteView, robot_id: str) -> tuple[str | None, str | None]:
    robot = view.robots.get(robot_id)
    status = robot.status if robot is not None else None
    return (status.state, status.reason) if status is not None else (None, None)
