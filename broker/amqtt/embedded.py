"""Start the configured broker from other code: in this event loop, in a background thread, or as a process.

For tests, the demo and the experiment harness: each helper listens on 127.0.0.1 with a free port by default,
creates the credentials folder when none is given, and stops cleanly (retained store flushed).

    async with embedded_broker(site_dir) as b:        # in an asyncio program
        ... connect to b.host, b.port with b.credentials(id) ...
    with BrokerThread(site_dir) as b:                  # from synchronous code (paho clients, pytest)
        ...
    with BrokerProcess(site_dir, creds, data_dir=d) as p:   # `wsnav broker run` as a child process
        p.terminate(); p.kill() ...
"""

from __future__ import annotations

import asyncio
import os
import re
import resource
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from types import TracebackType
from typing import IO

from wsnav.broker.amqtt.config import BrokerOptions
from wsnav.broker.amqtt.server import RunningBroker, serve, start_broker
from wsnav.broker.credentials import write_credentials
from wsnav.broker.identity_limits import IdentityLimits
from wsnav.schemas.credentials import Credentials, load_credentials
from wsnav.schemas.site import Site, load_site
from wsnav.schemas.site_file import SiteFile

SiteLike = Site | SiteFile | Path | str

SIMULATION_LIMITS = IdentityLimits(node_publish_rate=None, login_rate=None)
"""Simulated nodes run as fast as the experiment's clock goes, far above a real node's rate (and reconnect as
often)."""


@dataclass
class BrokerInfo:
    """Where a started broker listens and where the ids' credentials are."""

    host: str
    port: int
    credentials_dir: Path
    site: str
    extra: dict[str, tuple[str, int]] = field(default_factory=dict)

    def credentials(self, ident: str) -> Credentials:
        """The credentials (a NodeConfig for a node) of one id: username and password to connect with."""
        return load_credentials(self.credentials_dir / f"{ident}.json")


def _spec(site: SiteLike) -> SiteFile:
    if isinstance(site, Site):
        return site.spec
    if isinstance(site, SiteFile):
        return site
    return load_site(site).spec


def _credentials(
    spec: SiteFile, credentials_dir: Path | None, keep: list[tempfile.TemporaryDirectory[str]]
) -> Path:
    if credentials_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="wsnav-credentials-")
        keep.append(tmp)
        credentials_dir = Path(tmp.name)
        write_credentials(spec, credentials_dir)
    return credentials_dir


@asynccontextmanager
async def embedded_broker(
    site: SiteLike,
    credentials_dir: Path | None = None,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    data_dir: Path | None = None,
    flush_interval_s: float = 0.2,
) -> AsyncIterator[BrokerInfo]:
    """The broker in the running event loop; credentials generated into a temporary folder when None."""
    spec = _spec(site)
    temporaries: list[tempfile.TemporaryDirectory[str]] = []
    creds = _credentials(spec, credentials_dir, temporaries)
    options = BrokerOptions(
        bind=(host, port), data_dir=data_dir, flush_interval_s=flush_interval_s, limits=SIMULATION_LIMITS
    )
    running = await start_broker(spec, creds, options)
    try:
        yield _info(running, creds, spec)
    finally:
        await running.stop()
        for tmp in temporaries:
            tmp.cleanup()


def _info(running: RunningBroker, creds: Path, spec: SiteFile) -> BrokerInfo:
    extra = {k: v for k, v in running.addresses.items() if k != "default"}
    return BrokerInfo(running.host, running.port, creds, spec.name, extra)


class BrokerThread:
    """The broker on its own event loop in a daemon thread: for synchronous callers (paho clients, tests)."""

    def __init__(
        self,
        site: SiteLike,
        credentials_dir: Path | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        data_dir: Path | None = None,
        flush_interval_s: float = 0.2,
        start_timeout_s: float = 30.0,
        options: BrokerOptions | None = None,
    ) -> None:
        """`options`, when given, replaces host, port, data_dir and flush_interval_s (e.g. to add WebSocket
        or TLS listeners; their bound addresses are in `info.extra`)."""
        self._spec = _spec(site)
        self._temporaries: list[tempfile.TemporaryDirectory[str]] = []
        self._creds = _credentials(self._spec, credentials_dir, self._temporaries)
        self._options = options or BrokerOptions(
            bind=(host, port), data_dir=data_dir, flush_interval_s=flush_interval_s, limits=SIMULATION_LIMITS
        )
        self._timeout = start_timeout_s
        self._ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self.info: BrokerInfo | None = None

    @property
    def host(self) -> str:
        return self._started().host

    @property
    def port(self) -> int:
        return self._started().port

    @property
    def credentials_dir(self) -> Path:
        return self._creds

    def credentials(self, ident: str) -> Credentials:
        return self._started().credentials(ident)

    def _started(self) -> BrokerInfo:
        if self.info is None:
            raise RuntimeError("broker not started")
        return self.info

    def start(self) -> BrokerInfo:
        """Start and wait until the listener accepts connections; raises the start error if any."""
        self._thread = threading.Thread(target=self._run, name="wsnav-broker", daemon=True)
        self._thread.start()
        if not self._ready.wait(self._timeout):
            raise TimeoutError(f"broker did not start within {self._timeout:g} s")
        if self._error is not None:
            raise self._error
        return self._started()

    def stop(self, timeout_s: float = 30.0) -> None:
        """Shut down cleanly (flushes the retained store) and join the thread."""
        if self._loop is not None and self._stop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(timeout_s)
        for tmp in self._temporaries:
            tmp.cleanup()
        self._temporaries.clear()

    def _run(self) -> None:
        async def main() -> None:
            self._loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()

            def ready(running: RunningBroker) -> None:
                self.info = _info(running, self._creds, self._spec)
                self._ready.set()

            await serve(self._spec, self._creds, self._options, ready, self._stop)

        try:
            asyncio.run(main())
        except BaseException as exc:
            self._error = exc
        finally:
            self._ready.set()

    def __enter__(self) -> BrokerThread:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


