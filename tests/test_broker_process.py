"""`wsnav broker run` as a process: retained state across SIGTERM and kill -9 restarts, clean exits, and one-line
errors for a port in use and bad input."""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.broker_fixtures import (
    TIMEOUT,
    Endpoint,
    client,
    mosquitto_on,
    store_guard_plugin,
    wait_stored,
    wsnav,
)
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerProcess
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.plugin import JOURNAL
from wsnav.broker.mosquitto.store import STORE, check_store
from wsnav.schemas import topics
from wsnav.schemas.site import load_site

SITE = "tiny"
STATE = topics.zone_state(SITE, "z1", "n1")
STATUS = topics.node_status(SITE, "n1")
OTHER = topics.zone_state(SITE, "z2", "n2")


@pytest.fixture
def setup(tmp_path: Path) -> tuple[Path, Path]:
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    return site, creds


def endpoint(proc: BrokerProcess) -> Endpoint:
    return Endpoint("amqtt", proc.host, proc.port, proc.credentials_dir)


def publish_states(ep: Endpoint) -> None:
    """n1 blocked + online, n2 clear then removed (an empty retained payload clears a topic)."""
    with client(ep, "n1") as n1, client(ep, "n2") as n2, client(ep, "operator", "watch") as watch:
        assert watch.subscribe(f"wsn/{SITE}/#") == [1]
        n2.publish(OTHER, b"clear", retain=True)
        n1.publish(STATE, b"blocked", retain=True)
        n1.publish(STATUS, b"online", retain=True)
        n2.publish(OTHER, b"", retain=True)
        watch.wait_for(STATUS, b"online")
        watch.wait_for(OTHER, b"")


def retained_after_restart(ep: Endpoint) -> dict[str, bytes]:
    """What a fresh subscriber gets: by the sentinel it has every retained message."""
    with client(ep, "operator", "after") as after, client(ep, "n1") as n1:
        assert after.subscribe(f"wsn/{SITE}/zones/#") == [1]
        assert after.subscribe(f"wsn/{SITE}/nodes/#") == [1]
        sentinel = topics.node_status(SITE, "n1")
        after.wait_for(STATE)
        after.wait_for(STATUS)
        n1.publish(sentinel, b"sentinel")
        after.wait_for(sentinel, b"sentinel")
        return {m.topic: m.payload for m in after.received if m.retain}


@pytest.mark.parametrize("kind", ["amqtt", "mosquitto"])
def test_operator_blocks_acknowledged_just_before_a_kill_9_survive_it(
    setup: tuple[Path, Path], tmp_path: Path, kind: str
) -> None:
    """A power cut, as kill -9 right after the last PUBACK: amqtt lost a block acknowledged 0.01 s before (its
    store writes within 0.2 s), Mosquitto blocks acknowledged up to 2 s before (it saves every 2 s, after the
    PUBACK). Three blocks, each acknowledged, one lifted, then the kill: amqtt's PUBACK waits for the write,
    Mosquitto's for wsnav's plugin's fdatasync'd journal, which puts them back at the next start."""
    site, creds = setup
    data = tmp_path / "data"
    b1, b2, b3 = (topics.operator_block(SITE, b) for b in ("b1", "b2", "b3"))

    def broker() -> contextlib.AbstractContextManager[tuple[Endpoint, Any]]:
        if kind == "amqtt":
            return amqtt_on(site, creds, data)
        return mosquitto_on(site, creds, tmp_path / "mq", data, store_guard=store_guard_plugin(tmp_path))

    with broker() as (ep, proc), client(ep, "operator", "operator") as operator:
        operator.publish(b1, b'{"block": 1}', retain=True)
        operator.publish(b2, b'{"block": 2}', retain=True)
        operator.publish(b1, b"", retain=True)  # the operator lifted block 1
        operator.publish(b3, b'{"block": 3}', retain=True)
        proc.kill()
        proc.wait()
    with broker() as (ep, _), client(ep, "robot1") as robot:
        assert robot.subscribe(f"wsn/{SITE}/operator/blocks/#") == [1]
        robot.wait_for(b3, timeout=5.0)
        robot.wait_for(b2, timeout=1.0)
        assert {m.topic: m.payload for m in robot.received} == {b2: b'{"block": 2}', b3: b'{"block": 3}'}


