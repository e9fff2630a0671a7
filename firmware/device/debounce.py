"""Delayed-on / delayed-off debouncing of a raw sensor level: clear, blocked or caution.

Pure logic, shared by the board and the zone simulator (CPython): no I/O, no clock of its own; every call takes
the caller's `now_ms`, so a simulated clock drives it exactly like the real one. `now_ms` is a tick count that
may wrap (the board's `time.ticks_ms()`, period 2**30 ms: 12.4 days); times are only ever compared with
`ticks_diff` and moved with `ticks_add`, so every value stays a small int (no heap) for as long as the board runs.

Why both delays: a PIR fires on a person walking past (a short "occupied" must not block a corridor for the
robot), and it drops out while a person stands still (a short "free" must not clear it either). Levels are
ordered clear < caution < blocked: a move to a more severe level waits `on_delay_ms`, a move to a less severe
one `off_delay_ms`. A bool reading is a two-level sensor's level (False: CLEAR, True: BLOCKED).

While a change is pending the readings may wander on the same side of the current state (an object right at
the blocking distance reads blocked, caution, blocked...). When the delay is over the state becomes the level
that held the whole time: the least severe one seen going up, the most severe going down. So a reading that
flickers between two levels can neither keep a zone clear nor clear it early.
"""


def ticks_diff(a: int, b: int) -> int:
    """a - b on a clock that wraps at 2**30 ms, as the board's `time.ticks_diff` computes it (right while the
    true difference is under 2**29 ms). Ours, not the board's: the zone simulator runs this module on CPython,
    and the unix port's ticks wrap at 2**62; any clock whose period is a multiple of 2**30 gives right answers."""
    d = (a - b) & 0x3FFFFFFF
    return d - 0x40000000 if d >= 0x20000000 else d


def ticks_add(a: int, delta: int) -> int:
    """`a` moved by `delta` ms on the same wrapping clock (node_logic and app use these two too)."""
    return (a + delta) & 0x3FFFFFFF


CLEAR = 0
BLOCKED = 1
CAUTION = 2
_RANK = (0, 2, 1)
"""Severity of each level, indexed by level."""


class Debouncer:
    """Output follows the raw level only after the raw level has stayed on one side of it for the matching delay."""

    def __init__(self, on_delay_ms: int, off_delay_ms: int, initial: int = CLEAR) -> None:
        self.on_delay_ms = on_delay_ms
        self.off_delay_ms = off_delay_ms
        self.state = int(initial)
        # When the raw level left `state` (None while it agrees), and the level that has held since then.
        self._since = None  # type: int | None
        self._held = CLEAR

    def update(self, raw, now_ms: int) -> int:
        """Feed one reading (a level, or a bool) taken at `now_ms`; returns the debounced level."""
        raw = int(raw)
        state = self.state
        if raw == state:
            self._since = None
            return state
        up = _RANK[raw] > _RANK[state]
        since = self._since
        held = self._held
        if since is None or up != (_RANK[held] > _RANK[state]):
            since = now_ms  # a new change, or one the other way: its delay starts now
            held = raw
        elif up == (_RANK[raw] < _RANK[held]):
            held = raw  # nearer to the current state: only this much has held throughout
        if ticks_diff(now_ms, since) >= (self.on_delay_ms if up else self.off_delay_ms):
            self.state = held
            # The reading may still differ from the new state (it went further): that change starts now.
            since = None if raw == held else now_ms
            held = raw
        self._since = since
        self._held = held
        return self.state

    def pending_ms(self, now_ms: int) -> int:
        """How long until a pending change takes effect (-1 if none): lets a simulator schedule its next step."""
        since = self._since
        if since is None:
            return -1
        delay = self.on_delay_ms if _RANK[self._held] > _RANK[self.state] else self.off_delay_ms
        left = delay - ticks_diff(now_ms, since)
        return left if left > 0 else 0
