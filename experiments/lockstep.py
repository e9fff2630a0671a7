"""Lock-step delivery over a real broker: what was published for the agent is known, and simulated time does
not move on until the agent's bus has handed it over, so what the agent sees at each simulated instant does
not depend on the machine's speed (or on how many other runs share its cores).
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable

from wsnav.runtime.bus import Bus, Message
from wsnav.schemas.topics import topic_matches

REAL_TIMEOUT_S = 30.0


class DeliveryTimeout(RuntimeError):
    """The broker did not deliver a message within REAL_TIMEOUT_S real seconds."""


class Deliveries:
    """The multiset of (topic, payload) published for the agent and not yet polled by it."""

    def __init__(self, filters: list[str]) -> None:
        self.filters = filters
        self._pending: Counter[tuple[str, bytes]] = Counter()

    def expect(self, topic: str, payload: bytes) -> None:
        if any(topic_matches(f, topic) for f in self.filters):
            self._pending[(topic, payload)] += 1

    def delivered(self, messages: list[Message]) -> None:
        for m in messages:
            key = (m.topic, m.payload)
            if self._pending[key] > 0:
                self._pending[key] -= 1
        self._pending += Counter()  # drop zero counts

    @property
    def pending(self) -> int:
        return sum(self._pending.values())


class WatchedBus:
    """The agent's bus, telling `Deliveries` what has reached it.

    `fetch` takes what the broker has delivered so far into a buffer; the agent's `poll` sees only that buffer.
    So when the agent steps at a simulated instant it sees exactly what was published for it up to then, never
    a message that happened to arrive early or late in real time (which would let the machine's load decide
    whether a control tick runs on the old path or the new one).
    """

    def __init__(self, inner: Bus, deliveries: Deliveries) -> None:
        self.inner = inner
        self.deliveries = deliveries
        self._fetched: list[Message] = []
        self.tap: Callable[[list[Message]], None] | None = None
        """Sees every batch the agent polls (the run's record keeps them)."""

    def fetch(self) -> None:
        got = self.inner.poll()
        self.deliveries.delivered(got)
        self._fetched.extend(got)

    def publish(self, topic: str, payload: bytes, *, qos: int = 1, retain: bool = False) -> None:
        self.inner.publish(topic, payload, qos=qos, retain=retain)

    def subscribe(self, topic_filter: str, qos: int = 1) -> None:
        self.inner.subscribe(topic_filter, qos)

    def poll(self, max_messages: int | None = None) -> list[Message]:
        n = len(self._fetched) if max_messages is None else max_messages
        got, self._fetched = self._fetched[:n], self._fetched[n:]
        if got and self.tap is not None:
            self.tap(got)
        return got

    def wait(self, timeout_s: float) -> bool:
        return self.inner.wait(timeout_s)

    @property
    def connected(self) -> bool:
        return self.inner.connected

    def close(self) -> None:
        self.inner.close()


class Audience(Deliveries):
    """Every agent's `Deliveries` in a lock-step fleet: a message published is expected by each agent whose
    subscriptions match it (an agent's own status by no one: it does not subscribe to it)."""

    def __init__(self) -> None:
        super().__init__([])
        self.members: list[Deliveries] = []

    def expect(self, topic: str, payload: bytes) -> None:
        for member in self.members:
            member.expect(topic, payload)

    def delivered(self, messages: list[Message]) -> None:
        return  # each member is told by its own agent's bus

    @property
    def pending(self) -> int:
        return sum(member.pending for member in self.members)


class FleetBus(WatchedBus):
    """One agent's bus in a lock-step fleet: it watches its own deliveries and announces what it publishes
    (its status) to the audience, so simulated time waits until the other agents have it."""

    def __init__(self, inner: Bus, deliveries: Deliveries, audience: Audience) -> None:
        super().__init__(inner, deliveries)
        self.audience = audience

    def publish(self, topic: str, payload: bytes, *, qos: int = 1, retain: bool = False) -> None:
        self.audience.expect(topic, payload)
        super().publish(topic, payload, qos=qos, retain=retain)


class ExpectingBus(WatchedBus):
    """A publisher's bus (the zone simulator's world publisher) announcing what it sends to `Deliveries`."""

    def publish(self, topic: str, payload: bytes, *, qos: int = 1, retain: bool = False) -> None:
        self.deliveries.expect(topic, payload)
        super().publish(topic, payload, qos=qos, retain=retain)


def settle(
    done: Callable[[], bool], poke: Callable[[], None], wait: Callable[[float], object], what: str
) -> None:
    """Call `poke` (step at the current simulated instant) until `done()`; raise after a real-time timeout."""
    deadline = time.monotonic() + REAL_TIMEOUT_S
    while True:
        poke()
        if done():
            return
        if time.monotonic() > deadline:
            raise DeliveryTimeout(f"timed out waiting for {what}")
        wait(0.002)
