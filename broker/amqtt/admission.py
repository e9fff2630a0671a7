"""Who gets a socket: a connection cap below the descriptor limit, and idle sockets that make way for real logins.

An attacker who opens sockets and never logs in must not lock out the site's nodes. Every accepted connection
is *pending* until it has logged in; pending connections are closed after the CONNECT timeout (packet_gate), and
when the broker is full a new connection pushes out the oldest pending one instead of waiting behind it.
Logged-in connections are never pushed out: when all slots are logged in, a new connection is closed at once;
and one identity holds at most MAX_PER_IDENTITY of them, so a stolen credential cannot fill the slots either.
The cap stays below the process's open-file limit with a reserve for the store, logs and the bursts of sockets
asyncio accepts in one loop turn, so `accept()` itself never fails with "Too many open files".
"""

from __future__ import annotations

import logging
import resource
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

log = logging.getLogger("wsnav.broker")

DESCRIPTOR_RESERVE = 320
"""Descriptors kept free of connections at least: asyncio accepts up to 100 sockets per listener and loop turn
before any of them is seen here (and closing one takes another turn), plus the retained store, logs, TLS and the
event loop. Under a low limit half of it is kept free, since a loaded machine runs more turns behind."""


MAX_PER_IDENTITY = 16
"""Logged-in connections of one identity: a node or robot needs one, the operator a few tools at once."""


def raise_descriptor_limit() -> int:
    """Raise the soft open-file limit to the hard one (systemd's LimitNOFILE) and return the soft limit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 65536)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    return soft


def connection_capacity(max_connections: int, descriptor_limit: int) -> int:
    """How many client connections fit: `max_connections` (0: no own cap) but never past the descriptors."""
    reserve = min(max(DESCRIPTOR_RESERVE, descriptor_limit // 2), 1024)
    by_descriptors = max(1, descriptor_limit - reserve)
    return by_descriptors if max_connections <= 0 else min(max_connections, by_descriptors)


@dataclass(eq=False)
class Ticket:
    """One admitted connection; `close` aborts its socket (frees the descriptor at once)."""

    close: Callable[[], None]
    identity: str | None = None
    """Set when the connection has logged in."""
    since: float = field(default_factory=time.monotonic)
    logged_in_at: float = 0.0
    """Wall-clock time of the login (compared with the password file's modification time)."""


class Admission:
    """The broker's connection slots (all listeners share them, since they share the descriptors)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._pending: OrderedDict[Ticket, None] = OrderedDict()
        self._logged_in: set[Ticket] = set()
        self._per_identity: Counter[str] = Counter()
        self.evicted = 0
        self.refused = 0
        self._reported = (0, 0)
        self._last_report = 0.0

    @property
    def open(self) -> int:
        return len(self._pending) + len(self._logged_in)

    def admit(self, close: Callable[[], None]) -> Ticket | None:
        """A ticket for a new connection, pushing out the oldest pending one if full; None: refuse it."""
        if self.open >= self.capacity:
            if not self._pending:
                self.refused += 1
                self._report()
                return None
            oldest, _ = self._pending.popitem(last=False)
            self.evicted += 1
            oldest.close()
            self._report()
        ticket = Ticket(close)
        self._pending[ticket] = None
        return ticket

    def logged_in(self, ticket: Ticket, identity: str) -> bool:
        """Move a pending connection to the logged-in ones; False (and no change) if its identity is at its cap."""
        if ticket not in self._pending:
            return ticket.identity == identity  # evicted meanwhile (False) or already counted
        if self._per_identity[identity] >= MAX_PER_IDENTITY:
            self.refused += 1
            self._report()
            return False
        del self._pending[ticket]
        ticket.identity = identity
        ticket.logged_in_at = time.time()
        self._logged_in.add(ticket)
        self._per_identity[identity] += 1
        return True

    def release(self, ticket: Ticket) -> None:
        self._pending.pop(ticket, None)
        if ticket in self._logged_in:
            self._logged_in.discard(ticket)
            assert ticket.identity is not None
            self._per_identity[ticket.identity] -= 1

    def close_identity(self, identity: str, logged_in_before: float) -> int:
        """Close the connections of `identity` that logged in before `logged_in_before` (wall clock: when its
        password was renewed; later logins used the new one); returns how many."""
        mine = [t for t in self._logged_in if t.identity == identity and t.logged_in_at < logged_in_before]
        for ticket in mine:
            ticket.close()
        return len(mine)

    def close_all(self) -> int:
        """Abort every connection still open (the end of a shutdown): a peer must see the broker go at once, not
        a keepalive or two later because a session's cleanup left its socket open."""
        every = [*self._pending, *self._logged_in]
        for ticket in every:
            ticket.close()
        return len(every)

    def out_of_descriptors(self) -> None:
        """asyncio could not accept (EMFILE): counted and reported like a refusal, without its traceback."""
        self.refused += 1
        self._report()

    def _report(self) -> None:
        """One warning per 10 s at most, however hard the port is hammered (the log must not fill the disk)."""
        now = time.monotonic()
        if now - self._last_report < 10.0:
            return
        evicted, refused = self.evicted - self._reported[0], self.refused - self._reported[1]
        self._reported, self._last_report = (self.evicted, self.refused), now
        log.warning(
            f"connection slots full ({self.capacity}) or an identity at its {MAX_PER_IDENTITY}: closed {evicted} "
            f"idle connection(s) that had not logged in and refused {refused} since the last report"
        )
