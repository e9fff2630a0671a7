"""Test-only stand-in for the ESP8266 `machine` module, for the MicroPython unix port (on MICROPYPATH).

Input pin N reads the text ("0"/"1") of the file `$WSNAV_PINS/N` (missing: 0), so a test flips a sensor by
writing one file; `time_pulse_us` returns the integer in `$WSNAV_PINS/N.pulse` (missing: -1, a timeout), an
HC-SR04 echo. The WDT only counts feeds. No Timer or reset here: the drivers that need them install
soft_timers' (only then, so the heap measured by run_node and longrun does not pay for them). Kept small: on the
38 KiB heap this costs what the board never pays.
"""

import os

_DIR = os.getenv("WSNAV_PINS") or "/tmp/wsnav-pins"


_BUF = bytearray(12)


def _read(name, default):
    """Into one buffer: read() would allocate 256 bytes per call, which the board's pins never cost."""
    try:
        with open(_DIR + "/" + name, "rb") as f:
            n = f.readinto(_BUF)
        return int(bytes(_BUF[:n]))
    except (OSError, ValueError):
        return default


class Pin:
    IN = 0
    OUT = 1
    PULL_UP = 1
    """The ESP8266's value; the stub reads a pin the same with or without it."""

    def __init__(self, id, mode=0, pull=-1, value=0):
        self.id = id
        self.mode = mode
        self.out = value

    def value(self, v=-1):
        if v >= 0:
            self.out = v
        elif self.mode == 0:
            return _read(str(self.id), 0)
        return self.out


def time_pulse_us(pin, level, timeout_us=1000000):
    return _read(str(pin.id) + ".pulse", -1)


def reset_cause():
    return _read("reset_cause", 0)


class WDT:
    feeds = 0

    def __init__(self, id=0, timeout=5000):
        pass

    def feed(self):
        WDT.feeds += 1
