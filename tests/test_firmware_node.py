"""The zone-node firmware end to end: the built .mpy files on the MicroPython unix port with a 38 KiB heap,
fake pins and Wi-Fi, against the project's broker (`wsnav broker run`) with the node's real credentials.

Every payload the node sends is checked byte for byte against schemas.messages. Waits are on conditions with
generous timeouts (a busy 2-core machine), never fixed sleeps that decide the outcome, except the glitch itself.
"""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from tests.firmware_fixtures import (
    NODE,
    PIN,
    SITE,
    SITE_DIR,
    STATUS_TOPIC,
    WAIT,
    ZONE,
    Subscriber,
    info_of,
    is_info,
    is_state,
    is_status,
    state_of,
)
from wsnav.firmware.testing import (
    SIMULATED_TIME,
    NodeProcess,
    SiteBroker,
    build_for_host,
    micropython_cmd,
    micropython_env,
    parse_stats,
    write_credentials,
)
from wsnav.schemas import topics
from wsnav.schemas.credentials import NodeConfig, load_credentials
from wsnav.schemas.messages import MAX_LOG_LINE_CHARS, MAX_LOG_LINES, NodeCommand, NodeLog, ZoneState
from wsnav.schemas.site import load_site
from wsnav.zone_sim.firmware_modules import diagnostics


