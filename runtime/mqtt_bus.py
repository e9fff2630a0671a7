"""The bus over a real MQTT broker (paho-mqtt): one client, its own credentials, reconnects by itself.

paho calls back on its network thread; messages are stamped with the clock and queued for `poll`.
Subscriptions are remembered and renewed on every reconnect (a clean session forgets them at the broker).
What would otherwise be lost in silence is logged: a full inbound queue (the oldest messages go), a publish
paho could not take, a subscription the broker refused (its ACL) or paho could not send.
"""

from __future__ import annotations

import collections
import logging
import ssl
import threading
from pathlib import Path

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.reasoncodes import ReasonCode

from wsnav.runtime.bus import Message, Will
from wsnav.runtime.clock import Clock, WallClock
from wsnav.runtime.login_copies import LoginCopies
from wsnav.schemas.credentials import Credentials, tool_copies

log = logging.getLogger(__name__)

MAX_PAYLOAD_BYTES = 16 * 1024
"""Twice the largest valid payload of the contract (8 KiB, schemas.messages) and half the brokers' packet cap."""


class BusError(Exception):
    """The broker refused us or could not be reached in time: one line for the user."""


class MqttBus:
    def __init__(
        self,
        host: str,
        port: int,
        *,
        client_id: str,
        username: str,
        password: str,
        clock: Clock | None = None,
        will: Will | None = None,
        birth: Will | None = None,
        keepalive_s: int = 30,
        max_queue: int = 100_000,
        max_payload_bytes: int = MAX_PAYLOAD_BYTES,
        tls_ca: Path | None = None,
        logins: LoginCopies | None = None,
    ) -> None:
        """`birth` is published at every (re)connect, the counterpart of `will` (e.g. `online` / `offline`).

        Payloads over `max_payload_bytes` are dropped on arrival and counted (`dropped_oversize`), before they
        are copied or queued. With `tls_ca` the link is TLS, the broker's certificate checked against that CA
        and its address (the password never crosses the network in clear). With `logins` (an operator tool's
        copies) the bus logs in as the one they give, not `username`, and moves on to the next after a lost
        connection (runtime.login_copies)."""
        self._clock = clock or WallClock()
        self._host, self._port, self._keepalive = host, port, keepalive_s
        self._birth = birth
        self._filters: dict[str, int] = {}
        self._filters_lock = threading.Lock()
        """`_filters` is changed on the caller's thread and read on paho's (at every reconnect)."""
        self._pending_subs: dict[int, str] = {}
        """SUBSCRIBE message id -> filter, until the broker's SUBACK says whether it was granted."""
        self._queue: collections.deque[Message] = collections.deque(maxlen=max_queue)
        self._arrived = threading.Condition()
        self._connected = threading.Event()
        self._answered = threading.Event()
        """The broker answered the first CONNECT, yes or no: a refused login ends `connect` at once."""
        self._refused: str | None = None
        self.dropped_overflow = 0
        """Inbound messages pushed out of the full queue (logged at 1, 10, 100, ... of them)."""
        self.dropped_oversize = 0
        """Inbound payloads over `max_payload_bytes`, dropped on arrival."""
        self._max_payload = max_payload_bytes
        self.unsent = 0
        """Publishes paho did not take (QoS 0 while disconnected, its own queue full)."""
        self.refused_subscriptions: list[str] = []
        self.connects = 0
        self._logins, self._password, self._closing = logins, password, False
        if logins is not None:
            username = logins.take()
        self._client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=True)
        self._client.username_pw_set(username, password)
        self._tls = tls_ca is not None
        if tls_ca is not None:
            try:
                self._client.tls_set(ca_certs=str(tls_ca))
            except (OSError, ssl.SSLError) as exc:
                raise BusError(f"{tls_ca}: not a readable CA certificate (PEM): {exc}") from None
        if will is not None:
            self._client.will_set(will.topic, will.payload, qos=will.qos, retain=will.retain)
        self._client.reconnect_delay_set(min_delay=1, max_delay=8)
        self._client.on_connect = self._on_connect
        self._client.on_disconnect = self._on_disconnect
        self._client.on_message = self._on_message
        self._client.on_subscribe = self._on_subscribe

    def start(self) -> MqttBus:
        """Begin connecting in the background and keep at it (for a process that must serve while the broker
        is down, as the ROS bridge must); `connected`, `refusal` and `wait_answered` tell how it goes."""
        try:
            self._client.connect_async(self._host, self._port, keepalive=self._keepalive)
        except (OSError, ValueError) as exc:
            raise BusError(f"cannot reach MQTT broker {self._host}:{self._port}: {exc}") from None
        self._client.loop_start()
        return self

    def wait_answered(self, timeout_s: float) -> bool:
        """Wait for the broker's first answer (yes or no); False when none came in time."""
        return self._answered.wait(timeout_s)

    @property
    def refusal(self) -> str | None:
        """The broker's reason for refusing the login, if it did."""
        return self._refused

    @property
    def address(self) -> str:
        return f"{self._host}:{self._port}"

    def connect(self, timeout_s: float = 30.0) -> MqttBus:
        """Connect and wait for the broker's answer; afterwards the bus keeps reconnecting by itself."""
        self.start()
        self._answered.wait(timeout_s)
        if not self._connected.is_set():
            self._client.loop_stop()
            sock = self._client.socket()
            if sock is not None:  # a failed connect leaves nothing open behind it
                sock.close()
            if self._logins is not None:
                self._logins.release()
            where = f"MQTT broker {self._host}:{self._port}"
            if self._refused is not None:
                raise BusError(
                    f"{where} refused the login: {self._refused} (check the username and password)"
                )
            if self._tls:
                raise BusError(
                    f"cannot connect to {where} over TLS: no answer (is it the broker's TLS port, and did the "
                    "CA given with --tls-ca sign its certificate for this address?)"
                )
            raise BusError(f"cannot connect to {where}: no answer")
        return self

    def _on_connect(
        self, client: mqtt.Client, _u: object, _f: object, reason: ReasonCode, _p: object
    ) -> None:
        if reason.is_failure:
            self._refused = str(reason)
            if not self._answered.is_set():
                self._answered.set()
            else:
                log.warning("the broker refused the login on reconnect: %s", reason)
            return
        self.connects += 1
        with self._filters_lock:
            filters = list(self._filters.items())
        for topic_filter, qos in filters:
            self._send_subscribe(topic_filter, qos)
        if self._birth is not None:
            client.publish(
                self._birth.topic, self._birth.payload, qos=self._birth.qos, retain=self._birth.retain
            )
        self._connected.set()
        self._answered.set()

    def _on_disconnect(self, _c: object, _u: object, _f: object, reason: ReasonCode, _p: object) -> None:
        self._connected.clear()
        if self._logins is not None and not self._closing:  # perhaps taken over by a copy on another host
            self._client.username_pw_set(self._logins.move_on(), self._password)

    def _on_message(self, _c: object, _u: object, msg: mqtt.MQTTMessage) -> None:
        if len(msg.payload) > self._max_payload:
            self.dropped_oversize += 1
            return
        item = Message(msg.topic, bytes(msg.payload), bool(msg.retain), self._clock.now())
        with self._arrived:
            if len(self._queue) == self._queue.maxlen:
                self.dropped_overflow += 1
                if _is_power_of_ten(self.dropped_overflow):
                    log.warning(
                        "inbound queue full (%d messages): %d oldest dropped so far; the reader is too slow",
                        self._queue.maxlen,
                        self.dropped_overflow,
                    )
            self._queue.append(item)
            self._arrived.notify_all()

    def _on_subscribe(self, _c: object, _u: object, mid: int, reasons: list[ReasonCode], _p: object) -> None:
        with self._filters_lock:
            topic_filter = self._pending_subs.pop(mid, None)
        if topic_filter is not None and any(r.is_failure for r in reasons):
            self.refused_subscriptions.append(topic_filter)
            log.warning("the broker refused the subscription to %s (%s)", topic_filter, reasons[0])

    def _send_subscribe(self, topic_filter: str, qos: int) -> None:
        with self._filters_lock:
            rc, mid = self._client.subscribe(topic_filter, qos)
            if rc == mqtt.MQTT_ERR_SUCCESS and mid is not None:
                self._pending_subs[mid] = topic_filter
        if rc not in (mqtt.MQTT_ERR_SUCCESS, mqtt.MQTT_ERR_NO_CONN):  # NO_CONN: renewed on reconnect
            log.warning("cannot subscribe to %s: %s", topic_filter, mqtt.error_string(rc))

    def publish(self, topic: str, payload: bytes, *, qos: int = 1, retain: bool = False) -> None:
        """Queued by paho while disconnected (QoS 1 is sent after reconnecting); QoS 0 then is lost (counted)."""
        rc = self._client.publish(topic, payload, qos=qos, retain=retain).rc
        if rc == mqtt.MQTT_ERR_SUCCESS or (rc == mqtt.MQTT_ERR_NO_CONN and qos > 0):
            return
        self.unsent += 1
        if rc != mqtt.MQTT_ERR_NO_CONN or _is_power_of_ten(self.unsent):
            log.warning("publish to %s not sent (%d so far): %s", topic, self.unsent, mqtt.error_string(rc))

    def publish_confirmed(
        self, topic: str, payload: bytes, *, retain: bool = False, timeout_s: float = 10.0
    ) -> bool:
        """QoS 1, waiting for the broker's PUBACK: a command that exits right after can say it was delivered."""
        info = self._client.publish(topic, payload, qos=1, retain=retain)
        try:
            info.wait_for_publish(timeout_s)
        except (RuntimeError, ValueError):  # not connected, or the queue refused it
            return False
        return info.is_published()

    def subscribe(self, topic_filter: str, qos: int = 1) -> None:
        with self._filters_lock:
            self._filters[topic_filter] = qos
        if self._connected.is_set():
            self._send_subscribe(topic_filter, qos)

    def poll(self, max_messages: int | None = None) -> list[Message]:
        with self._arrived:
            n = len(self._queue) if max_messages is None else min(max_messages, len(self._queue))
            return [self._queue.popleft() for _ in range(n)]

    def wait(self, timeout_s: float) -> bool:
        with self._arrived:
            return self._arrived.wait_for(lambda: bool(self._queue), timeout_s)

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def wait_connected(self, timeout_s: float) -> bool:
        return self._connected.wait(timeout_s)

    def close(self) -> None:
        """A clean disconnect: the broker does not publish the will."""
        self._closing = True
        self._client.disconnect()
        self._client.loop_stop()
        if self._logins is not None:
            self._logins.release()

    def abort(self) -> None:
        """Drop the link without DISCONNECT, as a power cut would: the broker publishes the will."""
        self._closing = True
        self._client.loop_stop()
        sock = self._client.socket()
        if sock is not None:
            sock.close()
        if self._logins is not None:
            self._logins.release()


