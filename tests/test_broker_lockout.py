"""No lock-out by idle sockets: `wsnav broker run` under a 1024 open-file limit, attacked from other processes.

2,000 sockets that never send CONNECT plus 2,000 connect-and-close cycles: a real node still logs in within 2 s
during and after the attack, the log does not fill, and the broker's descriptors return to their baseline.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.broker_fixtures import TIMEOUT, Client, Endpoint, client
from tests.conftest import REPO
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.admission import MAX_PER_IDENTITY
from wsnav.broker.amqtt.embedded import BrokerProcess
from wsnav.broker.credentials import write_credentials
from wsnav.schemas import topics
from wsnav.schemas.site import load_site

SITE = "tiny"
LOGIN_S = 2.0
SLOTS = 30


def open_descriptors(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def login_seconds(ep: Endpoint) -> float:
    """How long node n1 takes from TCP connect to CONNACK (a refusal or no answer fails the test)."""
    return login_seconds_as(ep, "n1")


def login_seconds_as(ep: Endpoint, ident: str) -> float:
    started = time.monotonic()
    node = Client(ep, ident, ident, ep.password(ident))
    try:
        assert not node.connect().is_failure
    finally:
        node.close()
    return time.monotonic() - started


def attack(port: int, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "tests.broker_attack", *args[:1], str(port), *args[1:]],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


@pytest.fixture
def broker(tmp_path: Path) -> BrokerProcess:
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    return BrokerProcess(site, creds, data_dir=tmp_path / "data", open_files=1024)


def test_idle_sockets_and_churn_never_lock_a_node_out(broker: BrokerProcess) -> None:
    with broker:
        assert broker.proc is not None
        pid = broker.proc.pid
        ep = Endpoint("amqtt", broker.host, broker.port, broker.credentials_dir)
        login_seconds(ep)
        baseline = open_descriptors(pid)
        idle = attack(broker.port, "idle", "2000", "8")
        churn = attack(broker.port, "churn", "2000")
        during: list[float] = []
        try:
            while idle.poll() is None or churn.poll() is None:
                during.append(login_seconds(ep))
                time.sleep(0.3)
        finally:
            for proc in (idle, churn):
                proc.wait(TIMEOUT * 4)
        report = [(p.stdout.read() if p.stdout else "").strip() for p in (idle, churn)]
        assert len(during) >= 5, report
        assert max(during) < LOGIN_S, (during, report)
        print(report, f"logins during the attack: max {max(during):.3f} s over {len(during)}")
        after = login_seconds(ep)
        assert after < LOGIN_S
        deadline = time.monotonic() + TIMEOUT
        while open_descriptors(pid) > baseline and time.monotonic() < deadline:
            time.sleep(0.2)
        assert open_descriptors(pid) <= baseline
        with client(ep, "n1") as node, client(ep, "robot1") as robot:
            state = topics.zone_state(SITE, "z1", "n1")
            assert robot.subscribe(state) == [1]
            node.publish(state, b"still-served")
            robot.wait_for(state, b"still-served")
        assert len(broker.errors) < 20, broker.errors[:20]


def test_a_socket_that_never_sends_connect_is_dropped_within_seconds(broker: BrokerProcess) -> None:
    import socket

    with broker, socket.create_connection((broker.host, broker.port), timeout=TIMEOUT) as idle:
        started = time.monotonic()
        assert idle.recv(1) == b""  # closed by the broker
        assert time.monotonic() - started < 10


def test_a_full_broker_makes_room_for_a_login_by_closing_idle_sockets(tmp_path: Path) -> None:
    """`--max-connections 50` and 60 idle sockets used to lock everyone out."""
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    extra = ["--max-connections", "50", "--connect-timeout", "60"]
    with BrokerProcess(site, creds, extra_args=extra) as proc:
        ep = Endpoint("amqtt", proc.host, proc.port, creds)
        idle = attack(proc.port, "idle", "60", "5")
        time.sleep(2)
        try:
            assert login_seconds(ep) < LOGIN_S
            with client(ep, "robot1") as robot:  # logged-in clients are never pushed out by newer sockets
                more = attack(proc.port, "idle", "60", "1")
                more.wait(TIMEOUT)
                status = topics.robot_status(SITE, "robot1")
                assert robot.subscribe(status) == [1]
                robot.publish(status, b"still-here")
                robot.wait_for(status, b"still-here")
                assert robot.disconnects == []
        finally:
            idle.wait(TIMEOUT)


def test_a_stolen_credential_cannot_fill_the_slots_with_logins(tmp_path: Path) -> None:
    """Logged-in connections are never pushed out, so without a per-identity cap one node's password and
    distinct client ids could take every slot; the cap is MAX_PER_IDENTITY connections per identity."""
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    with BrokerProcess(site, creds, extra_args=["--max-connections", str(SLOTS)]) as proc:
        ep = Endpoint("amqtt", proc.host, proc.port, creds)
        thief = [Client(ep, f"n1-{i}", "n1", ep.password("n1")) for i in range(SLOTS + 4)]
        try:
            reasons = [c.connect() for c in thief]
            assert sum(not r.is_failure for r in reasons) == MAX_PER_IDENTITY
            assert login_seconds_as(ep, "robot1") < LOGIN_S
        finally:
            for c in thief:
                c.close()
        deadline = time.monotonic() + TIMEOUT
        while time.monotonic() < deadline:  # the broker sees the closes a moment later
            with contextlib.suppress(AssertionError):
                login_seconds(ep)
                break
            time.sleep(0.2)
        assert login_seconds(ep) < LOGIN_S
