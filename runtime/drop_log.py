"""Dropped messages, counted by reason and logged without flooding the log: the one rule every reader uses.

The first drop of a reason is logged at once, with what and why; later ones within `interval` seconds are only
counted, then summed up in one line ("dropped N <noun> (<reason>) in the last S s, the last: ..."), and a
reason quiet for a whole interval is logged at once again. `counts` has every drop. Time is the caller's clock
(the bus's), so lock-step simulated runs log the same lines.
"""

from __future__ import annotations

import logging
from collections import Counter

DROP_LOG_INTERVAL = 10.0
"""Seconds (of the caller's clock) between two log lines about drops of one reason."""


class DropLog:
    def __init__(
        self,
        logger: logging.Logger,
        prefix: str,
        noun: str,
        interval: float = DROP_LOG_INTERVAL,
        counts: Counter[str] | None = None,
    ) -> None:
        """Lines read `<prefix>: dropped <what> (<reason>): <detail>` and `<prefix>: dropped N <noun> ...`;
        `counts`: the counter to add to (the caller's statistics), else a new one."""
        self.counts: Counter[str] = counts if counts is not None else Counter()
        self._log, self._prefix, self._noun, self._interval = logger, prefix, noun, interval
        self._since: dict[str, float] = {}
        """Per reason with a log line in the last interval: when that interval began."""
        self._unlogged: Counter[str] = Counter()
        self._unlogged_last: dict[str, str] = {}

    def logs_at_once(self, reason: str) -> bool:
        """Would a drop of `reason` now get its own line (not only a count)?"""
        return reason not in self._since

    def drop(self, reason: str, now: float, what: str, detail: str) -> None:
        self.counts[reason] += 1
        if reason in self._since:
            self._unlogged[reason] += 1
            self._unlogged_last[reason] = f"{what}: {detail}"
        else:
            self._since[reason] = now
            self._log.warning("%s: dropped %s (%s): %s", self._prefix, what, reason, detail)

    def flush(self, now: float) -> None:
        """Sum up each reason's drops not logged in an interval that has ended; a quiet reason logs afresh.

        Call it often (on every message, every loop), so a flood that stops is still summed up."""
        for reason, since in list(self._since.items()):
            if now - since < self._interval:
                continue
            count = self._unlogged.pop(reason, 0)
            if count:
                self._log.warning(
                    "%s: dropped %d %s (%s) in the last %.0f s, the last: %s",
                    self._prefix,
                    count,
                    self._noun,
                    reason,
                    now - since,
                    self._unlogged_last.pop(reason),
                )
                self._since[reason] = now
            else:
                del self._since[reason]
