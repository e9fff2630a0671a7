"""Shared by the broker tests (no tests here): paho clients that wait on events, and a Mosquitto runner.

Everything waits on a condition with a generous timeout, never on a fixed sleep, so the tests hold on a busy
2-core machine.
"""

from __future__ import annotations

import contextlib
import os
import queue
import random
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.reasoncodes import ReasonCode

from tests.conftest import require_tool, unavailable
from wsnav.broker.amqtt.retained_store import read_retained
from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.broker.mosquitto.plugin import PluginBuildError, build_plugin
from wsnav.broker.mosquitto.process import free_port
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.site import load_site

TIMEOUT = 30.0


@dataclass(frozen=True)
class Endpoint:
    """A running broker under test: where it listens and where the ids' credentials are."""

    kind: str
    host: str
    port: int
    credentials_dir: Path

    def password(self, ident: str) -> str:
        return load_credentials(self.credentials_dir / f"{ident}.json").password


@dataclass(frozen=True)
class Received:
    topic: str
    payload: bytes
    qos: int
    retain: bool


class Client:
    """A paho client whose connect/subscribe/publish block until the broker answered."""

    def __init__(
        self,
        endpoint: Endpoint,
        client_id: str,
        username: str | None,
        password: str | None,
        clean_session: bool = True,
    ) -> None:
        self.endpoint = endpoint
        self.mqtt = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=clean_session)
        self.disconnects: list[ReasonCode] = []
        if username is not None:
            self.mqtt.username_pw_set(username, password)
        self.messages: queue.Queue[Received] = queue.Queue()
        self.received: list[Received] = []
        self._connack: queue.Queue[ReasonCode] = queue.Queue()
        self._subacks: dict[int, threading.Event] = {}
        self._granted: dict[int, list[int]] = {}
        self.mqtt.on_connect = self._on_connect
        self.mqtt.on_message = self._on_message
        self.mqtt.on_subscribe = self._on_subscribe
        self.mqtt.on_disconnect = self._on_disconnect

    def _on_connect(self, _c: object, _u: object, _f: object, reason: ReasonCode, _p: object) -> None:
        self._connack.put(reason)

    def _on_disconnect(self, _c: object, _u: object, _f: object, reason: ReasonCode, _p: object) -> None:
        self.disconnects.append(reason)
        if reason.is_failure:
            self._connack.put(reason)

    def _on_message(self, _c: object, _u: object, msg: mqtt.MQTTMessage) -> None:
        item = Received(msg.topic, bytes(msg.payload), msg.qos, bool(msg.retain))
        self.received.append(item)
        self.messages.put(item)

    def _on_subscribe(self, _c: object, _u: object, mid: int, reasons: list[ReasonCode], _p: object) -> None:
        self._granted[mid] = [r.value for r in reasons]
        self._subacks.setdefault(mid, threading.Event()).set()

    def connect(self, will: tuple[str, bytes] | None = None) -> ReasonCode:
        """Connect and wait for CONNACK (or the refusal); returns the reason code."""
        if will is not None:
            self.mqtt.will_set(will[0], will[1], qos=1, retain=True)
        self.mqtt.connect(self.endpoint.host, self.endpoint.port, keepalive=30)
        self.mqtt.loop_start()
        try:
            return self._connack.get(timeout=TIMEOUT)
        except queue.Empty:
            raise TimeoutError("no CONNACK") from None

    def subscribe(self, topic: str | list[str], qos: int = 1) -> list[int]:
        """Subscribe (several filters go in one SUBSCRIBE) and wait for SUBACK; returns the granted QoS codes
        (128 = refused)."""
        result, mid = self.mqtt.subscribe(topic if isinstance(topic, str) else [(t, qos) for t in topic], qos)
        assert result == mqtt.MQTT_ERR_SUCCESS and mid is not None
        event = self._subacks.setdefault(mid, threading.Event())
        assert event.wait(TIMEOUT), f"no SUBACK for {topic}"
        return self._granted[mid]

    def publish(self, topic: str, payload: bytes, qos: int = 1, retain: bool = False) -> None:
        """Publish; with QoS 1 wait for the PUBACK."""
        info = self.mqtt.publish(topic, payload, qos=qos, retain=retain)
        if qos:
            info.wait_for_publish(TIMEOUT)
            assert info.is_published(), f"no PUBACK for {topic}"

    def wait_for(self, topic: str, payload: bytes | None = None, timeout: float = TIMEOUT) -> Received:
        """The first message (already received or arriving) on `topic` (with `payload`, when given)."""
        deadline = time.monotonic() + timeout
        seen = 0
        while True:
            for item in self.received[seen:]:
                if item.topic == topic and (payload is None or item.payload == payload):
                    return item
            seen = len(self.received)
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"nothing on {topic} within {timeout:g} s; got {self.topics()}")
            with contextlib.suppress(queue.Empty):
                self.messages.get(timeout=min(left, 0.5))

    def topics(self) -> list[str]:
        return [m.topic for m in self.received]

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.mqtt.disconnect()
        self.mqtt.loop_stop()


