"""What the console tests share: the stack as processes (broker, zone simulator, robot agent, console), an
MQTT client that plays node s1 (so a test decides when it says `blocked`), and Debian's Chromium via Playwright.
"""

from __future__ import annotations

import base64
import contextlib
import json
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from tests.broker_fixtures import wait_listening
from tests.conftest import require_tool
from tests.stack_fixtures import HEARTBEAT_S, SITE, WSNAV, Proc, Stack
from wsnav.broker.mosquitto.process import free_port
from wsnav.runtime.bus import Will
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.messages import NodeStatus, ZoneState

CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


class NodeS1:
    """Node s1 of the sandbox site over a real MQTT link with its own credentials, birth and will."""

    def __init__(self, stack: Stack) -> None:
        creds = load_credentials(stack.creds / "s1.json")
        status = topics.node_status(SITE, "s1")
        self.bus = connect_with_credentials(
            stack.host,
            stack.port,
            creds,
            will=Will(status, NodeStatus(node="s1", status="offline").to_payload()),
            birth=Will(status, NodeStatus(node="s1", status="online").to_payload()),
        )
        self.seq = 0
        self.state = "clear"
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.silent = threading.Event()
        """Set: the node stays connected but says nothing (hung firmware): it turns stale."""
        self._beat = threading.Thread(target=self._heartbeat, daemon=True)
        self._beat.start()

    def say(self, state: str) -> None:
        with self._lock:
            self.state = state
            self.seq += 1
            msg = ZoneState(zone="upper", node="s1", state=state, seq=self.seq)  # type: ignore[arg-type]
            self.bus.publish(topics.zone_state(SITE, "upper", "s1"), msg.to_payload(), qos=1, retain=True)

    def _heartbeat(self) -> None:
        """As the firmware does: the current state again every heartbeat (1 s on this site)."""
        while not self._stop.wait(HEARTBEAT_S):
            if not self.silent.is_set():
                self.say(self.state)

    def close(self) -> None:
        self._stop.set()
        self._beat.join(5)
        self.bus.close()


@dataclass
class ConsoleStack:
    stack: Stack
    console: Proc
    url: str
    password: str
    node: NodeS1
    zones: Proc
    robot: Proc
    extra: list[Proc] = field(default_factory=list)

    def request(
        self,
        method: str,
        path: str,
        body: bytes | dict[str, Any] | None = None,
        *,
        basic: tuple[str, str] | None = None,
        headers: dict[str, str] | None = None,
    ) -> tuple[int, dict[str, Any]]:
        """An HTTP request from a script: (status, JSON body)."""
        data = json.dumps(body).encode() if isinstance(body, dict) else body
        req = urllib.request.Request(self.url + path, data=data, method=method, headers=headers or {})
        if isinstance(body, dict):
            req.add_header("Content-Type", "application/json")
        if basic is not None:
            req.add_header(
                "Authorization", "Basic " + base64.b64encode(f"{basic[0]}:{basic[1]}".encode()).decode()
            )
        try:
            with urllib.request.urlopen(req, timeout=20) as res:
                return res.status, json.loads(res.read() or b"{}")
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read() or b"{}")

    def state(self) -> dict[str, Any]:
        code, body = self.request("GET", "/api/state", basic=("operator", self.password))
        assert code == 200, body
        return body

    def robot_status(self) -> dict[str, Any]:
        return next(r for r in self.state()["robots"] if r["id"] == "robot1")


STARTUP_FAILURE = 3
"""uvicorn's exit when it cannot listen: a free port found was taken by another process before the console bound
it (this machine runs several test sessions at once); another free port is tried."""


def start_console(stack: Stack, port: int | None = None) -> tuple[Proc, str]:
    """`wsnav console` on `port` (a free one by default), its sessions under the stack's work directory."""
    for attempt in range(3):
        proc, url = _start_console(stack, port if port is not None else free_port())
        code = proc.popen.poll()
        if code is None:
            return proc, url
        if code != STARTUP_FAILURE or port is not None or attempt == 2:
            raise RuntimeError(f"the console exited with {code}: {proc.output()[-2000:]}")
    raise AssertionError("unreachable")


def _start_console(stack: Stack, port: int) -> tuple[Proc, str]:
    proc = stack.start(
        "console",
        [
            *WSNAV,
            "console",
            "--site",
            str(stack.site),
            "--broker",
            stack.broker_addr,
            "--credentials",
            str(stack.creds / "operator.json"),
            "--bind",
            f"127.0.0.1:{port}",
            "--state-dir",
            str(stack.work / "console-state"),
        ],
    )
    with contextlib.suppress(RuntimeError):  # it exited: start_console looks at why
        wait_listening("127.0.0.1", port, proc.popen)
    return proc, f"http://127.0.0.1:{port}"


@contextlib.contextmanager
def chromium() -> Iterator[Any]:
    """Debian's Chromium through Playwright (no browser download)."""
    executable = require_tool("chromium")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


def until(what: str, done: Any, timeout_s: float = 30.0, every_s: float = 0.2) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = done()
        if value:
            return value
        assert time.monotonic() < deadline, f"timed out waiting for: {what}"
        time.sleep(every_s)


def observer(stack: Stack, *filters: str) -> MqttBus:
    bus = connect_with_credentials(
        stack.host,
        stack.port,
        load_credentials(stack.creds / "operator.json"),
        client_id=f"test-observer-{time.monotonic_ns()}",
    )
    for f in filters:
        bus.subscribe(f)
    time.sleep(0.3)
    return bus