def _is_power_of_ten(n: int) -> bool:
    while n >= 10 and n % 10 == 0:
        n //= 10
    return n == 1


def connect_with_credentials(
    host: str,
    port: int,
    credentials: Credentials,
    *,
    client_id: str | None = None,
    clock: Clock | None = None,
    will: Will | None = None,
    birth: Will | None = None,
    timeout_s: float = 30.0,
    wait: bool = True,
    tls_ca: Path | None = None,
    copies: bool = False,
) -> MqttBus:
    """A connected bus that logs in with one id's credentials (client id: its username unless given); with
    `wait=False`, a bus still connecting in the background (MqttBus.start). With `copies`, an operator tool's
    credentials (`tool_login`) log in as a copy of that tool no other copy on this host holds (LoginCopies).

    Takes the loaded credentials, not their file: the loader is broker.credentials', which runtime does not
    import (callers: `load_credentials(path)` or BrokerThread.credentials(ident)).
    """
    bus = MqttBus(
        host,
        port,
        client_id=client_id if client_id is not None else credentials.username,
        username=credentials.username,
        password=credentials.password,
        clock=clock,
        will=will,
        birth=birth,
        tls_ca=tls_ca,
        logins=LoginCopies(tool_copies(credentials)) if copies else None,
    )
    return bus.connect(timeout_s=timeout_s) if wait else bus.start()
