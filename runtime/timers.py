"""Fixed-rate timers in the caller's time, so lock-step simulation and real time drive them the same way."""

from __future__ import annotations

import math


class Every:
    """A fixed-rate timer: `due(now)` is true once per period (0 Hz: never)."""

    def __init__(self, rate_hz: float) -> None:
        self.period = 1.0 / rate_hz if rate_hz > 0 else math.inf
        self.next = -math.inf

    def start(self, now: float) -> None:
        self.next = now + self.period

    def due(self, now: float) -> bool:
        if now < self.next:
            return False
        # Late by more than a period (a stalled loop): skip the missed ticks rather than bursting them.
        self.next = self.next + self.period if now - self.next < self.period else now + self.period
        return True
