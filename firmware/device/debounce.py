"""Delayed-on / delayed-off debouncing of a raw boolean sensor reading.

Pure logic, shared by the board and the zone simulator (CPython): no I/O, no clock of its own; every call takes
the caller's monotonic `now_ms`, so a simulated clock drives it exactly like the real one.

Why both delays: a PIR fires on a person walking past (a short "occupied" must not block a corridor for the
robot), and it drops out while a person stands still (a short "free" must not clear it either).
"""


class Debouncer:
    """Output follows the raw input only after the input has held its new value for the matching delay."""

    def __init__(self, on_delay_ms: int, off_delay_ms: int, initial: bool = False) -> None:
        self.on_delay_ms = on_delay_ms
        self.off_delay_ms = off_delay_ms
        self.state = initial
        # When the raw input started to differ from `state`; None while it agrees.
        self._since = None  # type: int | None

    def update(self, raw: bool, now_ms: int) -> bool:
        """Feed one reading taken at `now_ms`; returns the debounced state (True: occupied)."""
        if raw == self.state:
            self._since = None
            return self.state
        if self._since is None:
            self._since = now_ms
        delay = self.on_delay_ms if raw else self.off_delay_ms
        if now_ms - self._since >= delay:
            self.state = raw
            self._since = None
        return self.state

    def pending_ms(self, now_ms: int) -> int:
        """How long until a pending change takes effect (-1 if none): lets a simulator schedule its next step."""
        if self._since is None:
            return -1
        delay = self.off_delay_ms if self.state else self.on_delay_ms
        left = delay - (now_ms - self._since)
        return left if left > 0 else 0
