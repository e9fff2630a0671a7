"""`wsnav node-command`: the operator's commands to a zone node, checked against the site and sent as QoS 1,
not retained, to `nodes/<node>/command` (the node's side: tests/test_firmware_node.py)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.broker_fixtures import Endpoint, client
from tests.site_fixtures import tiny_site
from wsnav import cli
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.credentials import write_credentials
from wsnav.console import operator_commands as commands
from wsnav.console.operator_commands import CommandError
from wsnav.schemas import topics
from wsnav.schemas.messages import NodeCommand, parse_payload
from wsnav.schemas.site import load_site


def test_a_node_command_is_checked_against_the_site(tmp_path: Path) -> None:
    site = load_site(tiny_site(tmp_path))
    pub = commands.node_command(site, "n1", "set_heartbeat", 2.5)
    msg = parse_payload(NodeCommand, pub.payload)
    assert (pub.topic, pub.retain) == (topics.node_command(site.name, "n1"), False)
    assert (msg.command, msg.heartbeat_s) == ("set_heartbeat", 2.5)
    assert (
        commands.node_command(site, "n1", "restart").payload
        != commands.node_command(site, "n1", "restart").payload
    )
    with pytest.raises(CommandError, match="unknown node 'n9'"):
        commands.node_command(site, "n9", "send_info")
    for bad in (0.0, -1.0, 3601.0, None):
        with pytest.raises(CommandError, match="at most 3600 s"):
            commands.node_command(site, "n1", "set_heartbeat", bad)


def test_the_command_line_sends_it_confirmed_and_refuses_bad_input_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    site_dir = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site_dir).spec, creds)
    with BrokerThread(site_dir, creds) as broker:
        endpoint = Endpoint("amqtt", broker.host, broker.port, creds)
        common = ["--site", str(site_dir), "--broker", f"{broker.host}:{broker.port}"]
        common += ["--credentials", str(creds / "operator.json")]
        own = topics.node_command("tiny", "n1")
        with client(endpoint, "n1") as node:
            assert node.subscribe(own) == [1]
            assert cli.main(["node-command", *common, "n1", "heartbeat", "2"]) == 0
            got = node.wait_for(own)
            assert not got.retain and got.qos == 1
            assert parse_payload(NodeCommand, got.payload).heartbeat_s == 2.0
            assert cli.main(["node-command", *common, "n1", "send-info"]) == 0
            deadline = time.monotonic() + 30
            while len(node.received) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            sent = [parse_payload(NodeCommand, r.payload).command for r in node.received if r.topic == own]
            assert sent == ["set_heartbeat", "send_info"]
        capsys.readouterr()
        for argv, why in [
            (["n1", "heartbeat"], "heartbeat takes SECONDS"),
            (["n1", "restart", "5"], "heartbeat takes SECONDS"),
            (["n1", "heartbeat", "soon"], "expected a number"),
            (["n1", "heartbeat", "0"], "at most 3600 s"),
            (["n9", "restart"], "unknown node 'n9'"),
        ]:
            assert cli.main(["node-command", *common, *argv]) == 2
            err = capsys.readouterr().err
            assert why in err and err.count("\n") == 1, err