@pytest.fixture(scope="module")
def host_build(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return build_for_host(tmp_path_factory.mktemp("fw"))


@pytest.fixture(scope="module")
def creds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("creds")
    write_credentials(SITE_DIR, out)
    return out


@pytest.fixture
def broker(creds: Path, tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[SiteBroker]:
    """The site's broker; a test parametrizes it (indirect) with more `wsnav broker run` options."""
    b = SiteBroker(SITE_DIR, creds, tmp_path / "broker-data", getattr(request, "param", ()))
    b.start()
    yield b
    b.kill()


@pytest.fixture
def subscriber(broker: SiteBroker, creds: Path) -> Iterator[Subscriber]:
    s = Subscriber(broker, creds)
    yield s
    s.close()


def node_config(creds: Path, broker: SiteBroker, out: Path, **overrides: object) -> Path:
    """The node's credentials file as written by `wsnav broker credentials`, with the broker address filled in
    at deploy time (`host=` names it otherwise) and test timings; validated by the schema before the firmware sees it."""
    data = json.loads((creds / f"{NODE}.json").read_text())
    data["broker"] = {"host": overrides.pop("host", broker.host), "port": broker.port}
    warmup_s = overrides.pop("warmup_s", 0)  # the PIR's 60 s warm-up only where a test asks for one
    data.update(overrides)
    if data["sensor"]["type"] == "pir":
        data["sensor"]["warmup_s"] = warmup_s
    cfg = NodeConfig.model_validate(data)
    assert (cfg.node, cfg.zone) == (NODE, ZONE)
    out.write_text(cfg.model_dump_json())
    return out


class Pins:
    def __init__(self, folder: Path) -> None:
        folder.mkdir(exist_ok=True)
        self.folder = folder

    def set(self, pin: int | str, level: int) -> None:
        tmp = self.folder / f".{pin}.tmp"
        tmp.write_text(str(level))
        tmp.replace(self.folder / str(pin))  # atomic: the node never reads a half-written file

    def echo_at(self, pin: int, distance_m: float | None) -> None:
        """What an HC-SR04 on `pin` hears: the echo of something `distance_m` away, or nothing (None)."""
        self.set(f"{pin}.pulse", -1 if distance_m is None else round(distance_m * 2_000_000 / 343))


@pytest.fixture
def pins(tmp_path: Path) -> Pins:
    p = Pins(tmp_path / "pins")
    p.set(PIN, 0)
    return p


@pytest.fixture
def start_node(
    host_build: tuple[Path, Path], pins: Pins, tmp_path: Path
) -> Iterator[Callable[[Path], NodeProcess]]:
    started: list[NodeProcess] = []

    def start(config: Path) -> NodeProcess:
        device, stubs = host_build
        env = micropython_env(device, stubs, pins.folder)
        log = tmp_path / f"node{len(started)}.log" if started else tmp_path / "node.log"
        node = NodeProcess(micropython_cmd("run_node", str(config)), env, log)
        started.append(node)
        return node

    yield start
    for node in started:
        node.stop()


def test_sensor_change_reaches_a_subscriber(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, pins: Pins, start_node, tmp_path: Path
) -> None:
    cfg = node_config(
        creds, broker, tmp_path / "config.json", on_delay_ms=200, off_delay_ms=400, heartbeat_s=30
    )
    node = start_node(cfg)
    subscriber.wait(is_status("online"))
    first = subscriber.wait(is_state("clear"))
    pins.set(PIN, 1)
    blocked = subscriber.wait(is_state("blocked"))
    pins.set(PIN, 0)
    cleared = subscriber.wait(is_state("clear"), after=subscriber.snapshot().index(blocked))
    seqs = [s.seq for s in (state_of(first), state_of(blocked), state_of(cleared)) if s is not None]
    assert seqs == sorted(seqs) and len(set(seqs)) == 3
    # Retained: a late subscriber gets the node's current word and its birth at once.
    late = Subscriber(broker, creds)
    try:
        assert late.wait(is_state("clear")).retain
        assert late.wait(is_status("online")).retain
    finally:
        late.close()
    assert "MemoryError" not in node.output()
    # Power cut: no DISCONNECT, so the broker publishes the node's last will.
    mark = len(subscriber.snapshot())
    node.stop()
    assert subscriber.wait(is_status("offline"), after=mark).topic == STATUS_TOPIC


def test_pir_firing_during_its_warm_up_does_not_block_the_zone(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, pins: Pins, start_node, tmp_path: Path
) -> None:
    """After a power cut an HC-SR501 fires at random for up to a minute: with the pin high from power-on through
    a 4 s warm-up, the node comes online (birth) but publishes no state until the warm-up is over, then says
    clear (the pin dropped); nothing it sent said blocked."""
    cfg = node_config(
        creds, broker, tmp_path / "config.json", warmup_s=4, on_delay_ms=200, off_delay_ms=400, heartbeat_s=1
    )
    pins.set(PIN, 1)
    start_node(cfg)
    online = subscriber.wait(is_status("online"))
    time.sleep(2.0)  # online, inside the warm-up, the pin firing
    mark = subscriber.snapshot().index(online)
    assert not [m for m in subscriber.snapshot()[mark:] if state_of(m) is not None]
    pins.set(PIN, 0)
    subscriber.wait(is_state("clear"), after=mark)
    states = [s.state for m in subscriber.snapshot() if (s := state_of(m)) is not None]
    assert "blocked" not in states, states


def test_ultrasonic_node_says_caution_when_the_passage_narrows(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, pins: Pins, start_node, tmp_path: Path
) -> None:
    """An HC-SR04 with a caution band: something 1.5 m away (blocking under 1 m, caution under 2 m) is
    `caution`; nearer, `blocked`; gone, `clear`; every word debounced and delivered to a subscriber."""
    trig, echo = 12, 14
    sensor = {"type": "hcsr04", "trigger_pin": trig, "echo_pin": echo, "threshold_m": 1.0, "caution_m": 2.0}
    sensor["samples"] = 3
    cfg = node_config(
        creds,
        broker,
        tmp_path / "config.json",
        sensor=sensor,
        on_delay_ms=200,
        off_delay_ms=400,
        heartbeat_s=30,
    )
    pins.echo_at(echo, None)
    node = start_node(cfg)
    subscriber.wait(is_state("clear"))
    words = []
    for distance, word in ((1.5, "caution"), (0.5, "blocked"), (1.5, "caution"), (None, "clear")):
        mark = len(subscriber.snapshot())
        pins.echo_at(echo, distance)
        words.append(state_of(subscriber.wait(is_state(word), after=mark)))
    seqs = [w.seq for w in words if w is not None]
    assert len(seqs) == 4 and seqs == sorted(seqs)
    mark = len(subscriber.snapshot())
    pins.echo_at(echo, 1.8)
    subscriber.wait(is_state("caution"), after=mark)
    late = Subscriber(broker, creds)  # the caution word is retained like the others
    try:
        assert late.wait(is_state("caution")).retain
    finally:
        late.close()
    assert "MemoryError" not in node.output() and "Traceback" not in node.output()


def test_heartbeat_republishes_the_state(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, start_node, tmp_path: Path
) -> None:
    cfg = node_config(creds, broker, tmp_path / "config.json", heartbeat_s=0.5)
    start_node(cfg)
    first = subscriber.wait(is_state("clear"))
    after = subscriber.snapshot().index(first) + 1
    for _ in range(3):
        beat = subscriber.wait(is_state("clear"), after=after)
        after = subscriber.snapshot().index(beat) + 1


def test_debouncing_holds_a_glitch_back(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, pins: Pins, start_node, tmp_path: Path
) -> None:
    cfg = node_config(
        creds, broker, tmp_path / "config.json", on_delay_ms=3000, off_delay_ms=500, heartbeat_s=0.5
    )
    start_node(cfg)
    subscriber.wait(is_state("clear"))
    pins.set(PIN, 1)
    time.sleep(0.2)  # a person walking past the PIR
    pins.set(PIN, 0)
    mark = len(subscriber.snapshot())
    # Heartbeats keep coming for well past the on-delay: every one of them still says clear.
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        time.sleep(0.1)
    later = [s for m in subscriber.snapshot()[mark:] if (s := state_of(m)) is not None]
    assert later and all(s.state == "clear" for s in later), later
    # A sustained reading does get through.
    pins.set(PIN, 1)
    subscriber.wait(is_state("blocked"), after=mark)


def test_broker_killed_and_restarted_node_reconnects_and_republishes(
    broker: SiteBroker, creds: Path, pins: Pins, start_node, tmp_path: Path
) -> None:
    cfg = node_config(
        creds, broker, tmp_path / "config.json", on_delay_ms=100, off_delay_ms=100, heartbeat_s=60
    )
    node = start_node(cfg)
    before = Subscriber(broker, creds)
    try:
        last = state_of(before.wait(is_state("clear")))
    finally:
        before.close()
    assert last is not None
    assert node.wait_output("mqtt up 1", WAIT)
    broker.kill()
    assert node.wait_output("mqtt down:", WAIT), node.output()
    pins.set(PIN, 1)  # changes while the broker is away must not be lost
    time.sleep(1.0)
    broker.start()
    after = Subscriber(broker, creds)
    try:
        assert node.wait_output("mqtt up 2", WAIT), node.output()
        # Heartbeat is 60 s: a blocked word within WAIT can only be the republish after reconnecting.
        fresh = state_of(after.wait(is_state("blocked")))
        after.wait(is_status("online"))
    finally:
        after.close()
    assert fresh is not None and fresh.seq > last.seq
    assert "MemoryError" not in node.output()


def test_board_publishes_its_diagnostics_retained_and_again_after_a_reconnect(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, pins: Pins, start_node, tmp_path: Path
) -> None:
    """The board's own `nodes/<node>/info`: what it measured (reset cause, RSSI, free heap), retained for a
    late subscriber, and sent again after the broker comes back, counting the reconnect and saying why the
    link went down."""
    pins.set("reset_cause", 1)  # the board last started from its watchdog
    cfg = node_config(creds, broker, tmp_path / "config.json", heartbeat_s=60)
    node = start_node(cfg)
    first = info_of(subscriber.wait(is_info()))
    assert first is not None
    assert (first.node, first.fw, first.reset, first.rssi) == (
        NODE,
        diagnostics.FIRMWARE_VERSION,
        "watchdog",
        -58,
    )
    assert first.reconnects == 0 and first.error is None
    assert first.heap_free is not None and 2048 < first.heap_free < 38 * 1024
    late = Subscriber(broker, creds)
    try:
        assert late.wait(is_info()).retain
    finally:
        late.close()
    assert node.wait_output("mqtt up 1", WAIT)
    broker.kill()
    assert node.wait_output("mqtt down:", WAIT), node.output()
    broker.start()
    after = Subscriber(broker, creds)
    try:
        assert node.wait_output("mqtt up 2", WAIT), node.output()
        again = info_of(after.wait(is_info(lambda i: i.reconnects == 1)))
    finally:
        after.close()
    assert again is not None and again.error and again.uptime_s >= first.uptime_s
    out = node.output()
    assert "MemoryError" not in out and "info: no heap" not in out and "Traceback" not in out, out


@pytest.mark.parametrize("broker", [SIMULATED_TIME], indirect=True, ids=["no-node-rate-limit"])
def test_hours_of_simulated_time_on_a_38k_heap(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, host_build: tuple[Path, Path], tmp_path: Path
) -> None:
    hours = 24
    cfg = node_config(
        creds, broker, tmp_path / "config.json", heartbeat_s=10, on_delay_ms=500, off_delay_ms=3000
    )
    device, stubs = host_build
    node = NodeProcess(
        micropython_cmd("longrun", str(cfg), str(hours * 3600)),
        micropython_env(device, stubs, tmp_path),
        tmp_path / "longrun.log",
    )
    try:
        node.proc.wait(timeout=600)
    finally:
        node.stop()
    out = node.output()
    assert node.proc.returncode == 0, out
    assert "MemoryError" not in out and "Traceback" not in out, out
    stats = parse_stats(out)
    print(out)
    assert stats["errors"] == 0 and stats["connects"] == 1 and "info: no heap" not in out, out
    # 10 s heartbeats plus two changes per 97 s pattern period: at least the heartbeats.
    assert stats["publications"] >= hours * 360, out
    assert stats["heap_lowest"] > 2048, out  # free heap after GC never fell below 2 KiB
    assert stats["heap_lowest"] >= stats["heap_start"] - 1024, out  # and did not creep down: no leak
    # Everything it sent reached the broker and is valid (QoS 1, acked one by one).
    deadline = time.monotonic() + WAIT
    states: list[ZoneState] = []
    while time.monotonic() < deadline:
        states = [s for m in subscriber.snapshot() if (s := state_of(m)) is not None]
        if len(states) >= stats["publications"]:
            break
        time.sleep(0.1)
    assert len(states) == stats["publications"]
    assert {s.state for s in states} == {"clear", "blocked"}
    seqs = [s.seq for s in states]
    assert seqs == sorted(seqs)
    # The diagnostics, every 5 simulated minutes from the connect on, all of them sent and valid.
    infos = [i for m in subscriber.snapshot() if (i := info_of(m)) is not None]
    assert len(infos) >= hours * 3600 * 1000 // diagnostics.INFO_PERIOD_MS, len(infos)
    gaps = {b.uptime_s - a.uptime_s for a, b in itertools.pairwise(infos)}
    assert gaps <= {300, 301}, gaps
    assert all(i.heap_free is not None and i.heap_free > 2048 and i.reconnects == 0 for i in infos)


def test_wifi_lost_and_back_node_reconnects(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, pins: Pins, start_node, tmp_path: Path
) -> None:
    cfg = node_config(
        creds, broker, tmp_path / "config.json", on_delay_ms=100, off_delay_ms=100, heartbeat_s=60
    )
    node = start_node(cfg)
    assert node.wait_output("mqtt up 1", WAIT), node.output()
    subscriber.wait(is_state("clear"))
    down = pins.folder / "wifi_down"
    down.write_text("")
    assert node.wait_output("mqtt down: wifi lost", WAIT), node.output()
    pins.set(PIN, 1)
    time.sleep(0.5)
    mark = len(subscriber.snapshot())
    down.unlink()
    assert node.wait_output("mqtt up 2", WAIT), node.output()
    subscriber.wait(is_status("online"), after=mark)
    subscriber.wait(is_state("blocked"), after=mark)


# DNS: run_node's fake DNS server follows the file `dns` in the pins folder (0 or missing: the real lookup, 1: every
# lookup fails, 2: a lookup never returns), and prints "dns down HOST" / "dns hang HOST" when it is asked.


def test_broker_name_looked_up_again_and_last_address_reused_when_dns_fails(
    broker: SiteBroker, creds: Path, pins: Pins, start_node, tmp_path: Path
) -> None:
    cfg = node_config(creds, broker, tmp_path / "config.json", host="localhost", heartbeat_s=60)
    node = start_node(cfg)
    assert node.wait_output("mqtt up 1", WAIT), node.output()
    pins.set("dns", 1)
    broker.kill()
    assert node.wait_output("dns down localhost", WAIT), node.output()  # a name is looked up at every connect
    broker.start()
    assert node.wait_output("mqtt up 2", WAIT), node.output()
    out = node.output()
    assert "cannot resolve" not in out and "Traceback" not in out and "MemoryError" not in out, out


def test_unresolvable_broker_name_fails_at_once_and_the_node_retries(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, pins: Pins, start_node, tmp_path: Path
) -> None:
    pins.set("dns", 1)
    cfg = node_config(creds, broker, tmp_path / "config.json", host="localhost")
    node = start_node(cfg)
    assert node.wait_output("mqtt down: cannot resolve localhost", WAIT), node.output()
    first = time.monotonic()
    assert node.wait_output("mqtt down: cannot resolve localhost", WAIT, count=3), node.output()
    assert time.monotonic() - first < 15  # no wait in place: the 0.1-1 s broker backoff paces the attempts
    assert "Traceback" not in node.output()
    pins.set("dns", 0)
    assert node.wait_output("mqtt up 1", WAIT), node.output()
    subscriber.wait(is_status("online"))


def test_ipv4_broker_address_needs_no_dns(
    broker: SiteBroker, creds: Path, pins: Pins, start_node, tmp_path: Path
) -> None:
    pins.set("dns", 2)  # any lookup would never return
    cfg = node_config(creds, broker, tmp_path / "config.json", host="127.0.0.1", heartbeat_s=60)
    node = start_node(cfg)
    assert node.wait_output("mqtt up 1", WAIT), node.output()
    broker.kill()
    assert node.wait_output("mqtt down:", WAIT), node.output()
    broker.start()
    assert node.wait_output("mqtt up 2", WAIT), node.output()
    assert "dns hang" not in node.output()


def send_command(
    broker: SiteBroker, creds: Path, node: str, payload: bytes, sender: str = "operator"
) -> None:
    """One command as QoS 1, not retained, from `sender`'s identity; waits for the broker's PUBACK."""
    who = load_credentials(creds / f"{sender}.json")
    client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"{sender}-cmd-{time.monotonic_ns()}")
    client.username_pw_set(who.username, who.password)
    client.connect(broker.host, broker.port)
    client.loop_start()
    try:
        info = client.publish(topics.node_command(SITE, node), payload, qos=1)
        info.wait_for_publish(WAIT)
        assert info.is_published()
    finally:
        client.loop_stop()
        client.disconnect()


def command(cmd: str, ident: int, heartbeat_s: float | None = None) -> bytes:
    return NodeCommand(id=ident, command=cmd, heartbeat_s=heartbeat_s).to_payload()  # type: ignore[arg-type]


def test_operator_commands_reach_the_node_and_are_applied(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, start_node, tmp_path: Path
) -> None:
    """send_info: an info at once; set_heartbeat 2: heartbeats every ~2 s and the period in the info; a
    redelivered id, a malformed and an unknown command, and updates without a proper manifest change nothing but
    the count; restart: offline, the
    process resets (75) and, started again as a board reboots, the node comes back online."""
    cfg = node_config(creds, broker, tmp_path / "config.json", heartbeat_s=60)
    node = start_node(cfg)
    assert node.wait_output("mqtt up 1", WAIT), node.output()
    subscriber.wait(is_info())
    mark = len(subscriber.snapshot())
    send_command(broker, creds, NODE, command("send_info", 11))
    first = info_of(subscriber.wait(is_info(), after=mark))
    assert first is not None and first.heartbeat_ms == 60000 and first.bad_commands == 0
    mark = len(subscriber.snapshot())
    send_command(broker, creds, NODE, command("set_heartbeat", 12, 2))
    assert info_of(subscriber.wait(is_info(lambda i: i.heartbeat_ms == 2000), after=mark)) is not None
    beats: list[float] = []
    after = len(subscriber.snapshot())
    while len(beats) < 4:
        beat = subscriber.wait(is_state("clear"), after=after, timeout=10)
        beats.append(time.monotonic())
        after = subscriber.snapshot().index(beat) + 1
    gaps = [b - a for a, b in itertools.pairwise(beats[1:])]
    assert all(1.0 < g < 3.5 for g in gaps), gaps
    bad_updates = (b'{"v":1,"id":17,"command":"update"}', b'{"v":1,"id":18,"command":"update","manifest":5}')
    for bad in (
        b"{nope",
        b'{"v":1,"id":13,"command":"format_flash"}',
        command("set_heartbeat", 12, 5),
        *bad_updates,
    ):
        send_command(broker, creds, NODE, bad)  # the last one: id 12 again, a redelivery, ignored silently
    send_command(broker, creds, NODE, b'{"v":1,"id":14,"command":"set_heartbeat","heartbeat_s":7200}')
    mark = len(subscriber.snapshot())
    send_command(broker, creds, NODE, command("send_info", 15))
    counted = info_of(subscriber.wait(is_info(), after=mark))
    assert counted is not None and counted.bad_commands == 5 and counted.heartbeat_ms == 2000, counted
    mark = len(subscriber.snapshot())
    send_command(broker, creds, NODE, command("restart", 16))
    node.proc.wait(WAIT)
    assert node.proc.returncode == 75, node.output()
    assert "restart" in node.output() and "Traceback" not in node.output(), node.output()
    subscriber.wait(is_status("offline"), after=mark)
    mark = len(subscriber.snapshot())
    rebooted = start_node(cfg)
    assert rebooted.wait_output("mqtt up 1", WAIT), rebooted.output()
    subscriber.wait(is_status("online"), after=mark)
    again = info_of(subscriber.wait(is_info(), after=mark))
    assert again is not None and again.heartbeat_ms == 60000  # the commanded period was RAM only


def test_a_node_cannot_command_another_node(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, start_node, tmp_path: Path
) -> None:
    """n2 (its own credentials) publishing a restart and a send_info to n1's command topic: the broker drops
    them; n1 stays up and sends no info for them. The operator's next command still works."""
    cfg = node_config(creds, broker, tmp_path / "config.json", heartbeat_s=60)
    node = start_node(cfg)
    assert node.wait_output("mqtt up 1", WAIT), node.output()
    subscriber.wait(is_info())
    mark = len(subscriber.snapshot())
    send_command(broker, creds, NODE, command("restart", 21), sender="n2")
    send_command(broker, creds, NODE, command("send_info", 22), sender="n2")
    send_command(broker, creds, NODE, command("send_info", 23))
    subscriber.wait(is_info(), after=mark)
    infos = [m for m in subscriber.snapshot()[mark:] if info_of(m) is not None]
    assert len(infos) == 1 and node.proc.poll() is None, node.output()
    assert "restart" not in node.output() and "bad command" not in node.output()


HOSTILE = 'a "quoted" back\\slash\nnew\tline \x1b[2J ' + "x" * 80
"""A line as an exception's text may be: a quote, a backslash, a newline, a tab, a terminal's escape, too long."""

RING_DRIVER = (
    f"HOSTILE = {HOSTILE!r}\n"
    + r"""
import app
import command


class Client:
    def __init__(self):
        self.sent = []

    def publish(self, topic, payload, retain=False, qos=0):
        self.sent.append((topic, payload, retain, qos))


class Logic:
    status_topic = "wsn/school/nodes/n1/status"


class Node:  # the attributes app.Node.log and command.apply use, nothing else
    uptime_s = 7
    command_id = 0
    bad_commands = 0
    info_due_ms = 0
    trial = 1


n = Node()
n.buffer = []
n.client = Client()
n.logic = Logic()
for i in range(20):
    app.Node.log(n, "loop error:", i, HOSTILE)
command.apply(n, b'{"v":1,"id":5,"command":"log"}', 0)
topic, payload, retain, qos = n.client.sent[0]
print(topic, retain, qos, n.bad_commands)
print(payload)
"""
)


def test_the_log_ring_keeps_the_last_lines_bounded_and_valid_json(
    host_build: tuple[Path, Path], tmp_path: Path
) -> None:
    """On the MicroPython VM: 20 lines logged, each longer than a line may be and holding a quote, a backslash, a
    newline, a tab and a terminal escape; the `log` command then publishes the last 8, each cut to 60 characters,
    as a NodeLog the contract accepts (not retained, QoS 0), every character as it was (a quote left unescaped
    would make the whole message invalid JSON)."""
    device, stubs = host_build
    driver = tmp_path / "ring_driver.py"
    driver.write_text(RING_DRIVER)
    env = micropython_env(device, stubs, tmp_path)
    env["MICROPYPATH"] += f":{tmp_path}"
    proc = subprocess.run(
        micropython_cmd("ring_driver"),
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    head, payload = proc.stdout.splitlines()[-2:]
    assert head == f"{topics.node_log(SITE, NODE)} False 0 0", head
    log = NodeLog.model_validate_json(payload)
    assert log.node == NODE and len(log.lines) == MAX_LOG_LINES
    assert all(len(line) <= MAX_LOG_LINE_CHARS for line in log.lines)
    assert log.lines == [f"7 loop error: {i} {HOSTILE}"[:MAX_LOG_LINE_CHARS] for i in range(12, 20)], (
        log.lines
    )


def test_log_command_and_wsnav_firmware_logs_print_the_nodes_last_lines(
    broker: SiteBroker, creds: Path, subscriber: Subscriber, start_node, tmp_path: Path
) -> None:
    """The node's lines since boot come back on `nodes/<node>/log` (the broker's ACL lets the node write it),
    and `wsnav firmware logs` prints them; a node that is not running gets one line and exit 1, not a hang."""
    cfg = node_config(creds, broker, tmp_path / "config.json", heartbeat_s=60)
    node = start_node(cfg)
    assert node.wait_output("mqtt up 1", WAIT), node.output()
    subscriber.wait(is_info())
    mark = len(subscriber.snapshot())
    send_command(broker, creds, NODE, command("log", 31))
    msg = subscriber.wait(lambda m: m.topic == topics.node_log(SITE, NODE), after=mark)
    log = NodeLog.model_validate_json(msg.payload)
    assert not msg.retain and any(line.endswith(" mqtt up 1") for line in log.lines), log
    cli = [
        *(sys.executable, "-m", "wsnav.cli", "firmware", "logs"),
        *("--site", str(SITE_DIR), "--broker", f"{broker.host}:{broker.port}"),
        *("--credentials", str(creds / "operator.json"), "--timeout", "3"),
    ]
    ok = subprocess.run([*cli, "--nodes", NODE], capture_output=True, text=True, timeout=WAIT, check=False)
    assert ok.returncode == 0 and ok.stderr == "", ok.stdout + ok.stderr
    assert f"{NODE}: " in ok.stdout and " mqtt up 1" in ok.stdout, ok.stdout
    other = next(n.id for n in load_site(SITE_DIR).spec.nodes if n.id != NODE)  # never started here
    missing = subprocess.run(
        [*cli, "--nodes", f"{NODE},{other}"], capture_output=True, text=True, timeout=WAIT, check=False
    )
    assert missing.returncode == 1 and " mqtt up 1" in missing.stdout, missing.stdout + missing.stderr
    assert missing.stderr.strip() == f"{other}: no answer within 3 s (offline? a command is not queued)"
    assert "Traceback" not in missing.stderr


def test_wsnav_firmware_logs_shows_a_nodes_line_escaped_and_refuses_a_bad_message(
    broker: SiteBroker, creds: Path
) -> None:
    """A node's log lines are text from a board anyone could open: a line holding a terminal's escape sequence
    and a newline is printed escaped, on one line; a message the contract refuses gets one line and exit 1, no
    traceback. The node here is a paho client with n2's own credentials, answering each command as the firmware
    does (the broker's ACL is the real one); what it leaves out is the firmware itself (tested above)."""
    other = next(n.id for n in load_site(SITE_DIR).spec.nodes if n.id != NODE)
    answers = [
        NodeLog(node=other, lines=["5 loop error: \x1b[2J\nboom"]).to_payload(),
        b'{"v":1,"node":"%s","lines":"not a list"}' % other.encode(),
    ]
    who = load_credentials(creds / f"{other}.json")
    fake = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=other)
    fake.username_pw_set(who.username, who.password)

    def answer(c: mqtt.Client, _u: object, _m: mqtt.MQTTMessage) -> None:
        c.publish(topics.node_log(SITE, other), answers.pop(0))

    fake.on_message = answer
    subscribed = threading.Event()
    fake.on_subscribe = lambda *_a: subscribed.set()
    fake.connect(broker.host, broker.port)
    fake.loop_start()
    try:
        fake.subscribe(topics.node_command(SITE, other), qos=1)
        assert subscribed.wait(WAIT)
        cli = [
            *(sys.executable, "-m", "wsnav.cli", "firmware", "logs", "--nodes", other),
            *("--site", str(SITE_DIR), "--broker", f"{broker.host}:{broker.port}"),
            *("--credentials", str(creds / "operator.json"), "--timeout", "20"),
        ]
        shown = subprocess.run(cli, capture_output=True, text=True, timeout=WAIT, check=False)
        assert shown.returncode == 0, shown.stdout + shown.stderr
        assert shown.stdout == f"{other}: its last log lines (1)\n  5 loop error: \\x1b[2J\\nboom\n", (
            shown.stdout
        )
        refused = subprocess.run(cli, capture_output=True, text=True, timeout=WAIT, check=False)
        assert refused.returncode == 1 and refused.stdout == "", refused.stdout
        assert refused.stderr.startswith(f"{other}: its log message was refused: "), refused.stderr
        assert refused.stderr.count("\n") == 1 and "Traceback" not in refused.stderr, refused.stderr
    finally:
        fake.loop_stop()
        fake.disconnect()
