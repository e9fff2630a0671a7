"""The console's intake against hostile messages on both real brokers (amqtt and Mosquitto): whatever one message
does, from a robot's credential or the operator's, retained or live, the console keeps reading, `wsnav status`
answers without a traceback, and a console whose reading thread dies says so at once."""

from __future__ import annotations

import asyncio
import contextlib
import json
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.broker_fixtures import Endpoint, client, wait_listening
from tests.conftest import require_tool
from tests.stack_fixtures import SITE, WSNAV, make_site
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.broker.mosquitto.process import free_port, mosquitto_process
from wsnav.console.live_state import LiveState
from wsnav.console.site_view import Key, SiteView
from wsnav.runtime.clock import WallClock
from wsnav.runtime.mqtt_bus import connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.messages import RobotStatus, ZoneState
from wsnav.schemas.site import load_site

pytestmark = pytest.mark.timeout(120)

NESTED = b"[" * 4000 + b"]" * 4000
"""8,000 bytes of nested JSON: Python's parser raised RecursionError, which stopped the console's thread."""


@pytest.fixture(scope="module")
def site_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_site(tmp_path_factory.mktemp("intake") / "site")


@pytest.fixture(scope="module")
def creds_dir(site_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("creds") / "creds"
    write_credentials(load_site(site_dir).spec, out)
    return out


@pytest.fixture(params=["amqtt", "mosquitto"])
def endpoint(
    request: pytest.FixtureRequest, site_dir: Path, creds_dir: Path, tmp_path: Path
) -> Iterator[Endpoint]:
    """A fresh broker per test: retained poison from one test must not reach the next."""
    if request.param == "amqtt":
        with BrokerThread(site_dir, creds_dir, data_dir=tmp_path / "amqtt") as broker:
            yield Endpoint("amqtt", broker.host, broker.port, creds_dir)
    else:
        require_tool("mosquitto")
        with mosquitto_process(load_site(site_dir).spec, creds_dir, tmp_path / "mosquitto") as mq:
            yield Endpoint("mosquitto", mq.host, mq.port, creds_dir)


def poison() -> list[tuple[str, str, bytes]]:
    """(credential, topic, payload): what a robot's, a node's and the operator's credentials can publish."""
    status = topics.robot_status(SITE, "robot1")
    return [
        ("robot1", status, NESTED),
        ("robot1", status, b'{"v":1,"robot":"robot1","state":"idle","pose":[0,0,0],"state":"stuck"}'),
        ("robot1", status, b'{"v":1,"robot":"robot1","state":"idle","pose":[1e400,0,0]}'),
        ("operator", topics.operator_block(SITE, "op-ghost"), b'{"v":1,"zone":"z99"}'),
        ("operator", topics.operator_block(SITE, "op-nested"), NESTED),
        ("s1", topics.node_info(SITE, "s1"), NESTED),
    ]


def publish(endpoint: Endpoint, messages: list[tuple[str, str, bytes]]) -> None:
    for ident, topic, payload in messages:
        with client(endpoint, ident, f"{ident}-hostile-{time.monotonic_ns()}") as c:
            c.publish(topic, payload, qos=1, retain=True)
            time.sleep(0.05)


def good_status(x: float) -> bytes:
    return RobotStatus(robot="robot1", state="navigating", pose=(x, 0.0, 0.0), goal="P2").to_payload()


def console(endpoint: Endpoint, site_dir: Path) -> LiveState:
    creds = load_credentials(endpoint.credentials_dir / "operator.json")
    clock = WallClock()
    bus = connect_with_credentials(
        endpoint.host, endpoint.port, creds, client_id=f"operator-console-{time.monotonic_ns()}", clock=clock
    )
    live = LiveState(SiteView(load_site(site_dir)), bus, clock)
    live.start()
    return live


def wait_for(what: str, done: object, timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not done():  # type: ignore[operator]
        assert time.monotonic() < deadline, f"timed out waiting for: {what}"
        time.sleep(0.1)


def robot_x(live: LiveState) -> float | None:
    robot = next(r for r in live.snapshot()["robots"] if r["id"] == "robot1")
    return robot["pose"][0] if robot.get("state") else None


def test_retained_and_live_poison_from_a_robot_and_the_operator_stops_no_console(
    endpoint: Endpoint, site_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Retained before the console starts, then live while it runs: each message is dropped, counted and logged
    (rate-limited), and a good status after each is still shown; the page's `broker_connected` stays true only
    because the console really still reads."""
    publish(endpoint, poison())
    live = console(endpoint, site_dir)
    try:
        wait_for("the retained poison read", lambda: sum(live.view.dropped.values()) >= 3)
        time.sleep(0.5)  # every retained message in
        assert live.snapshot()["broker_connected"] is True
        assert live.snapshot()["blocks"] == [], (
            "a block on a zone the site lacks is not shown, as robots ignore it"
        )
        for i, (ident, topic, payload) in enumerate(poison()):
            publish(endpoint, [(ident, topic, payload)])
            publish(endpoint, [("robot1", topics.robot_status(SITE, "robot1"), good_status(0.1 * (i + 1)))])
            wait_for(
                f"a good status after {topic}", lambda i=i: robot_x(live) == pytest.approx(0.1 * (i + 1))
            )
        snap = live.snapshot()
        assert snap["broker_connected"] is True and "link_error" not in snap
        assert live.view.dropped["unknown_zone"] >= 2 and live.view.dropped["invalid"] >= 8, live.view.dropped
        json.dumps(snap, allow_nan=False)
    finally:
        live.stop()
        live.bus.close()
    drops = [r for r in caplog.records if r.name == "wsnav.console.site_view"]
    assert 1 <= len(drops) <= 6, [r.getMessage() for r in drops]  # one line per reason, not per message
    assert all(r.exc_info is None for r in drops)


def operator_command(endpoint: Endpoint, site_dir: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            *WSNAV,
            *args,
            "--site",
            str(site_dir),
            "--broker",
            f"{endpoint.host}:{endpoint.port}",
            "--credentials",
            str(endpoint.credentials_dir / "operator.json"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_wsnav_status_reads_a_retained_poisoned_bus_without_a_traceback_or_waiting_for_a_quiet_bus(
    endpoint: Endpoint, site_dir: Path
) -> None:
    """Robots at 2 Hz never let the bus be quiet: status waited its full 5 s every time; it now answers once
    the broker's retained replay is over."""
    publish(endpoint, poison())
    publish(endpoint, [("robot1", topics.robot_status(SITE, "robot1"), good_status(0.5))])
    stop = threading.Event()

    def robots_at_2_hz() -> None:  # a few robots' statuses: one every 0.2 s on the bus
        with client(endpoint, "robot1", f"robot1-live-{time.monotonic_ns()}") as robot:
            while not stop.wait(0.2):
                robot.publish(topics.robot_status(SITE, "robot1"), good_status(0.5), qos=0, retain=True)

    live = threading.Thread(target=robots_at_2_hz)
    live.start()
    try:
        started = time.monotonic()
        out = operator_command(endpoint, site_dir, "status", "--json", "--wait", "40")
        took = time.monotonic() - started
    finally:
        stop.set()
        live.join(10)
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr
    snap = json.loads(out.stdout)
    assert snap["robots"][0]["pose"][0] == pytest.approx(0.5)
    assert snap["blocks"] == []
    # With the longest wait at 40 s, a status that waits for a quiet bus takes all of it; one that stops when the
    # replay is over takes its start and a second (6 s on a loaded machine).
    assert took < 30.0, f"status took {took:.1f} s: it waited for a quiet bus"


def test_wsnav_unblock_of_an_unknown_id_exits_2_in_one_line_and_a_held_block_is_lifted(
    endpoint: Endpoint, site_dir: Path
) -> None:
    """`wsnav unblock op-...x` (a typo) printed "lifted" and exited 0 while the API answers 404."""
    block = topics.operator_block(SITE, "op-spill")
    publish(endpoint, [("operator", block, b'{"v":1,"zone":"upper","reason":"spill"}')])
    typo = operator_command(endpoint, site_dir, "unblock", "op-spilx")
    assert typo.returncode == 2 and typo.stdout == ""
    assert typo.stderr.count("\n") == 1 and "no active block 'op-spilx'" in typo.stderr, typo.stderr
    lifted = operator_command(endpoint, site_dir, "unblock", "op-spill")
    assert lifted.returncode == 0 and lifted.stdout == "lifted: op-spill\n", lifted.stderr
    again = operator_command(endpoint, site_dir, "unblock", "op-spill")
    assert again.returncode == 2, "a lifted block is gone from the broker"


class BrokenView(SiteView):
    """A bug of ours that escapes the intake (the boundary a test cannot reach with a message): rendering
    fails in the console's thread once a zone state arrives."""

    def entry(self, key: Key, now: float) -> dict[str, object] | None:
        in_thread = threading.current_thread().name == "console-mqtt"
        if in_thread and key[0] == "zone" and self.nodes["s1"].state is not None:
            raise RuntimeError("a bug")
        return super().entry(key, now)


def test_a_console_whose_reading_thread_dies_says_so_at_once(endpoint: Endpoint, site_dir: Path) -> None:
    """/api/state says broker_connected false with why, and an open page gets a `link` event at once."""
    creds = load_credentials(endpoint.credentials_dir / "operator.json")
    clock = WallClock()
    bus = connect_with_credentials(
        endpoint.host, endpoint.port, creds, client_id=f"operator-console-{time.monotonic_ns()}", clock=clock
    )
    live = LiveState(BrokenView(load_site(site_dir)), bus, clock)
    loop = asyncio.new_event_loop()
    pages = threading.Thread(target=loop.run_forever, daemon=True)
    pages.start()
    feed = live.open_feed(loop)
    live.start()
    try:
        assert live.snapshot()["broker_connected"] is True
        blocked = ZoneState(zone="upper", node="s1", state="blocked", seq=1).to_payload()
        publish(endpoint, [("s1", topics.zone_state(SITE, "upper", "s1"), blocked)])
        wait_for("the thread to die", lambda: not live._thread.is_alive())
        snap = live.snapshot()
        assert snap["broker_connected"] is False
        assert "restart" in snap["link_error"]
        events: list[dict[str, object]] = []
        link = {"type": "link", "broker_connected": False, "link_error": snap["link_error"]}

        def page_told() -> bool:  # the push runs on the pages' loop: it may come a moment after the snapshot
            while not feed.queue.empty():
                events.append(json.loads(feed.queue.get_nowait()))
            return link in events

        wait_for("the page told", page_told, 5)
    finally:
        live.stop()
        live.bus.close()
        loop.call_soon_threadsafe(loop.stop)
        pages.join(5)


@contextlib.contextmanager
def broker_on(kind: str, site_dir: Path, creds: Path, port: int, root: Path) -> Iterator[None]:
    """A broker of `kind` on a fixed port with an empty store under `root` (a restart that lost everything)."""
    if kind == "amqtt":
        with BrokerThread(site_dir, creds, port=port, data_dir=root / "amqtt"):
            yield
        return
    exe = require_tool("mosquitto")
    options = MosquittoOptions(bind=("127.0.0.1", port), data_dir=root / "mq-data", user="root")
    (root / "mq-data").mkdir(parents=True)
    write_mosquitto_config(load_site(site_dir).spec, creds, root / "mq", options)
    proc = subprocess.Popen([exe, "-c", str(root / "mq" / CONF)], stderr=subprocess.DEVNULL)
    try:
        wait_listening("127.0.0.1", port, proc)
        yield
    finally:
        proc.kill()  # kill -9: nothing is saved
        proc.wait(20)


@pytest.mark.parametrize("kind", ["amqtt", "mosquitto"])
def test_an_operator_block_the_broker_lost_is_published_again_by_the_running_console(
    kind: str, site_dir: Path, creds_dir: Path, tmp_path: Path
) -> None:
    """Mosquitto lost blocks acknowledged before a kill -9 (and a full disk wiped them all): while a console
    runs, it publishes every block in force again once the broker is back without it; a lifted one stays lifted."""
    port = free_port()
    endpoint = Endpoint(kind, "127.0.0.1", port, creds_dir)
    kept = topics.operator_block(SITE, "op-kept")
    lifted = topics.operator_block(SITE, "op-lifted")
    with broker_on(kind, site_dir, creds_dir, port, tmp_path / "first"):
        live = console(endpoint, site_dir)
        publish(endpoint, [("operator", kept, b'{"v":1,"zone":"upper","reason":"spill"}')])
        publish(endpoint, [("operator", lifted, b'{"v":1,"zone":"lower"}'), ("operator", lifted, b"")])
        wait_for("the block in the console", lambda: "op-kept" in live.view.blocks)
        assert "op-lifted" not in live.view.blocks
    try:
        wait_for("the console to see the broker gone", lambda: not live.snapshot()["broker_connected"])
        with broker_on(kind, site_dir, creds_dir, port, tmp_path / "second"):
            wait_for("the console back", lambda: live.snapshot()["broker_connected"], 30)
            # read as a robot does (on Mosquitto a second operator connection would knock the console off)
            with client(endpoint, "robot1", f"robot1-check-{time.monotonic_ns()}") as check:
                check.subscribe(topics.all_operator_blocks(SITE))
                got = check.wait_for(kept, timeout=15)
                assert json.loads(got.payload) == {"v": 1, "zone": "upper", "reason": "spill"}
                time.sleep(1.0)
                assert lifted not in check.topics(), "a lifted block came back"
            with client(endpoint, "robot1", f"robot1-late-{time.monotonic_ns()}") as late:
                late.subscribe(topics.all_operator_blocks(SITE))
                assert late.wait_for(kept, timeout=10).retain, (
                    "published again retained, for robots joining later"
                )
    finally:
        live.stop()
        live.bus.close()
