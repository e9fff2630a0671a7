"""Capped exponential backoff with jitter for Wi-Fi and broker reconnects.

Pure logic (MicroPython and CPython). Jitter matters: after a broker restart a whole building of nodes would
otherwise reconnect in lock-step and hammer the Raspberry Pi at the same instants. The random source is passed
in (`rand16`: returns an int in [0, 65535]) so tests and the simulator are deterministic.
"""


class Backoff:
    """Delay n is uniform in [d/2, d] where d = min(cap, base * 2**n) ("equal jitter": never zero, never above cap)."""

    def __init__(self, base_ms: int, cap_ms: int, rand16) -> None:  # rand16: () -> int
        self.base_ms = base_ms
        self.cap_ms = cap_ms
        self._rand16 = rand16
        self.attempts = 0

    def reset(self) -> None:
        """Call after a success: the next failure starts again from `base_ms`."""
        self.attempts = 0

    def next_delay_ms(self) -> int:
        """The wait before the next attempt; each call counts one more failed attempt."""
        d = self.base_ms
        n = self.attempts
        while n > 0 and d < self.cap_ms:
            d *= 2
            n -= 1
        if d > self.cap_ms:
            d = self.cap_ms
        self.attempts += 1
        half = d // 2
        return half + (half * (self._rand16() & 0xFFFF)) // 0xFFFF
