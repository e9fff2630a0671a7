"""What one identity may hold on the broker: subscriptions, parked sessions, and a node's publish rate.

An insider with one credential passes the ACL, so the ACL alone does not bound what it costs the broker:
100,000 subscription filters from one robot made node -> robot latency 7 s on amqtt, 2,000 parked persistent
sessions from one node never expired, and one node's QoS 0 flood delayed every other node's updates by
seconds. Rates (a node's PUBLISH, anyone's SUBSCRIBE, anyone's logins) are held by backpressure, not drops. Retained messages need no limit of their own: every identity but the operator may publish to a fixed
handful of topics (wsnav.broker.acl), so it holds at most that many retained messages of at most the packet cap.
The numbers are far above what the site's own clients use (an agent holds 6 subscriptions, a node publishes a
few messages a minute) and far below what hurt.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

log = logging.getLogger("wsnav.broker")

MAX_SUBSCRIPTIONS = 64
"""Topic filters one session holds (the console and agents hold under 10)."""

SESSION_EXPIRY_S = 24 * 3600
"""A disconnected persistent session is dropped after this (a node or robot off for a day starts afresh)."""

MAX_SESSIONS = 16
"""Disconnected persistent sessions one identity keeps parked (as many as it may hold connections)."""

NODE_PUBLISH_RATE = 20.0
"""Messages per second a node may publish on average (one real node sends a few a minute)."""

NODE_PUBLISH_BURST = 100
"""Messages a node may send at once before the rate applies (a reconnect sends its state, status and info)."""

SUBSCRIBE_RATE = 5.0
"""SUBSCRIBE and UNSUBSCRIBE packets per second of any identity (an agent sends a handful at each connect)."""

SUBSCRIBE_BURST = 50

LOGIN_RATE = 2.0
"""Logins per second of one identity (a node logs in once per Wi-Fi blip, the operator's tools a few times)."""

LOGIN_BURST = 20

MAX_PACKET_BYTES = 32 * 1024
"""Cap on a packet's remaining length, on amqtt (its packet gate) and Mosquitto alike: 4x the largest valid payload
of the contract (8 KiB operator blocks and simulated worlds, schemas.messages) plus topic and headers, and far
below a megabyte."""


@dataclass(frozen=True)
class IdentityLimits:
    """The per-identity limits amqtt enforces (Mosquitto 2.0 offers only the session expiry of these).

    Rates are enforced by backpressure: a packet over its identity's rate is read only when the rate allows it,
    so the sender's socket fills and TCP slows it down; the broker spends nothing on the excess, and nothing a
    client sent is dropped. A rate of None turns that limit off (a broker serving simulated nodes whose clock
    runs faster than real time)."""

    max_subscriptions: int = MAX_SUBSCRIPTIONS
    session_expiry_s: int = SESSION_EXPIRY_S
    max_sessions: int = MAX_SESSIONS
    node_publish_rate: float | None = NODE_PUBLISH_RATE
    node_publish_burst: int = NODE_PUBLISH_BURST
    subscribe_rate: float | None = SUBSCRIBE_RATE
    subscribe_burst: int = SUBSCRIBE_BURST
    login_rate: float | None = LOGIN_RATE
    login_burst: int = LOGIN_BURST


@dataclass
class _Bucket:
    tokens: float
    at: float


@dataclass
class RateBudget:
    """A token bucket per identity, shared by all its connections (16 connections get no more than one)."""

    what: str
    """What is counted, for the log line ("PUBLISH", "logins"...)."""
    rate: float
    burst: int
    delayed: int = 0
    _buckets: dict[str, _Bucket] = field(default_factory=dict[str, _Bucket])
    _last_report: float = 0.0
    _reported: int = 0

    def reserve(self, identity: str, now: float | None = None) -> float:
        """Take one token for `identity`: the seconds to wait before the packet may be handled (0: at once)."""
        now = time.monotonic() if now is None else now
        bucket = self._buckets.get(identity)
        if bucket is None:
            bucket = self._buckets[identity] = _Bucket(float(self.burst), now)
        bucket.tokens = min(float(self.burst), bucket.tokens + (now - bucket.at) * self.rate)
        bucket.at = now
        bucket.tokens -= 1.0
        if bucket.tokens >= 0.0:
            return 0.0
        self.delayed += 1
        self._report(identity, now)
        return -bucket.tokens / self.rate

    def _report(self, identity: str, now: float) -> None:
        """One warning per 10 s at most, however hard an identity pushes."""
        if now - self._last_report < 10.0:
            return
        log.warning(
            f"{identity!r} sends {self.what} faster than {self.rate:g}/s: {self.delayed - self._reported} held "
            "back to the rate since the last report"
        )
        self._last_report, self._reported = now, self.delayed


def budget(what: str, rate: float | None, burst: int) -> RateBudget | None:
    return None if rate is None else RateBudget(what, rate, burst)
