"""Where components take their time from, so the same code runs in real time and in lock-step simulated time."""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    """Seconds on the site clock: Unix time in a real deployment, simulated time in simulation.

    Times that cross hosts (operator block expiry, status stamps) are read on this clock, so every host of a
    real deployment must share it: Unix time, with the hosts' clocks kept in step (NTP).
    """

    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...


class WallClock:
    """Real time as Unix time, so a stamp or an expiry written on one host means the same on another.

    Read once from the system clock, then advanced by the monotonic clock: a step of the system clock while the
    process runs (NTP, an operator) cannot send it backwards or make intervals jump.
    """

    def __init__(self) -> None:
        self._offset = time.time() - time.monotonic()

    def now(self) -> float:
        return self._offset + time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class SimClock:
    """Simulated time that moves only when the driver advances it: runs as fast as the machine allows.

    `sleep` advances time too, so a component written for real time still works when driven alone.
    """

    def __init__(self, start: float = 0.0) -> None:
        self._now = start
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._now

    def advance(self, seconds: float) -> float:
        if seconds < 0:
            raise ValueError("simulated time does not run backwards")
        with self._lock:
            self._now += seconds
            return self._now

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.advance(seconds)
