"""A node's MQTT password changed over the air (`wsnav firmware config --new-password`) on both brokers: the
broker takes the new password beside the old one until the node confirms it, so the node is never refused.

The node is the firmware on the MicroPython unix port (firmware/unix_board.py, as tests/test_firmware_ota.py);
the brokers are `wsnav broker run` (amqtt) and Debian's Mosquitto 2.0 with the pending-password plugin built
from broker/mosquitto/pending_auth.c. The trial is seconds long (testing.SHORT_TRIAL), not the board's minutes.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import cast

import pytest

from tests.broker_fixtures import mosquitto_on
from tests.ota_fixtures import (
    NETWORKS,
    NODE,
    QUICK,
    SITE,
    SITE_DIR,
    WAIT,
    Board,
    Infos,
    follow,
    update_mode_then_trial,
)
from wsnav.firmware.build import build
from wsnav.firmware.ota_config import ConfigServer, Settings, seal_for
from wsnav.firmware.testing import (
    SHORT_TRIAL,
    SiteBroker,
    build_for_host,
    versioned_sources,
    write_credentials,
)
from wsnav.runtime.mqtt_bus import BusError, MqttBus
from wsnav.schemas.credentials import Credentials, NodeConfig, config_seq

pytestmark = pytest.mark.slow

REFUSED = ("refused", "not authori")
"""What the node's serial line says when the broker refuses its login (firmware/device/mqtt.py)."""