def _limit_open_files(limit: int) -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (limit, limit))


_READY = re.compile(r"^broker ready on (\[[^\]]+\]|[^:\s]+):(\d+)")


class BrokerProcess:
    """`wsnav broker run` as a child process (what systemd runs); waits for its ready line."""

    def __init__(
        self,
        site: Path,
        credentials_dir: Path,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        data_dir: Path | None = None,
        extra_args: list[str] | None = None,
        start_timeout_s: float = 60.0,
        open_files: int | None = None,
    ) -> None:
        """`open_files`: the child's RLIMIT_NOFILE (soft and hard), as systemd's LimitNOFILE would set it."""
        self.open_files = open_files
        self.args = [
            sys.executable,
            "-m",
            "wsnav.cli",
            "broker",
            "run",
            "--site",
            str(site),
            "--credentials",
            str(credentials_dir),
            "--bind",
            f"{host}:{port}",
            *(["--data", str(data_dir)] if data_dir is not None else []),
            *(extra_args or []),
        ]
        self.credentials_dir = credentials_dir
        self._timeout = start_timeout_s
        self.proc: subprocess.Popen[str] | None = None
        self.host = host
        self.port = port
        self.output: list[str] = []
        """stdout lines so far."""
        self.errors: list[str] = []
        """stderr lines so far."""
        self._pumps: list[threading.Thread] = []

    def start(self) -> BrokerProcess:
        """Spawn and wait for `broker ready on HOST:PORT`; raises RuntimeError with the process's stderr."""
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen(
            self.args,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            start_new_session=True,
            preexec_fn=None if self.open_files is None else partial(_limit_open_files, self.open_files),
        )
        ready = threading.Event()
        found: list[tuple[str, int]] = []

        def pump_stdout(stream: IO[str]) -> None:
            for line in iter(stream.readline, ""):
                self.output.append(line)
                match = _READY.match(line)
                if match and not found:
                    found.append((match.group(1).strip("[]"), int(match.group(2))))
                    ready.set()
            ready.set()

        def pump_stderr(stream: IO[str]) -> None:
            self.errors.extend(
                iter(stream.readline, "")
            )  # drained, so a chatty broker never blocks on a pipe

        assert self.proc.stdout is not None and self.proc.stderr is not None
        self._pumps = [
            threading.Thread(target=pump_stdout, args=(self.proc.stdout,), daemon=True),
            threading.Thread(target=pump_stderr, args=(self.proc.stderr,), daemon=True),
        ]
        for pump in self._pumps:
            pump.start()
        ready.wait(self._timeout)
        if not found:
            self.kill()
            reason = "".join(self.errors).strip() or f"no ready line within {self._timeout:g} s"
            raise RuntimeError(f"broker process did not become ready: {reason}")
        self.host, self.port = found[0]
        return self

    def terminate(self, timeout_s: float = 30.0) -> int:
        """SIGTERM and wait: the clean shutdown path."""
        return self.stop_with(signal.SIGTERM, timeout_s)

    def kill(self, timeout_s: float = 30.0) -> int:
        """SIGKILL (kill -9) and wait: the crash path."""
        return self.stop_with(signal.SIGKILL, timeout_s)

    def stop_with(self, sig: signal.Signals, timeout_s: float = 30.0) -> int:
        """Send `sig`, wait for the exit and for the output's last line (read by the pump threads)."""
        if self.proc is None:
            return 0
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        code = self.proc.wait(timeout_s)
        for pump in self._pumps:
            pump.join(timeout_s)
        return code

    def __enter__(self) -> BrokerProcess:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.terminate()
