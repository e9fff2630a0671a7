"""The simulated sensor's detection delay: fixed by default, spread per node with jitter, and seeded."""

from __future__ import annotations

import random

import pytest

from tests.conftest import SITES
from wsnav.schemas.site import load_site
from wsnav.zone_sim.sensor_model import SensorSettings, SimulatedSensor
from wsnav.zone_sim.world import World

PIR = {"zone": "z1", "sensor_type": "pir", "invert": False, "threshold_mm": 0, "samples": 1}


def first_seen(sensor: SimulatedSensor, step: float = 0.01) -> float:
    t = 0.0
    while not sensor.occupied(t):
        t = round(t + step, 6)
    return t


@pytest.fixture
def world() -> World:
    w = World(load_site(SITES / "school").spec)
    w.place("z1", 0.0)
    return w


def test_each_node_sees_the_obstacle_after_its_own_seeded_delay(world: World) -> None:
    settings = SensorSettings(detection_delay_s=0.5, detection_jitter_s=1.5)
    seen = [first_seen(SimulatedSensor(PIR, world, settings, random.Random(f"s/{n}"))) for n in range(12)]
    assert all(0.5 <= t <= 2.01 for t in seen)
    assert max(seen) - min(seen) > 0.5, "nodes differ"
    again = first_seen(SimulatedSensor(PIR, world, settings, random.Random("s/3")))
    assert again == seen[3], "the same seed, the same delay"


def test_without_jitter_every_node_waits_exactly_the_delay(world: World) -> None:
    settings = SensorSettings(detection_delay_s=0.5)
    seen = {first_seen(SimulatedSensor(PIR, world, settings, random.Random(n))) for n in range(5)}
    assert seen == {0.5}
    with pytest.raises(ValueError, match="jitter"):
        SensorSettings(detection_jitter_s=-1.0)
