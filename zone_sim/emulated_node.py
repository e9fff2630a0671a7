"""One emulated zone node: the firmware's NodeLogic fed by a simulated sensor, sending through its own MQTT link.

It follows firmware/device/app.py step for step: a reading every loop period (50 ms on the board), the
debouncer and heartbeat decided by NodeLogic, birth `online` + current state after every connect, the last will
`offline`, reconnects spaced by the firmware's Backoff (500 ms .. 30 s with jitter), a fresh seq base from
`getrandbits(20)` at every boot, and the firmware's diagnostics (`nodes/<node>/info`) after every connect and
every few minutes, without RSSI or free heap (nothing to measure). Time is the simulator's clock, in the board's milliseconds since boot.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Any

from wsnav.zone_sim.firmware_modules import POWER_ON_RESET, SEQ_BASE_BITS, Backoff, NodeLogic, diagnostics
from wsnav.zone_sim.links import LinkAddress, LinkLoop, NodeLink
from wsnav.zone_sim.sensor_model import SimulatedSensor

BROKER_BACKOFF_BASE_MS = 500
BROKER_BACKOFF_CAP_MS = 30000
"""app.py: `Backoff(500, 30000, _rand16)` for broker reconnects."""


class Power(Enum):
    ON = "on"
    DEAD = "dead"
    """Killed: no readings, no traffic, until rebooted."""


@dataclass(frozen=True)
class Sent:
    """One publication as it left the node: what the firmware asked to send, and when (simulator clock)."""

    node: str
    t: float
    topic: str
    payload: bytes
    retain: bool
    qos: int


class EmulatedNode:
    def __init__(
        self,
        cfg: dict[str, Any],
        sensor: SimulatedSensor,
        link_loop: LinkLoop,
        broker: tuple[str, int],
        rng: random.Random,
        sample_ms: int,
        on_sent: Callable[[Sent], None],
        on_event: Callable[[str, str], None],
    ) -> None:
        """`cfg` is the node's config.json parsed by the firmware's own nodeconfig.parse."""
        self.cfg = cfg
        self.id: str = cfg["node"]
        self.zone: str = cfg["zone"]
        self.sensor = sensor
        self.sample_ms = sample_ms
        self._rng = rng
        self._loop = link_loop
        self._broker = broker
        self._on_sent = on_sent
        self._on_event = on_event
        self.power = Power.DEAD
        self.boots = 0
        self.connects = 0
        self.logic = self._new_logic()
        self._boot_connects = 0
        self._info_due_t = 0.0
        self._last_error: str | None = None
        self.link: NodeLink | None = None
        self._boot_t = 0.0
        self._next_sample_t = 0.0
        self._next_attempt_t: float | None = None
        self._now = 0.0
        self._backoff = Backoff(
            BROKER_BACKOFF_BASE_MS, BROKER_BACKOFF_CAP_MS, lambda: self._rng.getrandbits(16)
        )

    def _new_logic(self) -> Any:
        c = self.cfg
        return NodeLogic(
            c["site"],
            c["zone"],
            c["node"],
            c["on_delay_ms"],
            c["off_delay_ms"],
            c["heartbeat_ms"],
            self._rng.getrandbits(SEQ_BASE_BITS),
        )

    def _ms(self, t: float) -> int:
        """The board's clock: milliseconds since this boot."""
        return round((t - self._boot_t) * 1000)

    # -- power ---------------------------------------------------------------------------------------------
    def boot(self, t: float) -> None:
        """Power on (or reboot): fresh logic and seq base, first reading now, connect at once."""
        self.boots += 1
        if self.boots > 1:
            self.logic = self._new_logic()
            self._boot_connects = self.connects
        self._last_error = None
        self._backoff.reset()
        self.power = Power.ON
        self._boot_t = t
        self._now = t
        # Spread the boards' loop phases so 1000 nodes do not all read their sensor on the same millisecond.
        self._next_sample_t = t + self._rng.random() * self.sample_ms / 1000
        self._next_attempt_t = t

    def kill(self, hang: bool = False) -> None:
        """Power cut: the link dies without DISCONNECT (`hang`: the socket stays open, silent, until the broker's
        keepalive check drops it)."""
        self.power = Power.DEAD
        self._next_attempt_t = None
        if self.link is not None:
            if hang:
                self.link.hang()
            else:
                self.link.drop()
        self.logic.on_disconnect()

    def reboot(self, t: float) -> None:
        """A power cycle: whatever link there was dies uncleanly, then the board boots again."""
        if self.link is not None:
            self.link.drop()
        self.link = None
        self.logic.on_disconnect()
        self.boot(t)

    def power_off(self) -> None:
        """End of simulation: the link is cut (the broker publishes `offline`, as for a real board)."""
        self.kill()
        if self.link is not None:
            self.link.drop()

    # -- the loop ----------------------------------------------------------------------------------------
    @property
    def online(self) -> bool:
        return self.power is Power.ON and self.link is not None and self.link.connected

    def advance(self, now: float) -> None:
        """Run every loop iteration due up to `now` (readings at their own times), then try to connect."""
        if self.power is not Power.ON:
            return
        self._now = now
        period = self.sample_ms / 1000
        logic = self.logic
        while self._next_sample_t <= now:
            t = self._next_sample_t
            occupied = self.sensor.occupied(t)
            msg = logic.step(occupied, self._ms(t))
            if msg is not None:
                self._send(msg, t)
            if logic.connected and t >= self._info_due_t:
                self._send_info(t)
            self._next_sample_t = t + period

    @property
    def wants_connect(self) -> bool:
        """A connect attempt is due (the simulator paces attempts so a 1000-node start does not flood the broker)."""
        return (
            self.power is Power.ON and self._next_attempt_t is not None and self._now >= self._next_attempt_t
        )

    def connect(self, now: float) -> None:
        self._next_attempt_t = None
        c = self.cfg
        address = LinkAddress(
            host=self._broker[0],
            port=self._broker[1],
            client_id=self.id,
            username=c["username"],
            password=c["password"],
            keepalive_s=c["keepalive_s"],
            will=self.logic.will(),
        )
        if self.link is not None:
            self.link.drop()
        self.link = NodeLink(self._loop, address, self._link_up, self._link_down)
        try:
            self.link.open()
        except OSError as exc:
            self._link_down(f"cannot connect: {exc}")

    def _link_up(self) -> None:
        if self.power is not Power.ON:
            return
        self.connects += 1
        self._backoff.reset()
        for msg in self.logic.on_connect(self._ms(self._now)):
            self._send(msg, self._now)
        self._send_info(self._now)

    def _send_info(self, t: float) -> None:
        """The firmware's diagnostics, as app.py sends them (without what only a board can measure): after each
        connect and every diagnostics.INFO_PERIOD_MS."""
        connects = self.connects - self._boot_connects
        topic, text, retain, qos = diagnostics.info(
            self.logic, self._ms(t) // 1000, connects, POWER_ON_RESET, error=self._last_error
        )
        self._send((topic, text.encode(), retain, qos), t)
        self._info_due_t = t + diagnostics.INFO_PERIOD_MS / 1000

    def _link_down(self, why: str) -> None:
        self.logic.on_disconnect()
        self._last_error = why
        if self.power is not Power.ON:
            return
        self._on_event(self.id, why)
        self._next_attempt_t = self._now + self._backoff.next_delay_ms() / 1000

    def _send(self, msg: tuple[str, bytes, bool, int], t: float) -> None:
        topic, payload, retain, qos = msg
        link = self.link
        if link is not None and link.publish(topic, payload, retain, qos):
            self._on_sent(Sent(self.id, t, topic, payload, retain, qos))

    @property
    def connecting(self) -> bool:
        return (
            self.power is Power.ON and self.link is not None and self.link.active and not self.link.connected
        )
