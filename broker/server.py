"""Start, serve and stop the configured amqtt broker, with amqtt 0.12.1's broker-side bugs neutralised.

- Fact 1 (a connecting client receives the retained messages matching *other* clients' subscriptions) and
  fact 2 (a retained QoS 0 message is delivered at the subscriber's QoS): `WsnavBroker` sends retained messages
  only for the session's own subscriptions, at min(granted QoS, stored QoS).
- Authentication before session lookup: see `WsnavBroker._initialize_client_session` (an unauthenticated
  client could otherwise blind a connected robot by reusing its client id).
- Fact 4 (silent clients are never dropped): a client that sends nothing for 1.5 x its keepalive (MQTT 3.1.1
  section 3.1.2.10) is disconnected as abnormal, so its last will (`offline`) is published: a node that loses
  power is reported within seconds, not never.
- Fact 3 (a listener that cannot bind leaves a process with no listener): `start_broker` raises
  `BrokerStartError` with one line, after closing whatever did open, so the caller exits non-zero.
- Fact 8 (the amqtt CLI dies on SIGTERM without shutdown): `serve` turns SIGTERM and SIGINT into a clean
  `Broker.shutdown()`, which flushes the retained store.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import signal
import socket
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from amqtt.adapters import ReaderAdapter, WriterAdapter
from amqtt.broker import Broker
from amqtt.contexts import Action, ListenerConfig
from amqtt.errors import AMQTTError, BrokerError, MQTTError, NoDataError, PluginError, PluginLoadError
from amqtt.mqtt.protocol.broker_handler import BrokerProtocolHandler
from amqtt.mqtt.puback import PubackPacket
from amqtt.session import OUTGOING, IncomingApplicationMessage, OutgoingApplicationMessage, Session
from amqtt.utils import gen_client_id

from broker.amqtt_config import BrokerOptions, amqtt_config, bind_text
from broker.credentials import PASSWORD_FILE, CredentialsError, read_password_file
from schemas.site_file import SiteFile

log = logging.getLogger("wsnav.broker")


class BrokerStartError(RuntimeError):
    """The broker could not start; str() is one line for the user."""


class _DropStartupTraceback(logging.Filter):
    """amqtt logs a full traceback when a listener cannot bind; we report that failure in one line instead."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.getMessage() != "Broker startup failed"


logging.getLogger("amqtt.broker").addFilter(_DropStartupTraceback())


_PREAUTHORIZED = "_wsnav_preauthorized"


class WsnavProtocolHandler(BrokerProtocolHandler):
    """amqtt's per-client handler with the QoS 1 send race fixed.

    amqtt 0.12.1 sends PUBLISH and only then registers the PUBACK waiter; on a fast link the PUBACK can come
    first ("Received PUBACK for unknown pending message"), and the send then hangs 5 s and fails. Registering
    the waiter first removes the race.
    """

    async def _handle_qos1_message_flow(
        self, app_message: OutgoingApplicationMessage | IncomingApplicationMessage
    ) -> None:
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


class WsnavBroker(Broker):
    """amqtt's Broker with retained-message delivery (facts 1, 2) and keepalive (fact 4) fixed."""

    async def _initialize_client_session(
        self, reader: ReaderAdapter, writer: WriterAdapter, remote_address: str, remote_port: int
    ) -> tuple[BrokerProtocolHandler, Session]:
        """amqtt's version, but authenticating *before* the client id is looked up.

        amqtt 0.12.1 deletes the old session of a clean-session client id (or merges username, password and
        will into a persistent one) before it checks the password: any unauthenticated client could silently
        cut a connected robot off its subscriptions, or plant a will on its session, by using its client id.
        """
        try:
            handler, session = await BrokerProtocolHandler.init_from_connect(
                reader, writer, self.plugins_manager
            )
        except AMQTTError as exc:
            raise AMQTTError(exc) from exc
        except MQTTError as exc:
            await writer.close()
            raise MQTTError(exc) from exc
        except NoDataError as exc:
            raise AMQTTError(exc) from exc
        session.parent = 0
        if not await self._authenticate_first(session):
            handler.attach(session, reader, writer)
            await handler.mqtt_connack_authorize(False)
            await writer.close()
            raise AMQTTError(f"connection refused: not authorized (client id {session.client_id!r})")

        if session.clean_session:
            if session.client_id:
                await self._delete_session(session.client_id)
            else:
                session.client_id = gen_client_id()
        elif session.client_id in self._sessions:
            existing, _ = self._sessions[session.client_id]
            for name in (
                "will_flag",
                "will_message",
                "will_topic",
                "will_qos",
                "keep_alive",
                "username",
                "password",
            ):
                setattr(existing, name, getattr(session, name))
            session = existing
            session.parent = 1
        if session.keep_alive > 0:
            # amqtt's reader times out after keep_alive seconds, then calls a handler hook that does nothing:
            # stretch the timeout to the spec's 1.5x and make the hook end the session abnormally (fact 4).
            session.keep_alive = math.ceil(session.keep_alive * 1.5)
            setattr(handler, "handle_read_timeout", partial(_drop_silent_client, handler))  # noqa: B010
        setattr(session, _PREAUTHORIZED, True)
        return handler, session

    async def _authenticate_first(self, session: Session) -> bool:
        return await super()._authenticate(session, ListenerConfig())

    async def _authenticate(self, session: Session, _: ListenerConfig) -> bool:
        """Already decided in `_initialize_client_session`; answering again would cost a second argon2 run."""
        if getattr(session, _PREAUTHORIZED, False):
            setattr(session, _PREAUTHORIZED, False)
            return True
        return await super()._authenticate(session, _)

    async def _topic_filtering(self, session: Session, topic: str, action: Action) -> bool:
        """RECEIVE needs no second look: every subscription was checked against the ACL when it was made, and
        skipping the plugin round trip per delivered message keeps fan-in cheap."""
        if action == Action.RECEIVE:
            return True
        return await super()._topic_filtering(session, topic, action)

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


