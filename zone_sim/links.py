"""Many MQTT connections on one thread: one paho client per emulated node, driven by a selector.

1000 nodes with paho's `loop_start()` would be 1000 threads contending for the GIL; here every client runs
without a thread of its own, through paho's external-loop calls (`socket()`, `loop_read()`, `loop_write()`,
`loop_misc()`, `want_write()`), and `LinkLoop.pump` does one round of I/O for all of them. Each link is a real
TCP connection with the node's own client id, credentials and last will, so the broker sees what a board sends.

Link-level timing (keepalive pings, the connect timeout) is about the TCP link, so it runs on real monotonic
time, as paho's own does; the node's behaviour runs on the simulator's clock.
"""

from __future__ import annotations

import contextlib
import selectors
import time
from collections.abc import Callable
from dataclasses import dataclass

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode
from paho.mqtt.reasoncodes import ReasonCode

CONNECT_TIMEOUT_S = 30.0
"""A link that has no CONNACK this long after the TCP connect is dropped and retried."""
MISC_PERIOD_S = 0.5
"""How often every link's keepalive is checked (paho sends PINGREQ when due)."""


@dataclass(frozen=True)
class LinkAddress:
    host: str
    port: int
    client_id: str
    username: str
    password: str
    keepalive_s: int
    will: tuple[str, bytes, bool, int]
    """(topic, payload, retain, qos), as NodeLogic.will() gives it."""


class NodeLink:
    """One node's connection. `on_up()` after CONNACK, `on_down(reason)` when the link is lost or refused."""

    def __init__(
        self,
        loop: LinkLoop,
        address: LinkAddress,
        on_up: Callable[[], None],
        on_down: Callable[[str], None],
    ) -> None:
        self._loop = loop
        self.address = address
        self._on_up = on_up
        self._on_down = on_down
        self.client: mqtt.Client | None = None
        self.connected = False
        self.hung = False
        self._opened_at = 0.0

    @property
    def active(self) -> bool:
        """A connection exists (connecting or up) and is being serviced."""
        return self.client is not None and not self.hung

    def open(self) -> None:
        """TCP connect and send CONNECT with the will; the CONNACK arrives through the loop. Raises OSError."""
        a = self.address
        client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=a.client_id, clean_session=True)
        client.username_pw_set(a.username, a.password)
        topic, payload, retain, qos = a.will
        client.will_set(topic, payload, qos=qos, retain=retain)
        client.max_queued_messages_set(0)
        client.max_inflight_messages_set(100)
        client.on_connect = self._connected
        client.on_disconnect = self._disconnected
        client.on_socket_close = self._socket_closed
        self.client = client
        self.hung = False
        self._opened_at = time.monotonic()
        try:
            client.connect(a.host, a.port, keepalive=a.keepalive_s)
        except (OSError, ValueError):
            self.client = None
            raise
        sock = client.socket()
        if sock is None:
            self.client = None
            raise OSError("no socket after connect")
        self._loop.register(self, sock)

    def publish(self, topic: str, payload: bytes, retain: bool, qos: int) -> bool:
        """Queue one PUBLISH; False when the link is not up (the node's logic tracks that itself)."""
        client = self.client
        if client is None or not self.connected or self.hung:
            return False
        info = client.publish(topic, payload, qos=qos, retain=retain)
        self._loop.want(self)
        return info.rc == MQTTErrorCode.MQTT_ERR_SUCCESS

    def drop(self) -> None:
        """Cut the TCP link without DISCONNECT, as a power cut does: the broker publishes the will."""
        client, self.client = self.client, None
        self.connected = False
        self.hung = False
        if client is None:
            return
        sock = client.socket()
        if sock is not None:
            self._loop.unregister(sock)
            sock.close()  # FIN without DISCONNECT: the broker treats it as a lost link

    def hang(self) -> None:
        """Stop all traffic but keep the socket open (a wedged board): the broker drops it after 1.5x keepalive."""
        if self.client is None:
            return
        sock = self.client.socket()
        if sock is not None:
            self._loop.unregister(sock)
        self.connected = False
        self.hung = True

    def disconnect(self) -> None:
        """A clean DISCONNECT (no will)."""
        client = self.client
        if client is not None and self.connected:
            client.disconnect()
            client.loop_write()
        self.drop()

    # -- paho callbacks (called inside loop_read / loop_misc) ------------------------------------------------
    def _connected(self, _c: object, _u: object, _f: object, reason: ReasonCode, _p: object) -> None:
        if reason.is_failure:
            self._loop.later(lambda: self._lost(f"broker refused the connection: {reason}"))
            return
        self.connected = True
        self._loop.later(self._on_up)

    def _disconnected(self, _c: object, _u: object, _f: object, reason: ReasonCode, _p: object) -> None:
        self._loop.later(lambda: self._lost(f"link lost: {reason}"))

    def _socket_closed(self, _c: object, _u: object, sock: object) -> None:
        self._loop.unregister(sock)

    def _lost(self, why: str) -> None:
        if self.client is None:
            return
        self.drop()
        self._on_down(why)

    def misc(self, now: float) -> None:
        client = self.client
        if client is None or self.hung:
            return
        if not self.connected and now - self._opened_at > CONNECT_TIMEOUT_S:
            self._lost("no CONNACK in time")
            return
        client.loop_misc()
        self._loop.want(self)