@contextlib.contextmanager
def client(
    endpoint: Endpoint, ident: str | None, client_id: str | None = None, clean_session: bool = True
) -> Iterator[Client]:
    """A connected client for a site id (its own password), refused connects raise AssertionError."""
    c = Client(
        endpoint,
        client_id or ident or "anonymous",
        ident,
        endpoint.password(ident) if ident else None,
        clean_session,
    )
    try:
        reason = c.connect()
        assert not reason.is_failure, f"{ident} refused: {reason}"
        yield c
    finally:
        c.close()


def connect_reason(
    endpoint: Endpoint,
    username: str | None,
    password: str | None,
    client_id: str = "probe",
    will: tuple[str, bytes] | None = None,
) -> ReasonCode:
    c = Client(endpoint, client_id, username, password)
    try:
        return c.connect(will)
    finally:
        c.close()


def port_outside_ephemeral_range(host: str = "127.0.0.1") -> int:
    """A free port the kernel never hands to an outgoing connection: a broker restarted on it cannot find it
    taken by a client that, retrying while the broker was down, connected to itself from that very port."""
    low, _ = (int(v) for v in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    rng = random.Random()
    for _ in range(200):
        port = rng.randrange(max(1024, low - 12000), low)
        with socket.socket() as probe:
            try:
                probe.bind((host, port))
                return port
            except OSError:
                continue
    raise RuntimeError("no free port below the ephemeral range")


def wait_listening(host: str, port: int, proc: subprocess.Popen[bytes] | None = None) -> None:
    """Until a TCP connect succeeds (or the process died)."""
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            err = proc.stderr.read().decode() if proc.stderr else ""
            raise RuntimeError(f"process exited with {proc.returncode}: {err}")
        with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=1):
            return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listening on {host}:{port}")


def wsnav(*args: str | Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "wsnav.cli", *map(str, args)], capture_output=True, text=True, timeout=timeout
    )


def wait_stored(data: Path, expected: dict[str, bytes]) -> None:
    """Until the store on disk holds exactly these topics (the flusher runs within its interval)."""
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        stored = {t: p for t, (p, _q) in read_retained(data).items()}
        if stored == expected:
            return
        time.sleep(0.05)
    raise AssertionError(f"store holds {read_retained(data)}, expected {expected}")


@contextlib.contextmanager
def mosquitto_on(
    site: Path, creds: Path, conf: Path, data: Path, *, log: Path | None = None, **options: Any
) -> Iterator[tuple[Endpoint, subprocess.Popen[bytes]]]:
    """Mosquitto from the generated config (`options` for MosquittoOptions: its defaults, a save every 2 s, unless
    given), its store in `data`, its log appended to `log` (else dropped); stopped cleanly (SIGTERM: it saves
    once more) unless the test killed it."""
    mosquitto = require_tool("mosquitto")
    port = free_port()
    user = "root" if os.geteuid() == 0 else None
    settings = MosquittoOptions(**{"bind": ("127.0.0.1", port), "data_dir": data, "user": user, **options})
    write_mosquitto_config(load_site(site).spec, creds, conf, settings)
    with contextlib.ExitStack() as files:
        stderr = files.enter_context(log.open("ab")) if log is not None else subprocess.DEVNULL
        proc = subprocess.Popen([mosquitto, "-c", str(conf / CONF)], stderr=stderr)
    try:
        wait_listening("127.0.0.1", port, proc)
        yield Endpoint("mosquitto", "127.0.0.1", port, creds), proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            assert proc.wait(30) == 0


def store_guard_plugin(out: Path) -> Path:
    """wsnav's Mosquitto plugin built from the repo's source into `out` (skips without a compiler or Debian's
    mosquitto-dev, fails so under WSNAV_REQUIRE_TOOLS=1)."""
    try:
        return build_plugin(out)
    except PluginBuildError as exc:
        unavailable(str(exc))
