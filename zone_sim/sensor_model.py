"""A node's sensor bound to the simulated world: what its pin (or its echo pulses) would read at a given time.

The truth is "an obstacle stands in my zone"; the sensor sees it `detection_delay_s` late (a PIR's warm-up, a
person walking into the beam) and, with `miss_rate`, a single reading drops out as a PIR does while a person
stands still. The raw signal then goes through the firmware's own `sensing` functions, so an inverted IR beam
or an HC-SR04 threshold is read exactly as on the board; the firmware's debouncer does the rest.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Any

from wsnav.zone_sim.firmware_modules import NO_ECHO_MM, digital_occupied, ultrasonic_occupied
from wsnav.zone_sim.world import World

SOUND_US_PER_MM = 2000 / 343
"""Round-trip echo microseconds per millimetre of distance (the inverse of sensing.echo_us_to_mm)."""


@dataclass(frozen=True)
class SensorSettings:
    detection_delay_s: float = 0.5
    """How long after an obstacle appears (or leaves) the sensor's raw output follows."""
    miss_rate: float = 0.0
    """Probability that one reading of an occupied zone reads free (seeded per node)."""
    detection_jitter_s: float = 0.0
    """Each sensor's delay is detection_delay_s plus a uniform draw in [0, this] (seeded per node): sensors
    differ (a PIR's warm-up, where in the beam a person stands)."""

    def __post_init__(self) -> None:
        if not self.detection_delay_s >= 0 or not self.detection_jitter_s >= 0:
            raise ValueError("detection_delay_s and detection_jitter_s must be >= 0")
        if not 0.0 <= self.miss_rate < 1.0:
            raise ValueError("miss_rate must be in [0, 1)")


class SimulatedSensor:
    """`occupied(t)` is the raw (undebounced) reading the node's sensor module would return at time `t`."""

    def __init__(
        self, cfg: dict[str, Any], world: World, settings: SensorSettings, rng: random.Random
    ) -> None:
        self.zone: str = cfg["zone"]
        self.kind: str = cfg["sensor_type"]
        self.invert: bool = cfg["invert"]
        self.threshold_mm: int = cfg["threshold_mm"]
        self.samples: int = cfg["samples"]
        self.settings = settings
        self._world = world
        self._rng = rng
        self.delay_s = settings.detection_delay_s + (
            rng.uniform(0.0, settings.detection_jitter_s) if settings.detection_jitter_s > 0 else 0.0
        )
        """This sensor's detection delay."""
        self.readings = 0
        self.misses = 0

    def truth(self, t: float) -> bool:
        """What the sensor would report with no misses: the world as it was `delay_s` ago."""
        return self._world.was_blocked(self.zone, t - self.delay_s)

    def occupied(self, t: float) -> bool:
        self.readings += 1
        present = self.truth(t)
        if present and self.settings.miss_rate > 0 and self._rng.random() < self.settings.miss_rate:
            self.misses += 1
            present = False
        if self.kind == "hcsr04":
            # An obstacle stands at half the threshold; a free corridor gives no echo within range.
            distance_mm = self.threshold_mm // 2 if present else NO_ECHO_MM
            pulse = int(distance_mm * SOUND_US_PER_MM) + 1 if present else -1
            return ultrasonic_occupied([pulse] * self.samples, self.threshold_mm)
        level = int(present != self.invert)  # what the pin reads: active-low modules invert
        return digital_occupied(level, self.invert)
