"""Start, serve and stop the configured amqtt broker, with amqtt 0.12.1's broker-side bugs neutralised.

- Fact 1 (a connecting client receives the retained messages matching *other* clients' subscriptions) and
  fact 2 (a retained QoS 0 message is delivered at the subscriber's QoS): `WsnavBroker` sends retained messages
  only for the session's own subscriptions, at min(granted QoS, stored QoS).
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
from amqtt.errors import AMQTTError, BrokerError, PluginError, PluginLoadError
from amqtt.mqtt.protocol.broker_handler import BrokerProtocolHandler
from amqtt.session import Session

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


class WsnavBroker(Broker):
    """amqtt's Broker with retained-message delivery (facts 1, 2) and keepalive (fact 4) fixed."""

    async def _initialize_client_session(
        self, reader: ReaderAdapter, writer: WriterAdapter, remote_address: str, remote_port: int
    ) -> tuple[BrokerProtocolHandler, Session]:
        handler, session = await super()._initialize_client_session(
            reader, writer, remote_address, remote_port
        )
        if session.keep_alive > 0:
            # amqtt's reader already times out after keep_alive seconds, then calls a handler hook that does
            # nothing: stretch the timeout to the spec's 1.5x and make the hook end the session abnormally.
            session.keep_alive = math.ceil(session.keep_alive * 1.5)
            setattr(handler, "handle_read_timeout", partial(_drop_silent_client, handler))  # noqa: B010
        return handler, session

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
