"""Our whole patch of amqtt 0.12.1, in one place: every override of amqtt code, why, and the test that pins it.

amqtt is the Pi's broker, and some of its behaviour cannot be fixed through its plugin API. Each override below
is pinned to amqtt==0.12.1 (pyproject.toml) and to a test; docs/broker-amqtt.md writes them up for upstream.

| override | amqtt behaviour it fixes | pinned by |
| --- | --- | --- |
| `WsnavBroker.stream_connected`, `ws_connected` | no CONNECT timeout, no packet size cap, malformed packets accepted, sockets of failed logins left open (CLOSE-WAIT), a connection cap that queues new sockets behind idle ones | tests/test_broker_lockout.py, tests/test_broker_protocol.py |
| `WsnavBroker._initialize_client_session` | the old session of a client id is dropped (or merged) before the password is checked; client ids are global, so one identity could resume or kick another's session | tests/test_broker_security.py |
| `WsnavBroker._authenticate` | (follows from the above: authentication already ran) | tests/test_broker_security.py |
| `WsnavBroker._topic_filtering` | one plugin round trip per delivered message (RECEIVE), and per published one (PUBLISH: asked once per identity and topic) | tests/test_broker_security.py |
| `WsnavBroker._broadcast_message` (and `SubscriptionIndex`) | every message queued for one broadcast task (2-3 event-loop turns each) and compared with every filter held: 1000 nodes at 1 Hz fell behind for good once the loop slowed (bench.zone_fanin) | tests/test_broker_subscription_index.py, tests/test_broker_delivery.py |
| `WsnavBroker._publish_retained_messages_for_subscription` | a new client gets retained messages matching *other* clients' filters; retained QoS 0 delivered at the subscriber's QoS | tests/test_broker_security.py, tests/test_broker_embedded.py |
| `WsnavBroker._client_message_loop` | QoS 1 messages acknowledged (PUBACK sent when queued) but still queued when the client disconnects are dropped without a word | tests/test_broker_delivery.py |
| `WsnavProtocolHandler._handle_qos1_message_flow` | PUBACK waiter registered after PUBLISH is sent: a fast PUBACK is lost and the send hangs 5 s | tests/test_broker_embedded.py |
| `WsnavBroker.add_subscription`, `_del_subscription` | no limit on the filters one session holds (100,000 from one robot: node -> robot latency 7 s) | tests/test_broker_limits.py |
| `WsnavBroker._initialize_client_session` (again) | persistent sessions of one identity never expire and have no cap (2,000 parked by one node) | tests/test_broker_limits.py |
| `WsnavBroker.start` (a password-file watch) | a changed password file needs a restart, and a revoked identity's connections and sessions live on | tests/test_broker_revoke.py |
| `WsnavBroker._gated` (the gate's `peer_left`, `backlog`, `closed_by_us`) | a flood held to its rate outlived its sender: megabytes unread in the socket kept its messages coming for minutes after the flooder left or was revoked | tests/test_broker_limits.py |
| `WsnavProtocolHandler._acknowledge_once_stored`, `WsnavBroker.retain_message` | an operator block acknowledged 0.01 s before a kill -9 was lost (PUBACK when queued, on disk within 0.2 s) | tests/test_broker_process.py |
| `handle_read_timeout` on each handler | keepalive never enforced: a silent client is never dropped and its will never fires | tests/test_broker_embedded.py |
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import logging
import math
import select
import struct
import termios
import time
from collections.abc import Awaitable, Callable
from functools import partial
from pathlib import Path
from typing import Any

from amqtt.adapters import (
    ReaderAdapter,
    StreamReaderAdapter,
    StreamWriterAdapter,
    WebSocketsReader,
    WebSocketsWriter,
    WriterAdapter,
)
from amqtt.broker import Broker
from amqtt.contexts import Action, ListenerConfig
from amqtt.errors import AMQTTError, MQTTError, NoDataError
from amqtt.mqtt.protocol.broker_handler import BrokerProtocolHandler
from amqtt.mqtt.puback import PubackPacket
from amqtt.session import INCOMING, OUTGOING, IncomingApplicationMessage, OutgoingApplicationMessage, Session
from amqtt.utils import gen_client_id
from websockets.asyncio.server import ServerConnection

from wsnav.broker.amqtt.admission import Admission, Ticket
from wsnav.broker.amqtt.packet_gate import MAX_PACKET_BYTES, PUBLISH, SUBSCRIBE, UNSUBSCRIBE, GateReader
from wsnav.broker.amqtt.retained_store import RetainedStorePlugin
from wsnav.broker.amqtt.subscription_index import SubscriptionIndex
from wsnav.broker.credentials import file_stamp, read_password_file
from wsnav.broker.identity_limits import IdentityLimits, budget
from wsnav.runtime.drop_log import DropLog
from wsnav.schemas import topics
from wsnav.schemas.credentials import CredentialsError

log = logging.getLogger("wsnav.broker")

_PREAUTHORIZED = "_wsnav_preauthorized"


class _QuietAmqttNoise(logging.Filter):
    """amqtt logs a traceback when a listener cannot bind (we report it in one line), a warning plus an error
    for every socket that ends before logging in (the gate and admission log those once, rate-limited), and a
    traceback after the warning for every QoS 1 delivery left unacknowledged."""

    _NOISE = (
        "Broker startup failed",
        "Failed to initialize client session",
        "No data from",
        "[MQTT-3.1.0-1]",
    )

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith(self._NOISE) and not _puback_timeout(record)


def _puback_timeout(record: logging.LogRecord) -> bool:
    """The traceback amqtt logs again for a delivery whose subscriber never acknowledged (it left, or hangs):
    the handler has already said so in one warning line."""
    return _is_puback_timeout(record.exc_info[1] if record.exc_info else None)


def _is_puback_timeout(error: BaseException | None) -> bool:
    return isinstance(error, TimeoutError) and str(error).startswith("Timeout waiting for PUBACK")


logging.getLogger("amqtt.broker").addFilter(_QuietAmqttNoise())


def session_key(username: str, client_id: str) -> str:
    """The broker-side session name: client ids live inside their identity, so no identity can reach another's.

    A client id equal to the username is the key itself (site ids hold no '/', so keys never collide).
    """
    return username if client_id == username else f"{username}/{client_id}"


class WsnavProtocolHandler(BrokerProtocolHandler):
    """amqtt's per-client handler with the QoS 1 send race fixed.

    amqtt 0.12.1 sends PUBLISH and only then registers the PUBACK waiter; on a fast link the PUBACK can come
    first ("Received PUBACK for unknown pending message"), and the send then hangs 5 s and fails. Registering
    the waiter first removes the race.

    It also keeps each message it takes off the session's delivery queue until the broker has handled it
    (`taken`): amqtt's loop drops one taken while it was busy with the client's DISCONNECT.
    """

    taken: list[Any] | None = None
    stored: Callable[[int], Awaitable[None]] | None = None
    """The retained store's `written`: an operator block is acknowledged once it is on disk (set by the broker)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.awaiting_store: dict[int, asyncio.Future[int]] = {}
        """id() of a message waiting for its PUBACK -> resolved by the broker once it has handled the message."""

    async def mqtt_deliver_next_message(self) -> Any:
        message = await super().mqtt_deliver_next_message()
        if message is not None:
            if self.taken is None:
                self.taken = []
            self.taken.append(message)
        return message

    async def _handle_qos1_message_flow(
        self, app_message: OutgoingApplicationMessage | IncomingApplicationMessage
    ) -> None:
        if (
            app_message.direction == INCOMING
            and self.stored is not None
            and self.session is not None
            and app_message.packet_id is not None
            and _stored_before_puback(app_message)
        ):
            await self._acknowledge_once_stored(app_message, self.session, app_message.packet_id, self.stored)
            return
        if app_message.direction != OUTGOING or self.session is None or app_message.packet_id is None:
            await super()._handle_qos1_message_flow(app_message)
            return
        if app_message.puback_packet:
            raise AMQTTError(f"Message '{app_message.packet_id}' has already been acknowledged")
        packet_id = app_message.packet_id
        if packet_id not in self.session.inflight_out and isinstance(app_message, OutgoingApplicationMessage):
            self.session.inflight_out[packet_id] = app_message
        dup = app_message.publish_packet is not None
        publish_packet = app_message.build_publish_packet(dup=dup)
        waiter: asyncio.Future[PubackPacket] = asyncio.get_running_loop().create_future()
        self._puback_waiters[packet_id] = waiter
        try:
            await self._send_packet(publish_packet)
            app_message.publish_packet = publish_packet
            app_message.puback_packet = await asyncio.wait_for(waiter, timeout=5)
        except TimeoutError:
            msg = f"Timeout waiting for PUBACK for packet ID {packet_id}"
            self.logger.warning(msg)
            raise TimeoutError(msg) from None
        finally:
            self._puback_waiters.pop(packet_id, None)
            self.session.inflight_out.pop(packet_id, None)

    async def _acknowledge_once_stored(
        self,
        app_message: OutgoingApplicationMessage | IncomingApplicationMessage,
        session: Session,
        packet_id: int,
        stored: Callable[[int], Awaitable[None]],
    ) -> None:
        """amqtt acknowledges a QoS 1 PUBLISH when it is queued; an operator block killed with the broker 0.01 s
        later was lost (the store writes within 0.2 s). Here the PUBACK waits until the broker has handled the
        message and the store has written (and fsync'd) it; not handled within STORED_WITHIN_S: no PUBACK, and
        the client sends it again."""
        if app_message.puback_packet:
            raise AMQTTError(f"Message '{packet_id}' has already been acknowledged")
        handled: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        self.awaiting_store[id(app_message)] = handled
        await session.delivered_message_queue.put(app_message)
        try:
            noted = await asyncio.wait_for(handled, STORED_WITHIN_S)
            await asyncio.wait_for(stored(noted), STORED_WITHIN_S)
        except TimeoutError:
            log.warning(f"{app_message.topic}: not stored within {STORED_WITHIN_S:g} s, not acknowledged")
            return
        finally:
            self.awaiting_store.pop(id(app_message), None)
        puback = PubackPacket.build(packet_id)
        await self._send_packet(puback)
        app_message.puback_packet = puback