def test_mosquittos_plugin_journals_only_what_the_acl_let_through_keeps_liftings_and_cuts_a_torn_record(
    setup: tuple[Path, Path], tmp_path: Path
) -> None:
    """The plugin publishes its journal again with the broker's own authority, so it must hold only what
    Mosquitto's ACL let through: a node's forged block (PUBACKed by MQTT 3.1.1, dropped by the ACL) never comes
    back. A block the store already held and the operator then lifted stays lifted after a kill -9 (the store
    alone brought it back). A record torn by the power cut is cut off; the whole ones before it still count."""
    site, creds = setup
    data = tmp_path / "data"
    saved, forged, kept = (topics.operator_block(SITE, b) for b in ("saved", "forged", "kept"))
    plugin = store_guard_plugin(tmp_path)

    def broker() -> contextlib.AbstractContextManager[tuple[Endpoint, subprocess.Popen[bytes]]]:
        return mosquitto_on(site, creds, tmp_path / "mq", data, store_guard=plugin)

    with broker() as (ep, proc), client(ep, "operator", "operator") as operator, client(ep, "n1") as node:
        operator.publish(saved, b'{"block": "saved"}', retain=True)
        deadline = time.monotonic() + TIMEOUT
        while check_store(data / STORE).retained < 1:  # Mosquitto's own save holds the block now
            assert time.monotonic() < deadline, check_store(data / STORE)
            time.sleep(0.05)
        node.publish(forged, b'{"block": "forged"}', retain=True)
        operator.publish(kept, b'{"block": "kept"}', retain=True)
        operator.publish(saved, b"", retain=True)  # lifted, acknowledged, then the power cut
        proc.kill()
        proc.wait()
    with (data / JOURNAL).open("ab") as journal:
        journal.write(b"\x00\x00\x00\x2a\x00\x00")  # a record's head cut by the power cut
    sentinel = topics.operator_block(SITE, "sentinel")
    with broker() as (ep, _), client(ep, "robot1") as robot, client(ep, "operator", "operator") as operator:
        assert robot.subscribe(f"wsn/{SITE}/operator/blocks/#") == [1]
        operator.publish(sentinel, b"after the retained ones")  # not retained: delivered after them
        robot.wait_for(sentinel)
        assert {m.topic: m.payload for m in robot.received if m.retain} == {kept: b'{"block": "kept"}'}


def test_mosquittos_plugin_sets_a_journal_that_is_not_one_aside_in_one_line_and_journals_again(
    setup: tuple[Path, Path], tmp_path: Path
) -> None:
    """Hostile input on disk: a journal file that is not one (garbage, another program's file) stops nothing.
    Mosquitto starts and serves its store's blocks, its log says where the file went, and the next block is
    journaled again (it survives a kill -9)."""
    site, creds = setup
    data, log = tmp_path / "data", tmp_path / "mosquitto.log"
    old, new = topics.operator_block(SITE, "old"), topics.operator_block(SITE, "new")
    plugin = store_guard_plugin(tmp_path)

    def broker() -> contextlib.AbstractContextManager[tuple[Endpoint, subprocess.Popen[bytes]]]:
        return mosquitto_on(site, creds, tmp_path / "mq", data, log=log, store_guard=plugin)

    with broker() as (ep, _), client(ep, "operator", "operator") as operator:
        operator.publish(old, b'{"block": "old"}', retain=True)
    garbage = b"not a journal \x00\xff" * 100
    (data / JOURNAL).write_bytes(garbage)  # after the clean stop: the store holds the block
    with broker() as (ep, proc), client(ep, "operator", "operator") as operator:
        line = next(line for line in log.read_text().splitlines() if "not an operator-block journal" in line)
        assert "ERROR" in line and f"{JOURNAL}.damaged" in line, line
        assert (data / f"{JOURNAL}.damaged").read_bytes() == garbage
        operator.publish(new, b'{"block": "new"}', retain=True)
        proc.kill()
        proc.wait()
    with broker() as (ep, _), client(ep, "robot1") as robot:
        assert robot.subscribe(f"wsn/{SITE}/operator/blocks/#") == [1]
        assert robot.wait_for(old, timeout=5.0).payload == b'{"block": "old"}'
        assert robot.wait_for(new, timeout=5.0).payload == b'{"block": "new"}'


