"""Board I/O for the HC-SR04 distance sensor: machine.Pin and machine.time_pulse_us. Decisions live in sensing.py.

`reading()` gives the raw (undebounced) level: debounce.CLEAR, BLOCKED or CAUTION.
"""

import time

from machine import Pin, time_pulse_us

from sensing import ultrasonic_level

ECHO_TIMEOUT_US = 30000
"""~5 m round trip: beyond the HC-SR04's range, and short enough that N pings fit well inside the watchdog."""
PING_GAP_MS = 25
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

    def ping_us(self) -> int:
        """One measurement: echo pulse length in us, negative on timeout (no echo)."""
        self._trig.value(0)
        time.sleep_us(2)
        self._trig.value(1)
        time.sleep_us(10)
        self._trig.value(0)
        return time_pulse_us(self._echo, 1, ECHO_TIMEOUT_US)

    def reading(self) -> int:
        pulses = self._pulses
        for i in range(len(pulses)):
            if i:
                time.sleep_ms(PING_GAP_MS)
            pulses[i] = self.ping_us()
        return ultrasonic_level(pulses, self.threshold_mm, self.caution_mm)