class LinkLoop:
    """The selector every NodeLink's socket is registered with; `pump(timeout)` does one round of I/O."""

    def __init__(self) -> None:
        self._selector = selectors.DefaultSelector()
        self._links: set[NodeLink] = set()
        self._writers: set[NodeLink] = set()
        self._deferred: list[Callable[[], None]] = []
        self._last_misc = time.monotonic()

    def register(self, link: NodeLink, sock: object) -> None:
        self._selector.register(sock, selectors.EVENT_READ, link)  # type: ignore[arg-type]
        self._links.add(link)
        self.want(link)

    def unregister(self, sock: object) -> None:
        try:
            key = self._selector.unregister(sock)  # type: ignore[arg-type]
        except (KeyError, ValueError):
            return
        link: NodeLink = key.data
        self._links.discard(link)
        self._writers.discard(link)

    def want(self, link: NodeLink) -> None:
        """Check after the caller queued packets: watch the socket for writability while paho holds data."""
        client = link.client
        if client is None or link.hung:
            return
        sock = client.socket()
        if sock is None:
            return
        writing = link in self._writers
        if client.want_write() and not writing:
            self._modify(sock, selectors.EVENT_READ | selectors.EVENT_WRITE, link)
            self._writers.add(link)
        elif writing and not client.want_write():
            self._modify(sock, selectors.EVENT_READ, link)
            self._writers.discard(link)

    def _modify(self, sock: object, events: int, link: NodeLink) -> None:
        with contextlib.suppress(KeyError, ValueError):
            self._selector.modify(sock, events, link)  # type: ignore[arg-type]

    def later(self, action: Callable[[], None]) -> None:
        """Run `action` after the current I/O round (paho callbacks must not reenter the client)."""
        self._deferred.append(action)

    def pump(self, timeout_s: float = 0.0) -> int:
        """Wait up to `timeout_s` for I/O, handle it, run deferred actions; returns the number of events."""
        events = self._selector.select(timeout_s) if self._links else []
        for key, mask in events:
            link: NodeLink = key.data
            client = link.client
            if client is None:
                continue
            if mask & selectors.EVENT_READ:
                rc = client.loop_read()
                if rc != MQTTErrorCode.MQTT_ERR_SUCCESS:
                    self.later(lambda link=link, rc=rc: link._lost(f"read failed: {mqtt.error_string(rc)}"))
                    continue
            if mask & selectors.EVENT_WRITE and link.client is not None:
                client.loop_write()
            self.want(link)
        now = time.monotonic()
        if now - self._last_misc >= MISC_PERIOD_S:
            self._last_misc = now
            for link in list(self._links):
                link.misc(now)
        self.run_deferred()
        return len(events)

    def run_deferred(self) -> None:
        while self._deferred:
            actions, self._deferred = self._deferred, []
            for action in actions:
                action()

    @property
    def link_count(self) -> int:
        return len(self._links)

    def close(self) -> None:
        self._selector.close()