STORED_WITHIN_S = 10.0
SHUTDOWN_GRACE_S = 2.0
"""A shutdown still running after this long aborts every connection it has not closed yet."""
PUBLISH_DECISIONS_KEPT = 100_000
"""ACL answers kept (`WsnavBroker._topic_filtering`); all are forgotten when full (an operator's block ids, a
client trying random topics), so memory stays bounded."""


def _stored_before_puback(message: OutgoingApplicationMessage | IncomingApplicationMessage) -> bool:
    """Operator blocks (and their clearing): nothing else restores them. Zone states and statuses come again
    within a heartbeat, so they keep amqtt's early PUBACK and the 0.2 s flush."""
    packet = message.publish_packet
    parsed = topics.parse(message.topic) if packet is not None and packet.retain_flag else None
    return parsed is not None and parsed.kind == "operator_block"


class WsnavBroker(Broker):
    """amqtt's Broker with the overrides listed in the module docstring."""

    def __init__(
        self,
        config: dict[str, Any],
        admission: Admission,
        *,
        max_packet_bytes: int = MAX_PACKET_BYTES,
        connect_timeout_s: float = 5.0,
        limits: IdentityLimits | None = None,
        nodes: frozenset[str] = frozenset(),
        password_file: Path | None = None,
    ) -> None:
        super().__init__(config)
        self.admission = admission
        self.max_packet_bytes = max_packet_bytes
        self.connect_timeout_s = connect_timeout_s
        self.limits = limits or IdentityLimits()
        limits = self.limits
        self.nodes = nodes
        self.publish_budget = budget("PUBLISH", limits.node_publish_rate, limits.node_publish_burst)
        self.subscribe_budget = budget("SUBSCRIBE", limits.subscribe_rate, limits.subscribe_burst)
        self.login_budget = budget("logins", limits.login_rate, limits.login_burst)
        self._subscription_count: dict[str | None, int] = {}
        self.refused_subscriptions = 0
        self.dropped_sessions = 0
        self.connections_ended = 0
        """Each one leaves cyclic garbage (its session, handler, streams) for gc_pacing's refresh."""
        self._last_limit_report = 0.0
        self._password_file = password_file
        self._watch: asyncio.Task[None] | None = None
        self._subscriptions = SubscriptionIndex(self._subscriptions.items())
        self._deliveries: set[asyncio.Future[Any]] = set()
        """Sends to subscribers started by `_broadcast_message` and not finished yet (cancelled at shutdown)."""
        self._failed_deliveries = DropLog(log, "broker", "deliveries to subscribers")
        self._publish_decisions: dict[tuple[str | None, str], bool] = {}
        """(username, topic) -> may publish, as the topic plugins answered (`_topic_filtering`)."""

    async def start(self) -> None:
        await super().start()
        if self._password_file is not None:
            self._watch = asyncio.create_task(self._watch_passwords(self._password_file))

    async def shutdown(self) -> None:
        """amqtt's, but the listeners stop listening first: amqtt closes them last, after the sessions' cleanup,
        and a cleanup that failed or hung left the port bound, so a broker restarted on it could not listen
        ("address already in use" for over 20 s, twice in CI)."""
        if self._watch is not None:
            self._watch.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watch
        for server in self._servers.values():
            if server.instance is not None:
                server.instance.close()
        # A session's cleanup can hang or crawl under load; the peers must still see the broker go at once, not
        # two keepalives later (60 s for paho's 30 s, seen twice in whole-suite runs).
        deadline = asyncio.get_running_loop().call_later(SHUTDOWN_GRACE_S, self.admission.close_all)
        try:
            await super().shutdown()
        finally:
            deadline.cancel()
            self.admission.close_all()
        for delivery in list(self._deliveries):
            delivery.cancel()
        if self._deliveries:
            await asyncio.wait(list(self._deliveries), timeout=1.0)

    async def _watch_passwords(self, path: Path, every_s: float = 0.5) -> None:
        """Revocation without a restart: when an identity's hash changes or goes, the connections that logged in
        before the change are closed and its parked sessions dropped (the auth plugin checks new logins against
        the new file)."""
        hashes, stamp = _hashes_or_none(path), file_stamp(path)
        while True:
            await asyncio.sleep(every_s)
            if file_stamp(path) == stamp:
                continue
            stamp = file_stamp(path)
            now = _hashes_or_none(path)
            if now is None or hashes is None or stamp is None:
                hashes = now if now is not None else hashes
                continue
            revoked = sorted(user for user in hashes if now.get(user) != hashes[user])
            hashes = now
            changed_at = stamp[1] / 1e9
            for user in revoked:
                closed = self.admission.close_identity(user, logged_in_before=changed_at)
                await asyncio.sleep(0.2)  # the closed connections end their sessions first
                parked = [
                    key
                    for key, (session, _) in self._sessions.items()
                    if session.username == user and session.transitions.state == "disconnected"
                ]
                for key in parked:
                    await self._delete_session(key)
                log.warning(
                    f"{user!r}: password renewed or removed: closed {closed} connection(s) that logged in "
                    f"before, dropped {len(parked)} parked session(s)"
                )

    async def stream_connected(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, listener_name: str
    ) -> None:
        """Every TCP/TLS connection: a slot (or none), the packet gate, and the socket closed whatever happens."""
        await self._gated(
            listener_name, StreamReaderAdapter(reader), StreamWriterAdapter(writer), writer.transport
        )

    async def ws_connected(self, websocket: ServerConnection, listener_name: str) -> None:
        await self._gated(
            listener_name, WebSocketsReader(websocket), WebSocketsWriter(websocket), websocket.transport
        )

    async def _gated(
        self,
        listener_name: str,
        reader: ReaderAdapter,
        writer: WriterAdapter,
        transport: asyncio.WriteTransport,
    ) -> None:
        aborted = (
            asyncio.Event()
        )  # closed by the broker (revoked, rejected), not by the peer (TLS closes on EOF)

        def abort() -> None:
            aborted.set()
            transport.abort()

        ticket = self.admission.admit(abort)
        if ticket is None:
            abort()
            return
        peer = writer.get_peer_info()

        def reject(reason: str) -> None:
            log.info(f"closing {peer}: {reason}")
            abort()

        gate = GateReader(
            reader, reject, max_bytes=self.max_packet_bytes, connect_timeout_s=self.connect_timeout_s
        )
        setattr(gate, "ticket", ticket)  # noqa: B010  (read back in _initialize_client_session)
        gate.packet_delay = partial(self._packet_delay, ticket)
        gate.closed_by_us = aborted.is_set
        gate.peer_left = partial(_peer_left, transport)
        gate.backlog = partial(_unread_bytes, transport)
        try:
            await self._client_connected(listener_name, gate, writer)
        finally:
            self.admission.release(ticket)
            self.connections_ended += 1
            abort()  # a no-op after a clean close; frees the descriptor of every other ending (CLOSE-WAIT)

    async def _initialize_client_session(
        self, reader: ReaderAdapter, writer: WriterAdapter, remote_address: str, remote_port: int
    ) -> tuple[BrokerProtocolHandler, Session]:
        """amqtt's version, but authenticating *before* the client id is looked up, in its identity's namespace.

        amqtt 0.12.1 deletes the old session of a clean-session client id (or merges username, password and
        will into a persistent one) before it checks the password, and client ids are global: any client could
        cut a connected robot off, and any identity could resume another identity's persistent session with
        its subscriptions (amqtt never re-checks the ACL on delivery). Here the session key is
        `session_key(username, client_id)`.
        """
        try:
            handler, session = await WsnavProtocolHandler.init_from_connect(
                reader, writer, self.plugins_manager
            )
        except (AMQTTError, MQTTError, NoDataError) as exc:
            raise AMQTTError(exc) from exc
        session.parent = 0
        if not await self._authenticate_first(session):
            handler.attach(session, reader, writer)
            await handler.mqtt_connack_authorize(False)
            await writer.close()
            raise AMQTTError(f"connection refused: not authorized (client id {session.client_id!r})")
        username = session.username or ""
        ticket = getattr(reader, "ticket", None)
        if isinstance(ticket, Ticket) and not self.admission.logged_in(ticket, username):
            handler.attach(session, reader, writer)
            await handler.mqtt_connack_authorize(False)
            await writer.close()
            raise AMQTTError(f"connection refused: {username!r} holds its maximum of connections")
        if self.login_budget is not None:
            wait = self.login_budget.reserve(username)
            if wait > 0.0:
                await asyncio.sleep(wait)  # a login storm of one identity waits its turn, others do not
        if not session.client_id:
            session.client_id = gen_client_id()
        session.client_id = session_key(username, session.client_id)
        if session.clean_session:
            await self._delete_session(session.client_id)
        elif session.client_id not in self._sessions:
            await self._make_room_for_session(username)
        else:
            existing, _ = self._sessions[session.client_id]
            for name in ("will_flag", "will_message", "will_topic", "will_qos", "will_retain", "keep_alive"):
                setattr(existing, name, getattr(session, name))
            session = existing
            session.parent = 1
        if session.keep_alive > 0:
            # amqtt's reader times out after keep_alive seconds, then calls a handler hook that does nothing:
            # stretch the timeout to the spec's 1.5x and make the hook end the session abnormally.
            session.keep_alive = math.ceil(session.keep_alive * 1.5)
            setattr(handler, "handle_read_timeout", partial(_drop_silent_client, handler))  # noqa: B010
        setattr(session, _PREAUTHORIZED, True)
        store = self._retained_store()
        if store is not None and isinstance(handler, WsnavProtocolHandler):
            handler.stored = store.written
        return handler, session

    def _retained_store(self) -> RetainedStorePlugin | None:
        return next((p for p in self.plugins_manager._plugins if isinstance(p, RetainedStorePlugin)), None)

    async def retain_message(
        self,
        source_session: Session | None,
        topic_name: str | None,
        data: bytes | bytearray | None,
        qos: int | None = None,
    ) -> None:
        """amqtt's, and the store notes the change now rather than in amqtt's event task, so that an operator
        block's PUBACK can wait for its write (`WsnavProtocolHandler._acknowledge_once_stored`)."""
        await super().retain_message(source_session, topic_name, data, qos)
        store = self._retained_store()
        if store is not None and topic_name is not None:
            parsed = topics.parse(topic_name)
            store.note(topic_name, urgent=parsed is not None and parsed.kind == "operator_block")

    def _packet_delay(self, ticket: Ticket, kind: int) -> float:
        """How long a packet of `kind` from this connection waits: its identity's PUBLISH (nodes only) or
        SUBSCRIBE/UNSUBSCRIBE rate."""
        identity = ticket.identity
        if identity is None:
            return 0.0
        if kind == PUBLISH and identity in self.nodes and self.publish_budget is not None:
            return self.publish_budget.reserve(identity)
        if kind in (SUBSCRIBE, UNSUBSCRIBE) and self.subscribe_budget is not None:
            return self.subscribe_budget.reserve(identity)
        return 0.0

    async def _make_room_for_session(self, username: str) -> None:
        """A new persistent session of `username`: drop its longest-parked ones beyond `max_sessions`.

        amqtt keeps persistent sessions (and their queued messages) forever; one node credential parked 2,000 of
        them under distinct client ids. Connected sessions are never dropped (admission caps those)."""
        own = [
            (s.last_disconnect_time or 0.0, key)
            for key, (s, _) in self._sessions.items()
            if s.username == username and not s.clean_session and s.transitions.state == "disconnected"
        ]
        excess = len(own) + 1 - self.limits.max_sessions
        for _, key in sorted(own)[: max(excess, 0)]:
            await self._delete_session(key)
            self.dropped_sessions += 1
            self._report_limits(f"{username!r} parked over {self.limits.max_sessions} sessions")

    async def add_subscription(self, subscription: tuple[str, int], session: Session) -> int:
        """amqtt's, refused (0x80) once the session holds `max_subscriptions` filters."""
        topic_filter, _ = subscription
        held = self._subscription_count.get(session.client_id, 0)
        already = any(s.client_id == session.client_id for s, _ in self._subscriptions.get(topic_filter, []))
        if not already and held >= self.limits.max_subscriptions:
            self.refused_subscriptions += 1
            self._report_limits(
                f"{session.username!r} asked for over {self.limits.max_subscriptions} subscriptions"
            )
            return 0x80
        granted = await super().add_subscription(subscription, session)
        if granted != 0x80 and not already:
            self._subscription_count[session.client_id] = held + 1
        return granted

    def _del_subscription(self, a_filter: str, session: Session) -> int:
        deleted = super()._del_subscription(a_filter, session)
        if deleted:
            left = self._subscription_count.get(session.client_id, 0) - deleted
            if left > 0:
                self._subscription_count[session.client_id] = left
            else:
                self._subscription_count.pop(session.client_id, None)
        return deleted

    def _report_limits(self, what: str) -> None:
        """One warning per 10 s at most: an identity hammering a limit must not fill the log."""
        now = time.monotonic()
        if now - self._last_limit_report < 10.0:
            return
        self._last_limit_report = now
        log.warning(
            f"identity limit: {what} (refused {self.refused_subscriptions} subscription(s), dropped "
            f"{self.dropped_sessions} parked session(s) so far)"
        )

    async def _client_message_loop(self, client_session: Session, handler: BrokerProtocolHandler) -> None:
        """amqtt's loop, then every message the client published and was acknowledged but not yet handled.

        amqtt 0.12.1 sends PUBACK when it queues an incoming QoS 1 message and cancels the queue's reader when
        the client goes: a client that waited for every PUBACK and disconnected lost some (8 of 200 retained
        messages at 20 a client), with nothing logged; and its loop drops a message it took off the queue while
        the DISCONNECT was being handled (16 of 4000 in CI after the first fix). Acknowledged means delivered: both
        are handled here, as the loop would have."""
        await super()._client_message_loop(client_session, handler)
        queue = client_session.delivered_message_queue
        left = list(handler.taken or []) if isinstance(handler, WsnavProtocolHandler) else []
        while not queue.empty():
            left.append(queue.get_nowait())
        loop = asyncio.get_running_loop()
        for (
            message
        ) in left:  # taken off the queue but dropped by amqtt's loop (a DISCONNECT came first), then the rest
            future: asyncio.Future[Any] = loop.create_future()
            future.set_result(message)
            if not await self._handle_message_delivery(client_session, handler, future):
                break

    async def _handle_message_delivery(
        self, client_session: Session, handler: BrokerProtocolHandler, wait_deliver: asyncio.Future[Any]
    ) -> bool:
        """amqtt's, after forgetting the message as taken-but-unhandled (see `_client_message_loop`)."""
        message = (
            wait_deliver.result()
            if not wait_deliver.cancelled() and wait_deliver.exception() is None
            else None
        )
        if isinstance(handler, WsnavProtocolHandler) and handler.taken and message is not None:
            handler.taken = [m for m in handler.taken if m is not message]
        handled = (
            handler.awaiting_store.get(id(message)) if isinstance(handler, WsnavProtocolHandler) else None
        )
        try:
            return await super()._handle_message_delivery(client_session, handler, wait_deliver)
        finally:
            if handled is not None and not handled.done():
                store = self._retained_store()
                handled.set_result(store.noted if store is not None else 0)

    async def _broadcast_message(
        self,
        session: Session | None,
        topic: str | None,
        data: bytes | bytearray | None,
        force_qos: int | None = None,
    ) -> None:
        """amqtt's `_run_broadcast` at once, instead of through its broadcast queue and loop.

        amqtt queues each message for one broadcast task, which takes two or three turns of the event loop per
        message and compares the topic with every filter held: with 1000 nodes at 1 Hz the queue fell behind
        whenever the loop's turns grew (a collection, a busy core) and never caught up (seconds of lag at 25-50 %
        of the core). Here the message goes to its subscribers' handlers now, in the order messages are handled;
        the filters matching it are found by `SubscriptionIndex`. Delivery is amqtt's: at the subscription's QoS
        (or `force_qos`), queued for a disconnected persistent session at QoS 1 and 2, skipped for others."""
        if topic is None or data is None:
            return
        subscriptions = self._subscriptions
        matching = (
            subscriptions.matching(topic, self._matches)
            if isinstance(subscriptions, SubscriptionIndex)
            else [(f, subs) for f, subs in subscriptions.items() if self._matches(topic, f)]
        )
        broadcast: dict[str, Any] = {"session": session, "topic": topic, "data": data}
        for _filter, subscribers in matching:
            for target, sub_qos in list(subscribers):
                qos = sub_qos if force_qos is None else force_qos
                connected = target.transitions.state == "connected"
                if not connected and not target.clean_session and qos in (1, 2) and not target.is_anonymous:
                    await self._retain_broadcast_message(broadcast, qos, target)
                    continue
                handler = self._get_handler(target) if connected else None
                if handler is None:
                    continue
                delivery = asyncio.ensure_future(handler.mqtt_publish(topic, data, qos, retain=False))
                self._deliveries.add(delivery)
                delivery.add_done_callback(self._delivered)

    def _delivered(self, delivery: asyncio.Future[Any]) -> None:
        """A send to a subscriber ended: forget it, and say why if it failed (as amqtt's broadcast loop does)."""
        self._deliveries.discard(delivery)
        if delivery.cancelled():
            return
        error = delivery.exception()
        if error is None or _is_puback_timeout(error):
            return  # (the handler has said so in a warning of its own)
        now = time.monotonic()
        self._failed_deliveries.drop(
            type(error).__name__, now, "a delivery to a subscriber", str(error) or repr(error)
        )
        self._failed_deliveries.flush(now)

    async def _authenticate_first(self, session: Session) -> bool:
        return await super()._authenticate(session, ListenerConfig())

    async def _authenticate(self, session: Session, _: ListenerConfig) -> bool:
        """Already decided in `_initialize_client_session`; answering again would cost a second argon2 run."""
        if getattr(session, _PREAUTHORIZED, False):
            setattr(session, _PREAUTHORIZED, False)
            return True
        return await super()._authenticate(session, _)

    async def _topic_filtering(self, session: Session, topic: str, action: Action) -> bool:
        """RECEIVE needs no second look: every subscription was checked against the ACL when it was made, a
        session never changes identity (`session_key`), and skipping the plugin per message keeps fan-in cheap.
        PUBLISH asks the plugins once per identity and topic: the rules are fixed for the broker's life, and the
        plugins' round trip (a task per plugin, gathered) was 8 % of the loop at 500 nodes."""
        if action == Action.RECEIVE:
            return True
        if action != Action.PUBLISH:
            return await super()._topic_filtering(session, topic, action)
        key = (session.username, topic)
        allowed = self._publish_decisions.get(key)
        if allowed is None:
            allowed = await super()._topic_filtering(session, topic, action)
            if len(self._publish_decisions) >= PUBLISH_DECISIONS_KEPT:
                self._publish_decisions.clear()
            self._publish_decisions[key] = allowed
        return allowed

    async def _publish_retained_messages_for_subscription(
        self, subscription: tuple[str, int], session: Session
    ) -> None:
        topic_filter, _requested = subscription
        granted = next(
            (qos for s, qos in self._subscriptions.get(topic_filter, []) if s.client_id == session.client_id),
            None,
        )
        if granted is None:
            return  # amqtt calls this for every filter anyone subscribed to; only the session's own count
        handler = self._get_handler(session)
        if handler is None:
            return
        tasks = [
            asyncio.ensure_future(
                handler.mqtt_publish(
                    retained.topic,
                    retained.data,
                    min(granted, retained.qos if retained.qos is not None else granted),
                    retain=True,
                )
            )
            for topic, retained in list(self._retained_messages.items())
            if self._matches(topic, topic_filter)
        ]
        if tasks:
            await asyncio.wait(tasks)


