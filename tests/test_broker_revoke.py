"""Revoking a stolen node credential without restarting the broker, on amqtt and on Mosquitto.

The thief is connected with the node's password and has left a retained `blocked` state and a last will.
`wsnav broker revoke n1 --broker ...` must end with: the thief's connection closed, its old password refused,
nothing of n1 retained (a robot starting afterwards sees no `blocked` from it), the other node untouched, and
the new password in n1.json working.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.broker_fixtures import TIMEOUT, Client, Endpoint, client, connect_reason
from tests.conftest import require_tool
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.config import PASSWORDS
from wsnav.broker.mosquitto.process import mosquitto_process
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.site import load_site

SITE = "tiny"


@contextlib.contextmanager
def broker(kind: str, site: Path, creds: Path, root: Path) -> Iterator[tuple[Endpoint, int | None]]:
    """(endpoint, Mosquitto's pid or None for amqtt)."""
    if kind == "amqtt":
        with BrokerThread(site, creds) as b:
            yield Endpoint("amqtt", b.host, b.port, creds), None
        return
    require_tool("mosquitto")
    with mosquitto_process(load_site(site).spec, creds, root) as mq:
        yield Endpoint("mosquitto", mq.host, mq.port, creds), mq.pid


@pytest.mark.parametrize("kind", ["amqtt", "mosquitto"])
def test_a_revoked_node_is_cut_off_and_its_retained_word_is_gone(kind: str, tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    old_password = load_credentials(creds / "n1.json").password
    state1, status1 = topics.zone_state(SITE, "z1", "n1"), topics.node_status(SITE, "n1")
    state2 = topics.zone_state(SITE, "z2", "n2")
    with broker(kind, site, creds, tmp_path / "mq") as (endpoint, mosquitto_pid):
        with client(endpoint, "n2") as n2:
            n2.publish(state2, b'{"other": "node"}', retain=True)
        thief = Client(endpoint, "n1", "n1", old_password)
        assert not thief.connect(will=(status1, b'{"status": "offline"}')).is_failure
        try:
            thief.publish(state1, b'{"state": "blocked"}', retain=True)
            thief.publish(status1, b'{"status": "online"}', retain=True)
            command = [
                sys.executable, "-m", "wsnav.cli", "broker", "revoke", "n1", "--site", str(site),
                "--credentials", str(creds), "--broker", f"{endpoint.host}:{endpoint.port}", "--wait", "30",
            ]  # fmt: skip
            if mosquitto_pid is not None:
                command += ["--mosquitto-config", str(tmp_path / "mq" / "mq")]
            passwd = tmp_path / "mq" / "mq" / PASSWORDS
            before = passwd.stat().st_mtime_ns if passwd.exists() else None
            revoke = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            if mosquitto_pid is not None:  # the operator's `systemctl reload mosquitto`, once the file is new
                deadline = time.monotonic() + TIMEOUT
                while passwd.stat().st_mtime_ns == before:
                    assert time.monotonic() < deadline, "the Mosquitto password file was not rewritten"
                    time.sleep(0.05)
                os.kill(mosquitto_pid, signal.SIGHUP)
            out, err = revoke.communicate(timeout=120)
            assert revoke.returncode == 0, (out, err)
            assert f"cleared {state1}" in out, out
            deadline = time.monotonic() + TIMEOUT
            while not thief.disconnects:
                assert time.monotonic() < deadline, "the thief is still connected"
                time.sleep(0.05)
        finally:
            thief.mqtt.reconnect_delay_set(3600, 3600)  # the thief would retry with the old password
            thief.close()
        assert connect_reason(endpoint, "n1", old_password, client_id="n1").is_failure
        assert load_credentials(creds / "n1.json").password != old_password
        with client(endpoint, "n1") as renewed:  # the new password works (Endpoint reads n1.json again)
            assert renewed.mqtt.is_connected()
        with client(endpoint, "operator", "operator-after") as robot_view:
            robot_view.subscribe(f"wsn/{SITE}/#")
            robot_view.wait_for(state2, b'{"other": "node"}')
            time.sleep(1.0)
            assert state1 not in robot_view.topics() and status1 not in robot_view.topics()


def test_revoke_refuses_unknown_ids_in_one_line(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    write_credentials(load_site(site).spec, tmp_path / "creds")
    done = subprocess.run(
        [sys.executable, "-m", "wsnav.cli", "broker", "revoke", "n9", "--site", str(site), "--credentials",
         str(tmp_path / "creds")],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 2 and "not ids of site tiny: n9" in done.stderr
    assert "Traceback" not in done.stderr
