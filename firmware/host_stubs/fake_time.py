"""Test-only: the ESP8266's `time` module on a simulated clock. A driver puts it in `sys.modules["time"]` before it
imports the firmware, so every `time.ticks_ms()`, `ticks_diff`, `ticks_add` and sleep of the firmware (and of
soft_timers) is this one: ticks wrap at 2**30 ms as the board's do (its small-int limit, 12.4 days), not at the
unix port's 2**62, and time passes only when a sleep or the driver advances it.
"""

PERIOD = 1 << 30
_MASK = PERIOD - 1
_HALF = PERIOD >> 1

t = 0
"""Simulated milliseconds since the driver started (the host's count: unbounded, never seen by the firmware)."""
start = 0
"""The tick count at t = 0: a driver starts near the wrap to cross it early."""


def ticks_ms() -> int:
    return (start + t) & _MASK


def ticks_diff(a: int, b: int) -> int:
    d = (a - b) & _MASK
    return d - PERIOD if d >= _HALF else d


def ticks_add(a: int, delta: int) -> int:
    return (a + delta) & _MASK


def advance(ms: int) -> None:
    """Let `ms` pass (a driver replaces this to run its soft timers on the way)."""
    global t
    t += ms


def sleep_ms(ms: int) -> None:
    advance(ms)


def sleep_us(us: int) -> None:
    advance(us // 1000)
