"""Test-only: the ESP8266's `machine.Timer` (soft timers) and `machine.reset`; `install()` puts them on the
machine stub (drivers call it when they need them).

Timer callbacks run when `_run_timers()` is called: where the ESP8266 runs its soft timers, in any wait
(mp_handle_pending while the REPL waits for input, while lwIP resolves a name...), so a driver calls it in its
waits. `reset()` ends the process; the host (firmware/unix_board.py) starts it again, as the board reboots.
"""

import sys
import time

now = time.ticks_ms
"""The clock timers follow; a simulated-time driver replaces it."""
_timers = []


class Timer:
    ONE_SHOT = 0
    PERIODIC = 1

    def __init__(self, id=-1):
        self._due = 0

    def init(self, mode=1, period=-1, callback=None):
        self._mode = mode
        self._period = period
        self._cb = callback
        self._due = time.ticks_add(now(), period)
        if self not in _timers:
            _timers.append(self)

    def deinit(self):
        if self in _timers:
            _timers.remove(self)


def _run_timers():
    for t in list(_timers):
        if time.ticks_diff(now(), t._due) >= 0:
            if t._mode == Timer.PERIODIC:
                t._due = time.ticks_add(t._due, t._period)
            else:
                t.deinit()
            t._cb(t)


def reset():
    """A hard reset: the process ends and the host starts it again."""
    sys.exit(75)



def install():
    import machine

    machine.Timer = Timer  # pyright: ignore[reportAttributeAccessIssue]
    machine.reset = reset
