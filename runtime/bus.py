"""The publish/subscribe interface components talk through: MQTT in production, the same calls in tests.

Inbound messages are queued and handed out by `poll`, on the caller's thread: a component's logic stays
single-threaded and can be stepped in lock-step simulated time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol


@dataclass(frozen=True, slots=True)
class Message:
    topic: str
    payload: bytes
    retain: bool
    received_at: float
    """Clock time at which the bus took the message in: what freshness is judged by."""


@dataclass(frozen=True, slots=True)
class Will:
    """Published by the broker when the link dies without a clean disconnect."""

    topic: str
    payload: bytes
    qos: int = 1
    retain: bool = True


class Bus(Protocol):
    def publish(self, topic: str, payload: bytes, *, qos: int = 1, retain: bool = False) -> None: ...

    def subscribe(self, topic_filter: str, qos: int = 1) -> None:
        """Kept across reconnects: the bus subscribes again after every (re)connect."""
        ...

    def poll(self, max_messages: int | None = None) -> list[Message]:
        """The messages received since the last poll, oldest first; never blocks."""
        ...

    def wait(self, timeout_s: float) -> bool:
        """Block up to `timeout_s` (real seconds) until a message is queued; True if one is."""
        ...

    @property
    def connected(self) -> bool: ...

    def close(self) -> None: ...
