"""The retained store's policy, on `wsnav broker run`: a damaged, truncated or empty file is set aside with one
loud line and the broker starts empty and keeps storing; a full disk (a tiny tmpfs) is reported at once, nothing
acknowledged is dropped while the broker runs, and what could not be written by exit is reported as lost."""

from __future__ import annotations

import contextlib
import os
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.broker_fixtures import TIMEOUT, Endpoint, client, wait_stored, wsnav
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerProcess
from wsnav.broker.amqtt.retained_store import DB_NAME, read_retained
from wsnav.broker.credentials import write_credentials
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


def cannot(reason: str) -> None:
    """Skip, but fail under WSNAV_REQUIRE_TOOLS=1 (CI): there the full-disk test must run, not skip."""
    if os.environ.get("WSNAV_REQUIRE_TOOLS") == "1":
        pytest.fail(f"{reason} (WSNAV_REQUIRE_TOOLS=1)")
    pytest.skip(reason)


@contextlib.contextmanager
def tiny_tmpfs(path: Path, size: str) -> Iterator[Path]:
    path.mkdir()
    if os.geteuid() != 0:
        cannot("mounting a tmpfs needs root (CI runs as root)")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], check=False)
    if mounted.returncode != 0:
        cannot("cannot mount a tmpfs here")
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
