"""The retained store's policy, on `wsnav broker run`: a damaged, truncated or empty file is set aside with one
loud line and the broker starts empty and keeps storing; a full disk (a tiny tmpfs) is reported at once, nothing
acknowledged is dropped while the broker runs, and what could not be written by exit is reported as lost."""

from __future__ import annotations

import contextlib
import os
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

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
from tests.conftest import unavailable
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerProcess
from wsnav.broker.amqtt.retained_store import DB_NAME, read_retained
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.store import MAGIC, STORE, StoreCheck, check_store, keep_good
from wsnav.schemas import topics
from wsnav.schemas.site import load_site

SITE = "tiny"
STATE = topics.zone_state(SITE, "z1", "n1")
STATUS = topics.node_status(SITE, "n1")


@pytest.fixture
def setup(tmp_path: Path) -> tuple[Path, Path]:
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    return site, creds


def endpoint(proc: BrokerProcess) -> Endpoint:
    return Endpoint("amqtt", proc.host, proc.port, proc.credentials_dir)


def store_two_states(site: Path, creds: Path, data: Path) -> None:
    with BrokerProcess(site, creds, data_dir=data) as proc, client(endpoint(proc), "n1") as node:
        node.publish(STATE, b"blocked", retain=True)
        node.publish(STATUS, b"online", retain=True)
        wait_stored(data, {STATE: b"blocked", STATUS: b"online"})


def damage(path: Path, how: str) -> None:
    if how == "garbage-in-pages":
        with path.open("r+b") as f:
            f.seek(4096)  # page 2: the table's root page; the header (page 1) stays valid
            f.write(os.urandom(4096))
    elif how == "truncated":
        with path.open("r+b") as f:
            f.truncate(5000)
    else:
        path.write_bytes(b"")


def wait_line(proc: BrokerProcess, needle: str) -> str:
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        for line in proc.errors:
            if needle in line:
                return line
        time.sleep(0.05)
    raise AssertionError(f"no log line with {needle!r}; stderr: {proc.errors}")


@pytest.mark.parametrize("how", ["garbage-in-pages", "truncated", "empty"])
def test_damaged_store_is_set_aside_loudly_and_the_broker_keeps_storing(
    setup: tuple[Path, Path], tmp_path: Path, how: str
) -> None:
    site, creds = setup
    data = tmp_path / "data"
    store_two_states(site, creds, data)
    damage(data / DB_NAME, how)
    with BrokerProcess(site, creds, data_dir=data) as proc:
        line = wait_line(proc, "is damaged")
        assert "ERROR" in line and "moved to" in line and "NO retained" in line
        aside = [p for p in data.glob(f"{DB_NAME}.damaged-*") if not p.name.endswith(("-wal", "-shm"))]
        assert len(aside) == 1 and aside[0].name in line
        with client(endpoint(proc), "n1") as node:
            node.publish(STATE, b"clear", retain=True)
        wait_stored(data, {STATE: b"clear"})  # the flusher runs: new updates are not lost
    assert "Task exception was never retrieved" not in "".join(proc.errors)


@contextlib.contextmanager
def tiny_tmpfs(path: Path, size: str) -> Iterator[Path]:
    path.mkdir()
    if os.geteuid() != 0:
        unavailable("mounting a tmpfs needs root (CI runs as root)")
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], check=False, capture_output=True
    )
    if mounted.returncode != 0:
        unavailable(f"cannot mount a tmpfs here: {mounted.stderr.decode(errors='replace').strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def test_full_disk_is_loud_loses_nothing_while_running_and_counts_what_is_lost(
    setup: tuple[Path, Path], tmp_path: Path
) -> None:
    site, creds = setup
    with tiny_tmpfs(tmp_path / "disk", "512k") as disk:
        data = disk / "data"
        with BrokerProcess(site, creds, data_dir=data) as proc, client(endpoint(proc), "n1") as node:
            node.publish(STATE, b"blocked", retain=True)
            wait_stored(data, {STATE: b"blocked"})
            filler = disk / "filler"
            with contextlib.suppress(OSError), filler.open("wb") as f:
                while True:
                    f.write(b"\0" * 65536)
            node.publish(STATUS, b"x" * 8000, retain=True)  # acknowledged (PUBACK) by the broker
            node.publish(STATE, b"clear" + b" " * 8000, retain=True)
            line = wait_line(proc, "cannot store")
            assert "ERROR" in line and "kept in memory" in line
            with client(endpoint(proc), "robot1") as late:  # what was acknowledged is still served
                assert late.subscribe(STATE) == [1]
                assert late.wait_for(STATE).payload.startswith(b"clear")
            filler.unlink()
            wait_line(proc, "writable again")
            wait_stored(data, {STATE: b"clear" + b" " * 8000, STATUS: b"x" * 8000})
            with filler.open("wb") as f, contextlib.suppress(OSError):
                while True:
                    f.write(b"\0" * 65536)
            node.publish(STATE, b"lost-at-exit" + b" " * 8000, retain=True)
            wait_line(proc, "cannot store")
        assert proc.proc is not None and proc.proc.returncode == 0
        wait_line(proc, "are LOST")
        assert "Task exception was never retrieved" not in "".join(proc.errors)  # one line, no traceback
        filler.unlink()
        with BrokerProcess(site, creds, data_dir=data) as again:
            with client(endpoint(again), "robot1") as robot:
                assert robot.subscribe(STATE) == [1]
                assert robot.wait_for(STATE).payload.startswith(b"clear")
            assert not [line for line in again.errors if "damaged" in line]
        assert read_retained(data)[STATUS][0] == b"x" * 8000


