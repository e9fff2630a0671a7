"""Start, serve and stop the configured amqtt broker (our amqtt overrides live in wsnav.broker.amqtt.patch).

- A listener that cannot bind: amqtt keeps running with no listener; `start_broker` raises `BrokerStartError`
  with one line instead, after closing whatever did open, so the caller exits non-zero.
- SIGTERM and SIGINT (the amqtt CLI dies on SIGTERM without shutdown): `serve` turns them into a clean
  `Broker.shutdown()`, which flushes the retained store.
- Garbage collection: every object alive is frozen out of collections every 0.25 s, without a collection
  (wsnav.broker.amqtt.gc_pacing), so no collection stalls every delivery for a walk over 1000 nodes' objects.
- Descriptors: the soft open-file limit is raised to the hard one, and the connection cap kept below it
  (wsnav.broker.amqtt.admission).
"""

from __future__ import annotations

import asyncio
import logging
import signal
import socket
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from amqtt.broker import Broker
from amqtt.errors import AMQTTError, BrokerError, PluginError, PluginLoadError

from wsnav.broker.amqtt.admission import Admission, connection_capacity, raise_descriptor_limit
from wsnav.broker.amqtt.config import BrokerOptions, amqtt_config, bind_text
from wsnav.broker.amqtt.gc_pacing import pace_collections
from wsnav.broker.amqtt.patch import WsnavBroker, close_listeners
from wsnav.broker.credentials import PASSWORD_FILE, read_password_file
from wsnav.schemas.credentials import CredentialsError
from wsnav.schemas.site_file import SiteFile

log = logging.getLogger("wsnav.broker")


class BrokerStartError(RuntimeError):
    """The broker could not start; str() is one line for the user."""


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
    capacity = connection_capacity(options.max_connections, raise_descriptor_limit())
    try:
        broker = WsnavBroker(
            amqtt_config(spec, credentials_dir, options),
            Admission(capacity),
            max_packet_bytes=options.max_packet_bytes,
            connect_timeout_s=options.connect_timeout_s,
            limits=options.limits,
            nodes=frozenset(node.id for node in spec.nodes),
            password_file=credentials_dir / PASSWORD_FILE,
        )
    except (AMQTTError, PluginError, PluginLoadError, OSError, ValueError) as exc:
        raise BrokerStartError(f"cannot configure the broker: {_root_cause(exc)}") from None
    try:
        await broker.start()
    except (BrokerError, AMQTTError, OSError) as exc:
        await close_listeners(broker)
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
        if loop.get_exception_handler() is None:
            loop.set_exception_handler(partial(_loop_exception, running.broker.admission))
        pacer = (
            asyncio.create_task(
                pace_collections(
                    options.gc_freeze_s, options.gc_refresh_s, ended=lambda: running.broker.connections_ended
                )
            )
            if options.gc_freeze_s > 0
            else None
        )
        try:
            on_ready(running)
            await stop.wait()
        finally:
            if pacer is not None:
                pacer.cancel()
            await running.stop()
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)


def _loop_exception(
    admission: Admission, loop: asyncio.AbstractEventLoop, context: dict[str, object]
) -> None:
    """asyncio logs a traceback per failed accept(); a port under attack would fill the disk with them."""
    if context.get("message") == "socket.accept() out of system resource":
        admission.out_of_descriptors()
        return
    loop.default_exception_handler(context)


def _bound_addresses(broker: Broker) -> dict[str, tuple[str, int]]:
    addresses: dict[str, tuple[str, int]] = {}
    for name, server in broker._servers.items():
        sockets = list(getattr(server.instance, "sockets", None) or [])
        if sockets:
            sock: socket.socket = sockets[0]
            host, port = sock.getsockname()[:2]
            addresses[name] = (str(host), int(port))
    return addresses


def _root_cause(exc: BaseException) -> str:
    while exc.__cause__ is not None:
        exc = exc.__cause__
    text = str(exc.args[1]) if isinstance(exc, OSError) and len(exc.args) > 1 else str(exc)
    return " ".join(text.split()) or type(exc).__name__
