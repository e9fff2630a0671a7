"""Board I/O for the HC-SR04 distance sensor: machine.Pin and machine.time_pulse_us. Decisions live in sensing.py.

`reading()` gives the raw (undebounced) level: debounce.CLEAR, BLOCKED or CAUTION.
"""

import time

from machine import Pin, time_pulse_us
from micropython import const

from sensing import ultrasonic_level

_ECHO_TIMEOUT_US = const(30000)
"""~5 m round trip: beyond the HC-SR04's range. `time_pulse_us` applies it twice (waiting for the echo to start,
then for it to end), so a ping without echo costs up to 60 ms: 15 of them, with the gaps, ~1.25 s, which is why
`reading` feeds the watchdog between pings."""
_PING_GAP_MS = const(25)
"""Let the previous ping's echoes die out before the next one (cross-talk from the walls of a corridor)."""


class Ultrasonic:
    """HC-SR04: 10 us trigger pulse, echo high for the round trip; median of `samples` pings; blocked nearer
    than `threshold_mm`, caution nearer than `caution_mm` (0: never caution)."""

    def __init__(
        self, trigger_pin: int, echo_pin: int, threshold_mm: int, samples: int = 5, caution_mm: int = 0
    ) -> None:
        self._trig = Pin(trigger_pin, Pin.OUT)
        self._trig.value(0)
        self._echo = Pin(echo_pin, Pin.IN)
        self.threshold_mm = threshold_mm
        self.caution_mm = caution_mm
        self._pulses = [0] * samples

    def reading(self, feed=None) -> int:
        """`samples` pings (10 us trigger pulse, then the echo's length in us, negative on timeout: no echo), one
        function rather than a method per ping: each function is bytecode kept on the 38 KiB heap. `feed` (the
        node's watchdog feed) is called before each ping: at most ~85 ms pass between two calls."""
        trig = self._trig
        echo = self._echo
        pulses = self._pulses
        for i in range(len(pulses)):
            if feed is not None:
                feed()
            if i:
                time.sleep_ms(_PING_GAP_MS)
            trig.value(0)
            time.sleep_us(2)
            trig.value(1)
            time.sleep_us(10)
            trig.value(0)
            pulses[i] = time_pulse_us(echo, 1, _ECHO_TIMEOUT_US)
        return ultrasonic_level(pulses, self.threshold_mm, self.caution_mm)