@pytest.fixture(scope="module")
def fw(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The firmware with a short trial, built, and the host stubs."""
    root = tmp_path_factory.mktemp("pw-fw")
    src = versioned_sources(root / "src", QUICK, None, SHORT_TRIAL)
    build(root / "build", src)
    return {"stubs": build_for_host(root / "host")[1], QUICK: src, f"{QUICK}-build": root / "build"}


class Site:
    """A credentials folder of the test's own (a password change rewrites it), a broker for it, the operator's
    subscriber and the node on it; `mosquitto`: the generated Mosquitto folder, or None on amqtt."""

    def __init__(self, creds: Path, broker: SiteBroker, mosquitto: Path | None, pid: int | None) -> None:
        self.creds = creds
        self.broker = broker
        self.mosquitto = mosquitto
        self.pid = pid
        self.infos = Infos(broker, creds)

    def password(self) -> str:
        return NodeConfig.model_validate_json((self.creds / f"{NODE}.json").read_text()).password


@contextlib.contextmanager
def running_site(kind: str, tmp_path: Path) -> Iterator[Site]:
    creds = tmp_path / "creds"
    write_credentials(SITE_DIR, creds)
    if kind == "amqtt":
        broker = SiteBroker(SITE_DIR, creds, tmp_path / "broker-data")
        broker.start()
        s = Site(creds, broker, None, None)
        try:
            yield s
        finally:
            s.infos.close()
            broker.kill()
        return
    conf = tmp_path / "mq"
    with mosquitto_on(SITE_DIR, creds, conf, tmp_path / "mq-data", pending_passwords=True) as (end, proc):
        s = Site(creds, cast(SiteBroker, end), conf, proc.pid)
        try:
            yield s
        finally:
            s.infos.close()


@contextlib.contextmanager
def running_node(fw: dict[str, Path], site: Site, tmp_path: Path) -> Iterator[Board]:
    """The node on the site, online."""
    (tmp_path / "node").mkdir()
    board = Board(fw, QUICK, site.creds, site.broker, tmp_path / "node")
    board.unix.power_on()
    try:
        site.infos.wait(lambda i: i.fw == QUICK)
        yield board
    finally:
        board.unix.close()


@pytest.fixture(params=["amqtt", "mosquitto"])
def both(request: pytest.FixtureRequest, fw: dict[str, Path], tmp_path: Path) -> Iterator[tuple[Site, Board]]:
    """The site and its node on each broker."""
    with running_site(request.param, tmp_path) as site, running_node(fw, site, tmp_path) as node:
        yield site, node


@pytest.fixture
def on_amqtt(fw: dict[str, Path], tmp_path: Path) -> Iterator[tuple[Site, Board]]:
    """The site and its node on amqtt: for the node's side, the same on both brokers."""
    with running_site("amqtt", tmp_path) as site, running_node(fw, site, tmp_path) as node:
        yield site, node


def logs_in(site: Site, password: str) -> bool:
    """Does the broker take NODE's login with `password`? (On Mosquitto the login takes over the node's
    connection, client id = username: asked only once the node's part is over.)"""
    try:
        MqttBus(
            site.broker.host, site.broker.port, client_id=f"{NODE}-probe", username=NODE, password=password
        ).connect(10).close()
        return True
    except BusError:
        return False


def config_cli(site: Site, *more: str) -> subprocess.CompletedProcess[str]:
    cmd = [
        *(sys.executable, "-m", "wsnav.cli", "firmware", "config", "--new-password", *more),
        *("--site", str(SITE_DIR), "--broker", f"{site.broker.host}:{site.broker.port}"),
        *("--credentials", str(site.creds / "operator.json"), "--nodes", NODE, "--timeout", str(WAIT)),
    ]
    if site.mosquitto is not None:
        cmd += ["--mosquitto-config", str(site.mosquitto)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=WAIT * 2)


def test_a_new_mqtt_password_is_tried_confirmed_and_the_old_one_refused(both: tuple[Site, Board]) -> None:
    """The operator gives the node a new password: it fetches it sealed, boots with it on trial, is taken at
    once (pending at the broker) and confirms; the new one is the node's in its credentials file and on the
    board, the old one is refused (Mosquitto: after its reload, which keeps the node's connection), and the
    broker refused the node not once on the way."""
    site, node = both
    old = site.password()
    proc = config_cli(site)
    assert proc.returncode == 0, (proc.stdout, proc.stderr, node.serial()[-3000:])
    assert f"{NODE}: new configuration confirmed" in proc.stdout
    new = site.password()
    assert new != old
    assert json.loads((node.fs / "config.json").read_text())["password"] == new
    assert new not in node.serial() and new not in proc.stdout + proc.stderr
    if site.pid is not None:  # Mosquitto reads its password file on SIGHUP (systemctl reload)
        before = node.serial().count("mqtt down")
        os.kill(site.pid, signal.SIGHUP)
        time.sleep(2)
        assert node.serial().count("mqtt down") == before, node.serial()[-2000:]  # the node's link stays
    else:
        time.sleep(1.5)  # the amqtt broker's look at its password file (every 0.5 s) must not close the link
    assert not any(word in node.serial() for word in REFUSED), node.serial()[-3000:]
    assert site.infos.wait(lambda i: i.error is None and i.trial is None).fw == QUICK
    assert logs_in(site, new) and not logs_in(site, old)


def test_a_password_the_broker_does_not_take_is_rolled_back_and_the_old_one_kept(
    on_amqtt: tuple[Site, Board],
) -> None:
    """A new password the broker never had pending (its pending file lost, or a replayed configuration whose
    password was withdrawn): the node is refused with it, goes back to its old configuration within the trial's
    bound and is online with its old password again; nothing else changed."""
    from wsnav.schemas.credentials import UPDATE_KEY_FILE, node_update_key

    site, node = on_amqtt
    old = site.password()
    before = (node.fs / "config.json").read_bytes()
    key = node_update_key((site.creds / UPDATE_KEY_FILE).read_text().strip(), NODE)
    sealed, signature = seal_for(key, Settings(password="never-pending-0123456789").payload())
    failures = send_config(site, sealed, signature)
    assert failures and "rolled back to its old configuration" in failures[0], failures
    assert (node.fs / "config.json").read_bytes() == before
    assert site.infos.wait(lambda i: i.error == "config: rolled back").fw == QUICK
    assert logs_in(site, old)


def send_config(site: Site, sealed: bytes, signature: str) -> list[str]:
    """A `config` command as the operator's tool sends it, the sealed settings served; the failures."""
    from wsnav.console.operator_commands import node_command
    from wsnav.schemas.site import load_site

    op = Credentials.model_validate_json((site.creds / "operator.json").read_text())
    failures: list[list[str]] = []
    server = threading.Thread(
        target=lambda: failures.append(
            follow(site.broker, site.creds, lambda bus: ConfigServer(bus, SITE, {NODE: sealed}))
        )
    )
    server.start()
    time.sleep(1)  # subscribed before the node asks
    bus = MqttBus(
        site.broker.host, site.broker.port, client_id="pw-test", username=op.username, password=op.password
    )
    try:
        pub = node_command(load_site(SITE_DIR), NODE, "config", manifest=signature)
        assert bus.connect(30).publish_confirmed(pub.topic, pub.payload)
    finally:
        bus.close()
    server.join(WAIT * 2)
    return failures[0]


@pytest.mark.parametrize("value", [12345, "short", ["a-list-of-one-password"]])
def test_a_garbage_password_is_refused_in_one_line_and_nothing_changes(
    on_amqtt: tuple[Site, Board], value: object
) -> None:
    """A configuration signed for the node whose password is not one (a number, under 16 characters, a list):
    the node refuses it before its config.json is touched (`ota: config` in its `info`), stays online with its
    old password, and the tool's one line names it."""
    from wsnav.schemas.credentials import (
        UPDATE_KEY_FILE,
        config_seq,
        node_update_key,
        seal_config,
        sign_manifest,
    )

    site, node = on_amqtt
    old = site.password()
    before = (node.fs / "config.json").read_bytes()
    key = node_update_key((site.creds / UPDATE_KEY_FILE).read_text().strip(), NODE)
    settings = {"password": value, "seq": config_seq(time.time())}  # numbered: refused for its password alone
    sealed = seal_config(key, json.dumps(settings).encode(), os.urandom(16))
    failures = send_config(site, sealed, sign_manifest(key, sealed))
    assert failures == [f"{NODE}: configuration refused: ota: config"], failures
    assert (node.fs / "config.json").read_bytes() == before
    assert site.infos.wait(lambda i: i.error is None and i.trial is None).fw == QUICK
    assert logs_in(site, old)


def test_a_replayed_or_older_configuration_is_refused_and_nothing_changes(
    on_amqtt: tuple[Site, Board],
) -> None:
    """A configuration the node took, captured on the bus (its sealed chunk and its `config` command) and sent
    again, and one numbered before it: each refused in one line (`ota: old config`) before anything changes,
    the node online on what it has. The number survives the node's reboots (it is in `config.seq`)."""
    from wsnav.schemas.credentials import UPDATE_KEY_FILE, node_update_key

    site, node = on_amqtt
    key = node_update_key((site.creds / UPDATE_KEY_FILE).read_text().strip(), NODE)
    here = (site.broker.host, site.broker.port)  # a change the node can confirm: the broker's own address
    sealed, signature = seal_for(key, Settings(broker=here).payload())
    assert send_config(site, sealed, signature) == []  # taken and confirmed
    node.wait_confirmed()
    kept = (node.fs / "config.json").read_bytes()
    assert send_config(site, sealed, signature) == [f"{NODE}: configuration refused: ota: old config"]
    older = Settings(broker=("192.0.2.1", 1883), seq=config_seq(time.time()) - 3600).payload()
    sealed, signature = seal_for(key, older)
    assert send_config(site, sealed, signature) == [f"{NODE}: configuration refused: ota: old config"]
    assert (node.fs / "config.json").read_bytes() == kept
    assert site.infos.wait(lambda i: i.error is None and i.trial is None).fw == QUICK


def test_wifi_broker_and_password_at_once_fit_the_boards_heap(fw: dict[str, Path], tmp_path: Path) -> None:
    """main.py itself on `micropython -X heapsize=HEAP` (testing.HEAP: the board's free bytes after setup) from a
    `config` command's ota.json, the heaviest configuration there is (a new Wi-Fi network, the broker's address and
    a new MQTT password, pending at the broker): update mode fetches, opens and swaps it without a MemoryError,
    and the trial boot joins, logs in with the new password and confirms."""
    from wsnav.broker.credentials import add_pending, new_password
    from wsnav.schemas.credentials import UPDATE_KEY_FILE, node_update_key

    with running_site("amqtt", tmp_path) as site:
        (tmp_path / "node").mkdir()
        board = Board(fw, QUICK, site.creds, site.broker, tmp_path / "node", NETWORKS)
        password = new_password()
        add_pending(site.creds, NODE, password)
        key = node_update_key((site.creds / UPDATE_KEY_FILE).read_text().strip(), NODE)
        here = (site.broker.host, site.broker.port)
        settings = Settings(wifi=("school-new", NETWORKS["school-new"]), broker=here, password=password)
        sealed, signature = seal_for(key, settings.payload())
        (board.fs / "ota.json").write_text(json.dumps({"stage": "config", "manifest": signature, "boots": 0}))
        failures: list[list[str]] = []
        server = threading.Thread(
            target=lambda: failures.append(
                follow(site.broker, site.creds, lambda bus: ConfigServer(bus, SITE, {NODE: sealed}))
            )
        )
        server.start()
        time.sleep(1)  # the server subscribed before the node asks
        node = update_mode_then_trial(board, fw["stubs"], tmp_path / "node")
        try:
            server.join(WAIT)
            assert failures == [[]], node.output()
            board.wait_confirmed()
        finally:
            node.stop()
        assert "MemoryError" not in node.output()
        assert json.loads((board.fs / "config.json").read_text())["password"] == password