def test_store_that_cannot_be_opened_stops_the_start_in_one_line(
    setup: tuple[Path, Path], tmp_path: Path
) -> None:
    """Not damage (so nothing is moved): here the store's path is a folder; a read-only disk reads the same."""
    site, creds = setup
    data = tmp_path / "data"
    (data / DB_NAME).mkdir(parents=True)
    result = wsnav(
        "broker", "run", "--site", site, "--credentials", creds, "--bind", "127.0.0.1:0", "--data", data
    )
    assert result.returncode != 0
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert "cannot open the retained store" in result.stderr and "left as it is" in result.stderr
    assert (data / DB_NAME).is_dir()


def fill(disk: Path) -> Path:
    filler = disk / "filler"
    with contextlib.suppress(OSError), filler.open("wb") as f:  # the close's flush fails too
        while True:
            f.write(b"\0" * 65536)
            f.flush()
    return filler


def healthcheck(data: Path) -> subprocess.CompletedProcess[str]:
    command = [
        sys.executable,
        "-m",
        "wsnav.healthcheck",
        "mosquitto-store",
        "--data",
        str(data),
        "--autosave",
        "1",
    ]
    return subprocess.run(command, capture_output=True, text=True, timeout=60)


def test_mosquitto_full_disk_is_reported_at_once_and_the_last_whole_store_comes_back(
    setup: tuple[Path, Path], tmp_path: Path
) -> None:
    """Mosquitto 2.0.11 on a full disk renames an empty store into place without a word: the healthcheck said
    "saved 4 s ago", and after a clean stop every retained message was gone, operator blocks included. Now the
    check fails as soon as the disk is full, and `wsnav broker mosquitto-restore` (ExecStartPre) puts back the
    last whole store the check kept."""
    site, creds = setup
    block = topics.operator_block(SITE, "b1")
    with tiny_tmpfs(tmp_path / "disk", "512k") as disk:
        data = disk / "data"
        with (
            mosquitto_on(site, creds, tmp_path / "mq", data) as (mq, _),
            client(mq, "operator", "operator") as operator,
            client(mq, "n1") as node,
        ):
            operator.publish(block, b'{"marker": "block"}', retain=True)
            node.publish(STATE, b"blocked", retain=True)
            deadline = time.monotonic() + TIMEOUT
            while check_store(data / STORE).retained < 2:
                assert time.monotonic() < deadline, check_store(data / STORE)
                time.sleep(0.1)
            healthy = healthcheck(data)  # the monitor's run every autosave interval: it keeps a copy
            assert healthy.returncode == 0 and "saved" in healthy.stdout, healthy
            filler = fill(disk)
            node.publish(STATE, b"clear", retain=True)
            full = healthcheck(data)  # at once, before Mosquitto's next save
            assert full.returncode == 1 and "bytes free" in full.stderr, full
            deadline = time.monotonic() + TIMEOUT
            while check_store(data / STORE).problem is None:  # Mosquitto's next save, cut short
                assert time.monotonic() < deadline, "Mosquitto's store stayed whole on a full disk"
                time.sleep(0.1)
            cut = healthcheck(data)
            assert cut.returncode == 1, cut
            assert "last save failed" in cut.stderr and "2 retained messages) is kept" in cut.stderr, cut
        assert check_store(data / STORE).problem is not None  # the clean stop's save was cut short too
        filler.unlink()  # room again, then the restart, with ExecStartPre's restore
        restored = wsnav("broker", "mosquitto-restore", "--data", data)
        assert restored.returncode == 0 and "restored the last whole store" in restored.stderr, restored
        assert check_store(data / STORE).retained == 2
        with mosquitto_on(site, creds, tmp_path / "mq", data) as (mq, _), client(mq, "robot1") as robot:
            assert robot.subscribe(block) == [1]
            assert robot.wait_for(block).payload == b'{"marker": "block"}'


