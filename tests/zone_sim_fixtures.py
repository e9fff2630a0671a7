"""What the zone simulator tests share: a tiny site with short heartbeats, a subscriber, lock-step driving."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.runtime.bus import Message
from wsnav.runtime.clock import Clock, SimClock
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.zone_sim.simulator import ZoneSimulator

SITE = "tiny"
HEARTBEAT_S = 1.0
NODES: list[dict[str, Any]] = [
    {"id": "n1", "zone": "z1", "sensor": {"type": "pir", "pin": 5}, "on_delay_ms": 200, "off_delay_ms": 400},
    {"id": "n2", "zone": "z2", "sensor": {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 14}},
    {
        "id": "n3",
        "zone": "z1",
        "sensor": {"type": "ir_beam", "pin": 4, "invert": True},
        "on_delay_ms": 200,
        "off_delay_ms": 400,
    },
]


def sim_site(directory: Path) -> Path:
    """tiny_site with three nodes (z1 watched by a PIR and an inverted IR beam) and 1 s heartbeats."""
    return tiny_site(directory, heartbeat_s=HEARTBEAT_S, nodes=NODES)


def subscriber(broker: BrokerThread, clock: Clock, ident: str = "robot1") -> MqttBus:
    """A robot-credential bus on zone states, node statuses and the simulated world, stamped by `clock`."""
    bus = connect_with_credentials(broker.host, broker.port, broker.credentials(ident), clock=clock)
    for flt in (topics.all_zone_states(SITE), topics.all_node_statuses(SITE), topics.sim_world(SITE)):
        bus.subscribe(flt)
    time.sleep(0.3)  # the SUBACKs: the bus subscribes asynchronously
    return bus


def drive(sim: ZoneSimulator, clock: SimClock, until: float, dt: float = 0.05, io_s: float = 0.003) -> None:
    """Lock-step: advance simulated time by `dt` and step the simulator, giving the sockets `io_s` each step."""
    while clock.now() < until - 1e-9:
        clock.advance(dt)
        sim.step(io_timeout_s=io_s)


def wait_online(sim: ZoneSimulator, clock: SimClock, count: int, timeout_s: float = 30.0) -> None:
    """Step (simulated time moves slowly) until `count` nodes have their CONNACK."""
    deadline = time.monotonic() + timeout_s
    while sim.online_count < count:
        if time.monotonic() > deadline:
            raise AssertionError(f"only {sim.online_count} of {count} nodes online after {timeout_s:g} s")
        clock.advance(0.001)
        sim.step(io_timeout_s=0.01)


def settle(bus: MqttBus, quiet_s: float = 0.5, timeout_s: float = 10.0) -> list[Message]:
    """Everything the bus receives until it has been quiet for `quiet_s` real seconds."""
    got: list[Message] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not bus.wait(quiet_s):
            break
        got += bus.poll()
    return got + bus.poll()