def _hashes_or_none(path: Path) -> dict[str, str] | None:
    """The password file's hashes, or None while it cannot be read (the auth plugin says why)."""
    try:
        return read_password_file(path)
    except CredentialsError:
        return None


def _peer_left(transport: asyncio.BaseTransport) -> bool:
    """Has the client closed its side (FIN or reset received), even with bytes still unread in the socket?

    poll()'s POLLRDHUP (Linux) says so at once, where reading would first drain the backlog."""
    if transport.is_closing():
        return True
    sock = transport.get_extra_info("socket")
    fd = sock.fileno() if sock is not None else -1
    if fd < 0:
        return True
    poller = select.poll()
    poller.register(fd, _HANGUP)
    return any(events & _HANGUP for _, events in poller.poll(0))


def _unread_bytes(transport: asyncio.BaseTransport) -> int:
    """Bytes received on the connection's socket and not read yet (FIONREAD), 0 when that cannot be known."""
    sock = transport.get_extra_info("socket")
    fd = sock.fileno() if sock is not None else -1
    if fd < 0:
        return 0
    try:
        return int(struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0])
    except OSError:
        return 0


_HANGUP = getattr(select, "POLLRDHUP", 0) | select.POLLHUP | select.POLLERR


def _drop_silent_client(handler: BrokerProtocolHandler) -> None:
    client_id = handler.session.client_id if handler.session else None
    log.info(f"{client_id}: silent for 1.5x its keepalive, disconnecting (its will is published)")
    task = asyncio.ensure_future(handler.handle_connection_closed())
    _background.add(task)
    task.add_done_callback(_background.discard)


_background: set[asyncio.Future[None]] = set()


async def close_listeners(broker: Broker) -> None:
    """Close the listeners that did bind and the plugins (the retained store), when start() failed."""
    for server in broker._servers.values():
        with contextlib.suppress(OSError):
            await server.close_instance()
    await broker.plugins_manager.close()
