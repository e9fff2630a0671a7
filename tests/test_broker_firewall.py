"""Mosquitto's per-source byte rate (`wsnav broker firewall`), tried in network namespaces of our own.

One namespace holds Mosquitto (from the generated config) and the robot's subscription; another holds two node
addresses: n1 floods QoS 0 zone states from one, n2 sends its states from the other. With the generated rule
loaded in the broker's namespace, n1's flood reaches the robot only at its byte rate, every n2 state arrives,
and no n1 state arrives more than 1 s after the flooder exited. Without the rule (checked while writing this
test) the robot took 67,850 of n1's states in the window and 2 of n2's 40 states had not arrived by its end;
with the rule that dropped the excess instead of resetting the connection, n1's states went on arriving 3.4 s
after the flooder exited, until the window closed (its kernel sent on what it had queued, at the rate).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import require_tool, unavailable
from tests.netns_fixtures import NamespaceError, NamespacePair, exec_in, namespace_pair
from tests.site_fixtures import tiny_site
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.broker.mosquitto.firewall import NODE_BURST_KBYTES, NODE_RATE_KBYTES, nft_rules
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.site import load_site

SECONDS = 6.0


@pytest.fixture
def namespaces() -> Iterator[NamespacePair]:
    require_tool("ip")
    require_tool("nft")
    if os.geteuid() != 0:
        unavailable("network namespaces need root (CI runs as root)")
    try:
        with namespace_pair("10.99.37", "t") as pair:
            yield pair
    except NamespaceError as exc:
        unavailable(str(exc))


def peer(ns: str, *args: str) -> subprocess.Popen[str]:
    command = [*exec_in(ns), sys.executable, "-m", "tests.netns_peer", *args]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def result(proc: subprocess.Popen[str]) -> dict[str, Any]:
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    return dict(json.loads(out.splitlines()[-1]))


def test_a_flooding_node_is_held_to_its_byte_rate_and_the_other_node_gets_through(
    namespaces: NamespacePair, tmp_path: Path
) -> None:
    pair = namespaces
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    password = {i: load_credentials(creds / f"{i}.json").password for i in ("n1", "n2", "robot1")}
    options = MosquittoOptions(bind=("0.0.0.0", 1883), data_dir=tmp_path / "data", user="root")
    write_mosquitto_config(load_site(site).spec, creds, tmp_path / "mq", options)
    rules = tmp_path / "mqtt.nft"
    rules.write_text(nft_rules(pair.subnet))
    subprocess.run([*exec_in(pair.broker), "nft", "-f", str(rules)], check=True)
    mosquitto = require_tool("mosquitto")
    broker = subprocess.Popen(
        [*exec_in(pair.broker), mosquitto, "-c", str(tmp_path / "mq" / CONF)],
        stderr=subprocess.PIPE,
    )
    try:
        subprocess.run(  # until it listens
            [*exec_in(pair.broker), sys.executable, "-c",
             "import socket,time\nfor _ in range(300):\n    try:\n        socket.create_connection(('127.0.0.1', 1883), 1).close(); break\n"
             "    except OSError: time.sleep(0.05)"],
            check=True, timeout=60,
        )  # fmt: skip
        watch = peer(pair.broker, "watch", "127.0.0.1", "robot1", password["robot1"], str(SECONDS + 4))
        assert watch.stdout is not None and watch.stdout.readline().strip() == "subscribed", result(watch)
        flood = peer(pair.nodes, "flood", pair.broker_address, "n1", password["n1"], str(SECONDS))
        probe = peer(
            pair.nodes, "probe", pair.broker_address, "n2", password["n2"], "40", pair.node_address(2)
        )
        flooded, probed, seen = result(flood), result(probe), result(watch)
    finally:
        broker.terminate()
        broker.wait(30)
    got, last = seen["got"], seen["last"]
    assert probed == {"sent": 40, "acknowledged": 40}
    assert got.get("wsn/tiny/zones/z2/state/n2") == 40, seen  # every state of the other node
    allowed_bytes = (NODE_BURST_KBYTES + NODE_RATE_KBYTES * (SECONDS + 4)) * 1024
    n1 = got.get("wsn/tiny/zones/z1/state/n1", 0)
    assert 0 < n1 <= allowed_bytes / 80, (n1, flooded)  # a flood message is over 80 bytes on the wire
    assert flooded["sent"] > 10 * n1
    # the flooder is gone: nothing it sent is still on its way 1 s later (its kernel held it behind the rate)
    assert last["wsn/tiny/zones/z1/state/n1"] <= flooded["ended"] + 1.0, (last, flooded)
