"""Board I/O for a digital zone sensor (PIR, IR break beam): one machine.Pin. The decision is sensing.py's.

`reading()` gives the raw (undebounced) level as a bool: occupied or not.
"""

from machine import Pin

from sensing import digital_occupied


class DigitalSensor:
    """PIR (high while motion) or IR break-beam receiver; `invert` for active-low modules. `pull` turns on the
    pin's internal pull-up: an IR receiver's open-collector output needs one (GPIO16 has none: the config refuses
    it for an IR beam)."""

    def __init__(self, pin: int, invert: bool = False, pull: bool = False) -> None:
        self._pin = Pin(pin, Pin.IN, Pin.PULL_UP) if pull else Pin(pin, Pin.IN)
        self.invert = invert

    def reading(self, feed=None) -> bool:
        """The pin's level as occupied or not; one pin read, so `feed` (for slow sensors) is not needed."""
        return digital_occupied(self._pin.value(), self.invert)