def test_mosquitto_with_wsnavs_plugin_logs_a_full_disk_within_a_save_interval_and_keeps_the_last_whole_store(
    setup: tuple[Path, Path], tmp_path: Path
) -> None:
    """Mosquitto 2.0.11 logs nothing when a full disk cuts its store short; with wsnav's plugin its own log says
    so within one save interval (2 s), before and after the save, and says which block a full disk kept out of
    the journal (a block journaled after the last whole save comes back with it); the plugin keeps the last whole store for `wsnav broker mosquitto-restore` by itself (no
    healthcheck runs here). A real 512 KiB tmpfs; the log is on another disk."""
    site, creds = setup
    block, late_block, big_block = (topics.operator_block(SITE, b) for b in ("b1", "b2", "b3"))
    log = tmp_path / "mosquitto.log"
    plugin = store_guard_plugin(tmp_path / "plugin")
    with tiny_tmpfs(tmp_path / "disk", "512k") as disk:
        data = disk / "data"
        with (
            mosquitto_on(site, creds, tmp_path / "mq", data, log=log, store_guard=plugin) as (mq, _),
            client(mq, "operator", "operator") as operator,
            client(mq, "n1") as node,
        ):
            operator.publish(block, b'{"marker": "block"}', retain=True)
            node.publish(STATE, b"blocked", retain=True)
            deadline = time.monotonic() + TIMEOUT
            while check_store(data / f"{STORE}.good").retained < 2:
                assert time.monotonic() < deadline, check_store(data / f"{STORE}.good")
                time.sleep(0.1)
            filler = fill(disk)
            full_at = time.monotonic()
            line = wait_log(log, "is full")
            assert time.monotonic() - full_at < 2.5, "not within one save interval"
            assert "ERROR" in line and "bytes free" in line, line
            node.publish(STATE, b"clear", retain=True)
            line = wait_log(log, "a restart would lose every retained message")
            assert "ERROR" in line and f"{STORE}.good" in line, line
            operator.publish(late_block, b'{"marker": "late"}', retain=True)  # fits the journal's last page
            operator.publish(big_block, b"x" * 8000, retain=True)  # does not: in force, and said so
            line = wait_log(log, "NOT journaled")
            assert big_block in line and "will not survive a power cut" in line, line
        assert check_store(data / STORE).problem is not None  # the clean stop's save was cut short too
        assert check_store(data / f"{STORE}.good").retained == 2
        filler.unlink()
        restored = wsnav("broker", "mosquitto-restore", "--data", data)
        assert restored.returncode == 0 and "restored the last whole store" in restored.stderr, restored
        with (
            mosquitto_on(site, creds, tmp_path / "mq", data, store_guard=plugin) as (mq, _),
            client(mq, "robot1") as robot,
        ):
            assert robot.subscribe(topics.all_operator_blocks(SITE)) == [1]
            assert robot.wait_for(block).payload == b'{"marker": "block"}'
            assert robot.wait_for(late_block).payload == b'{"marker": "late"}'  # from the journal


def wait_log(log: Path, needle: str) -> str:
    """The first line of Mosquitto's log holding `needle`, waiting for it up to TIMEOUT."""
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        for line in log.read_text(errors="replace").splitlines():
            if needle in line:
                return line
        time.sleep(0.05)
    raise AssertionError(f"no line with {needle!r} in Mosquitto's log: {log.read_text(errors='replace')}")


def mosquitto_store(retained: int) -> bytes:
    """A store in Mosquitto 2.0's framing: header, a config chunk, `retained` retain chunks."""
    chunks = struct.pack("!II", 1, 16) + bytes(16)
    chunks += b"".join(struct.pack("!II", 4, 8) + struct.pack("!Q", i) for i in range(retained))
    return MAGIC + bytes(4) + struct.pack("!I", 6) + chunks


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"", "empty"),
        (b"\x00" * 4096, "not a Mosquitto store"),
        (mosquitto_store(3)[:-3], "cut short"),
        (mosquitto_store(3)[:-20], "cut short"),
        (mosquitto_store(0)[:23], "no config chunk"),
    ],
    ids=["empty", "zeros", "cut-in-payload", "cut-in-header", "header-only"],
)
def test_mosquitto_restore_puts_the_last_whole_store_back_and_sets_the_cut_one_aside(
    tmp_path: Path, content: bytes, problem: str
) -> None:
    (tmp_path / STORE).write_bytes(mosquitto_store(3))
    assert check_store(tmp_path / STORE) == StoreCheck(None, 3, (tmp_path / STORE).stat().st_mtime)
    keep_good(tmp_path)
    (tmp_path / STORE).unlink()  # Mosquitto's rename of a new file over it
    (tmp_path / STORE).write_bytes(content)
    assert problem in str(check_store(tmp_path / STORE).problem)
    restored = wsnav("broker", "mosquitto-restore", "--data", tmp_path)
    assert restored.returncode == 0 and "restored the last whole store" in restored.stderr, restored
    assert (tmp_path / STORE).read_bytes() == mosquitto_store(3)
    assert [p.read_bytes() for p in tmp_path.glob(f"{STORE}.damaged-*")] == [content]
    again = wsnav("broker", "mosquitto-restore", "--data", tmp_path)
    assert again.returncode == 0 and "whole (3 retained messages)" in again.stdout, again


def test_mosquitto_restore_without_a_whole_copy_says_so_and_lets_mosquitto_start(tmp_path: Path) -> None:
    (tmp_path / STORE).write_bytes(b"")
    restored = wsnav("broker", "mosquitto-restore", "--data", tmp_path)
    assert restored.returncode == 1 and restored.stderr.count("\n") == 1, restored
    assert "ERROR" in restored.stderr and "send the operator blocks again" in restored.stderr
    first = wsnav("broker", "mosquitto-restore", "--data", tmp_path / "new")
    assert first.returncode == 0 and "a first start" in first.stdout, first