@contextlib.contextmanager
def amqtt_on(site: Path, creds: Path, data: Path) -> Iterator[tuple[Endpoint, subprocess.Popen[str]]]:
    with BrokerProcess(site, creds, data_dir=data) as proc:
        assert proc.proc is not None
        yield endpoint(proc), proc.proc


@pytest.mark.parametrize("stop", ["sigterm", "sigint", "kill-9"])
def test_retained_state_survives_a_restart(setup: tuple[Path, Path], tmp_path: Path, stop: str) -> None:
    site, creds = setup
    data = tmp_path / "data"
    first = BrokerProcess(site, creds, data_dir=data).start()
    try:
        publish_states(endpoint(first))
        if stop == "kill-9":
            wait_stored(data, {STATE: b"blocked", STATUS: b"online"})
            assert first.kill() == -signal.SIGKILL
        else:
            assert first.stop_with(signal.SIGTERM if stop == "sigterm" else signal.SIGINT, TIMEOUT) == 0
            assert "broker stopped\n" in first.output
    finally:
        first.kill()
    with BrokerProcess(site, creds, data_dir=data) as second:
        got = retained_after_restart(endpoint(second))
    assert got[STATE] == b"blocked"
    assert got[STATUS] == b"online"
    assert OTHER not in got


def test_ready_line_and_clean_exit(setup: tuple[Path, Path], tmp_path: Path) -> None:
    site, creds = setup
    proc = BrokerProcess(site, creds, data_dir=tmp_path / "data").start()
    assert proc.output[0] == f"broker ready on 127.0.0.1:{proc.port}\n"
    assert proc.terminate() == 0
    assert proc.errors == []


def test_port_in_use_is_one_line_and_nonzero(setup: tuple[Path, Path]) -> None:
    site, creds = setup
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = wsnav("broker", "run", "--site", site, "--credentials", creds, "--bind", f"127.0.0.1:{port}")
    assert result.returncode != 0
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert "cannot start listening" in lines[0] and "address already in use" in lines[0]
    assert "broker ready" not in result.stdout


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (
            ["--site", "{tmp}/nowhere", "--credentials", "{creds}", "--bind", "127.0.0.1:0"],
            "no such site file",
        ),
        (
            ["--site", "{site}", "--credentials", "{tmp}/nowhere", "--bind", "127.0.0.1:0"],
            "not a credentials",
        ),
        (["--site", "{site}", "--credentials", "{site}", "--bind", "127.0.0.1:0"], "no password file"),
        (["--site", "{site}", "--credentials", "{creds}", "--bind", "localhost"], "expected HOST:PORT"),
        (["--site", "{site}", "--credentials", "{creds}"], "required"),
        (
            [
                "--site",
                "{site}",
                "--credentials",
                "{creds}",
                "--bind",
                "127.0.0.1:0",
                "--connect-timeout",
                "0",
            ],
            "--connect-timeout must be",
        ),
        (
            [
                "--site",
                "{site}",
                "--credentials",
                "{creds}",
                "--bind",
                "127.0.0.1:0",
                "--max-packet-bytes",
                "9",
            ],
            "--max-packet-bytes must be",
        ),
        (
            ["--site", "{site}", "--credentials", "{creds}", "--bind", "127.0.0.1:0", "--gc-freeze", "-1"],
            "--gc-freeze must be",
        ),
        (
            ["--site", "{site}", "--credentials", "{creds}", "--bind", "127.0.0.1:0", "--gc-refresh", "0"],
            "--gc-refresh must be",
        ),
    ],
)
def test_bad_input_is_one_line(
    setup: tuple[Path, Path], tmp_path: Path, args: list[str], needle: str
) -> None:
    site, creds = setup
    filled = [a.format(tmp=tmp_path, site=site, creds=creds) for a in args]
    result = wsnav("broker", "run", *filled)
    assert result.returncode != 0
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert needle in result.stderr


def test_broken_password_file_is_one_line(setup: tuple[Path, Path]) -> None:
    site, creds = setup
    (creds / "broker.passwd").write_text("n1 has no hash\n")
    result = wsnav("broker", "run", "--site", site, "--credentials", creds, "--bind", "127.0.0.1:0")
    assert result.returncode != 0
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert "broker.passwd: line 1" in result.stderr