def _drop_silent_client(handler: BrokerProtocolHandler) -> None:
    client_id = handler.session.client_id if handler.session else None
    log.info(f"{client_id}: silent for 1.5x its keepalive, disconnecting (its will is published)")
    task = asyncio.ensure_future(handler.handle_connection_closed())
    _background.add(task)
    task.add_done_callback(_background.discard)


_background: set[asyncio.Future[None]] = set()


@dataclass
class RunningBroker:
    """A started broker and the addresses its listeners really bound (port 0 becomes a free port)."""

    broker: WsnavBroker
    addresses: dict[str, tuple[str, int]]

    @property
    def host(self) -> str:
        return self.addresses["default"][0]

    @property
    def port(self) -> int:
        return self.addresses["default"][1]

    def ready_line(self) -> str:
        """`broker ready on HOST:PORT` (plus other listeners): scripts wait for this line."""
        extra = [f"{name} {bind_text(*addr)}" for name, addr in self.addresses.items() if name != "default"]
        return f"broker ready on {bind_text(self.host, self.port)}" + (
            f" ({', '.join(extra)})" if extra else ""
        )

    async def stop(self) -> None:
        await self.broker.shutdown()


async def start_broker(spec: SiteFile, credentials_dir: Path, options: BrokerOptions) -> RunningBroker:
    """Start amqtt for the site; raises BrokerStartError (one line) on bad credentials, data dir or bind."""
    if not credentials_dir.is_dir():
        raise BrokerStartError(
            f"{credentials_dir}: not a credentials folder (run `wsnav broker credentials`)"
        )
    try:
        read_password_file(credentials_dir / PASSWORD_FILE)
    except CredentialsError as exc:
        raise BrokerStartError(str(exc)) from None
    if options.data_dir is not None:
        try:
            options.data_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        except OSError as exc:
            raise BrokerStartError(
                f"{options.data_dir}: cannot create the data folder: {exc.strerror}"
            ) from None
    try:
        broker = WsnavBroker(amqtt_config(spec, credentials_dir, options))
    except (AMQTTError, PluginError, PluginLoadError, OSError, ValueError) as exc:
        raise BrokerStartError(f"cannot configure the broker: {_root_cause(exc)}") from None
    try:
        await broker.start()
    except (BrokerError, AMQTTError, OSError) as exc:
        await _close_after_failed_start(broker)
        raise BrokerStartError(f"cannot start listening: {_root_cause(exc)}") from None
    return RunningBroker(broker, _bound_addresses(broker))


async def serve(
    spec: SiteFile,
    credentials_dir: Path,
    options: BrokerOptions,
    on_ready: Callable[[RunningBroker], None],
    stop: asyncio.Event | None = None,
) -> None:
    """Run until `stop` is set or SIGTERM/SIGINT arrives, then shut down cleanly (retained store flushed)."""
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    installed: list[signal.Signals] = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        try:
            loop.add_signal_handler(sig, stop.set)
            installed.append(sig)
        except (NotImplementedError, RuntimeError, ValueError):
            pass  # not the main thread (embedded use): the caller sets `stop` instead
    try:
        running = await start_broker(spec, credentials_dir, options)
        try:
            on_ready(running)
            await stop.wait()
        finally:
            await running.stop()
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)


def _bound_addresses(broker: Broker) -> dict[str, tuple[str, int]]:
    addresses: dict[str, tuple[str, int]] = {}
    for name, server in broker._servers.items():
        sockets = list(getattr(server.instance, "sockets", None) or [])
        if sockets:
            sock: socket.socket = sockets[0]
            host, port = sock.getsockname()[:2]
            addresses[name] = (str(host), int(port))
    return addresses


async def _close_after_failed_start(broker: Broker) -> None:
    """Close the listeners that did bind and the plugins (the retained store), since shutdown() is refused."""
    for server in broker._servers.values():
        with contextlib.suppress(OSError):
            await server.close_instance()
    await broker.plugins_manager.close()


def _root_cause(exc: BaseException) -> str:
    while exc.__cause__ is not None:
        exc = exc.__cause__
    text = str(exc.args[1]) if isinstance(exc, OSError) and len(exc.args) > 1 else str(exc)
    return " ".join(text.split()) or type(exc).__name__
