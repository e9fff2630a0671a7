"""Pending passwords on both brokers: a node's new password taken beside its own until the node confirms it
(`wsnav firmware config --new-password`), never a moment where neither is taken; then only the new one.

amqtt reads broker.pending beside its password file (broker/amqtt/auth.py); Debian's Mosquitto 2.0.11 loads the
plugin built from broker/mosquitto/pending_auth.c by `wsnav broker mosquitto-config --pending-passwords`.
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

from tests.broker_fixtures import Client, Endpoint, client, connect_reason, mosquitto_on, store_guard_plugin
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.credentials import add_pending, promote_pending, withdraw_pending, write_credentials
from wsnav.broker.mosquitto import pending
from wsnav.broker.mosquitto.config import rewrite_passwords
from wsnav.broker.mosquitto.pending_plugin import PENDING
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.site import load_site

pytestmark = pytest.mark.slow

NEW = "a-new-password-of-the-node-0123"


@contextlib.contextmanager
def broker(
    kind: str, site: Path, creds: Path, root: Path
) -> Iterator[tuple[Endpoint, Path | None, int | None]]:
    """(endpoint, the Mosquitto configuration folder, Mosquitto's pid), both None on amqtt."""
    if kind == "amqtt":
        with BrokerThread(site, creds) as b:
            yield Endpoint("amqtt", b.host, b.port, creds), None, None
        return
    conf = root / "mq"
    with mosquitto_on(site, creds, conf, root / "mq-data", pending_passwords=True) as (end, proc):
        yield end, conf, proc.pid


def add(creds: Path, mosquitto: Path | None, user: str, password: str) -> None:
    """As `wsnav firmware config --new-password` adds a node's new password."""
    add_pending(creds, user, password)
    if mosquitto is not None:
        pending.add(mosquitto, user, password)


def takes(endpoint: Endpoint, user: str, password: str) -> bool:
    return not connect_reason(endpoint, user, password, client_id=f"{user}-probe").is_failure


@pytest.mark.parametrize("kind", ["amqtt", "mosquitto"])
def test_the_pending_password_is_taken_beside_the_old_one_until_it_is_promoted(
    kind: str, tmp_path: Path
) -> None:
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    spec = load_site(site).spec
    write_credentials(spec, creds)
    old = load_credentials(creds / "n1.json").password
    with broker(kind, site, creds, tmp_path) as (end, mosquitto, pid):
        assert takes(end, "n1", old) and not takes(end, "n1", NEW)
        add(creds, mosquitto, "n1", NEW)
        time.sleep(0.6)  # amqtt looks at its files every 0.5 s
        assert takes(end, "n1", old) and takes(end, "n1", NEW)
        assert not takes(end, "n1", "a-wrong-password-0123456789")
        assert not takes(end, "n2", NEW)  # n1's pending password is n1's only
        node = Client(end, "n1", "n1", NEW)  # the node, back with its new password
        assert not node.connect().is_failure
        try:
            promote_pending(creds, "n1", NEW)  # it confirmed
            if mosquitto is not None:
                pending.keep_only(mosquitto, "n1", NEW)
                rewrite_passwords(spec, creds, mosquitto)
                assert pid is not None
                os.kill(pid, signal.SIGHUP)  # systemctl reload mosquitto
            time.sleep(1.5)
            assert node.disconnects == []  # the node's connection stays
            assert load_credentials(creds / "n1.json").password == NEW
            assert takes(end, "n1", NEW) and not takes(end, "n1", old)
        finally:
            node.close()


@pytest.mark.parametrize("kind", ["amqtt", "mosquitto"])
def test_a_change_that_went_back_withdraws_its_own_password_only(kind: str, tmp_path: Path) -> None:
    """The node's password is taken from the pending file alone (amqtt: an earlier change it never answered;
    Mosquitto: an earlier change it confirmed, its password file rewritten but not reloaded yet); a later change
    that went back withdraws that change's password, and the node's still logs in."""
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    spec = load_site(site).spec
    write_credentials(spec, creds)
    earlier, later = "an-earlier-new-password-0123", "a-later-new-password-4567"
    with broker(kind, site, creds, tmp_path) as (end, mosquitto, _pid):
        add(creds, mosquitto, "n1", earlier)
        if mosquitto is not None:
            promote_pending(creds, "n1", earlier)
            pending.keep_only(mosquitto, "n1", earlier)
            rewrite_passwords(spec, creds, mosquitto)  # and no `systemctl reload mosquitto` yet
        add(creds, mosquitto, "n1", later)
        withdraw_pending(creds, "n1", later)  # as `wsnav firmware config` does for a node that went back
        if mosquitto is not None:
            pending.withdraw(mosquitto, "n1", later)
        time.sleep(0.6)
        assert takes(end, "n1", earlier) and not takes(end, "n1", later)


@pytest.mark.parametrize("kind", ["amqtt", "mosquitto"])
def test_a_revoked_node_loses_its_pending_password_too(kind: str, tmp_path: Path) -> None:
    """A stolen node is revoked in the middle of a password change: neither its old nor its pending password
    logs in afterwards."""
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    old = load_credentials(creds / "n1.json").password
    with broker(kind, site, creds, tmp_path) as (end, mosquitto, pid):
        add(creds, mosquitto, "n1", NEW)
        command = [
            sys.executable, "-m", "wsnav.cli", "broker", "revoke", "n1", "--site", str(site),
            "--credentials", str(creds),
        ]  # fmt: skip
        if mosquitto is not None:
            command += ["--mosquitto-config", str(mosquitto)]
        done = subprocess.run(command, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        if pid is not None:
            os.kill(pid, signal.SIGHUP)
        time.sleep(1.5)
        assert not takes(end, "n1", NEW) and not takes(end, "n1", old)
        assert takes(end, "n1", load_credentials(creds / "n1.json").password)


@pytest.mark.parametrize("kind", ["amqtt", "mosquitto"])
def test_a_garbage_pending_file_stops_no_login(kind: str, tmp_path: Path) -> None:
    """Lines no broker can use (bad base64, absurd iteration counts, a 10 KB line, binary): every login the
    password file takes still works, and no garbage line lets anyone in."""
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    with broker(kind, site, creds, tmp_path) as (end, mosquitto, _pid):
        garbage = (
            "n1:$7$101$!!!!$????\n"
            "n1:$7$2000000000$AAAAAAAAAAAAAAAA$AAAA\n"
            "n1:$7$-5$AAAAAAAAAAAAAAAA$" + "A" * 88 + "\n"
            "n1:" + "x" * 10_000 + "\n"
            "\x00\xff:garbage\n"
            "n1:$argon2id$v=19$m=1,t=1,p=1$AAAA$AAAA\n"
        )
        target = (mosquitto / PENDING) if mosquitto is not None else (creds / "broker.pending")
        target.write_text(garbage, errors="surrogateescape")
        time.sleep(0.6)
        for user in ("n1", "n2"):
            assert takes(end, user, end.password(user))
        assert not takes(end, "n1", "x" * 32) and not takes(end, "n1", "AAAA" * 8)


def test_mosquitto_config_builds_and_loads_the_plugin_and_a_rerun_keeps_pending_passwords(
    tmp_path: Path,
) -> None:
    """`wsnav broker mosquitto-config --pending-passwords`: the plugin built into the folder and loaded by
    mosquitto.conf, its file owner-only; run again (a site's config regenerated), the passwords of a change under
    way are kept (a new empty file would lock out the node trying its new one)."""
    site = tiny_site(tmp_path / "site")
    creds, out = tmp_path / "creds", tmp_path / "mosq"
    write_credentials(load_site(site).spec, creds)
    cmd = [
        sys.executable, "-m", "wsnav.cli", "broker", "mosquitto-config", "--site", str(site),
        "--credentials", str(creds), "--out", str(out), "--data", str(tmp_path / "data"), "--pending-passwords",
    ]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    conf = (out / "mosquitto.conf").read_text().splitlines()
    assert f"plugin {out.resolve() / 'wsnav_pending.so'}" in conf
    assert f"plugin_opt_pending_file {out.resolve() / PENDING}" in conf
    assert (out / PENDING).read_text() == "" and (out / PENDING).stat().st_mode & 0o777 == 0o600
    pending.add(out, "n1", NEW)
    line = (out / PENDING).read_text()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert (out / PENDING).read_text() == line


def test_mosquitto_with_both_of_wsnavs_plugins_takes_pending_passwords_and_keeps_blocks_over_a_kill_9(
    tmp_path: Path,
) -> None:
    """The Pi guide's Mosquitto loads both plugins (--store-guard --pending-passwords): each gets its own
    plugin_opt lines and neither hides the other: a node's pending password is taken, and an operator block
    acknowledged just before a kill -9 is back after the restart."""
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    conf, data = tmp_path / "mq", tmp_path / "mq-data"
    guard = store_guard_plugin(tmp_path / "guard")
    block = topics.operator_block("tiny", "b1")

    def both() -> contextlib.AbstractContextManager[tuple[Endpoint, subprocess.Popen[bytes]]]:
        return mosquitto_on(site, creds, conf, data, pending_passwords=True, store_guard=guard)

    with both() as (end, proc):
        add(creds, conf, "n1", NEW)
        assert takes(end, "n1", NEW)
        with client(end, "operator", "operator") as operator:
            operator.publish(block, b'{"block": 1}', retain=True)
        proc.kill()
        proc.wait()
    with both() as (end, _), client(end, "robot1") as robot:
        assert takes(end, "n1", NEW)
        assert robot.subscribe("wsn/tiny/operator/blocks/#") == [1]
        robot.wait_for(block, b'{"block": 1}', timeout=5.0)
