"""Mosquitto's per-source byte rate (`wsnav broker firewall`), tried in network namespaces of our own.

One namespace holds Mosquitto (from the generated config) and the robot's subscription; another holds two node
addresses: n1 floods QoS 0 zone states from one, n2 sends its states from the other. With the generated rule
loaded in the broker's namespace, n1's flood reaches the robot only at its byte rate and every n2 state arrives.
Without it (checked while writing this test) the robot took 67,850 of n1's states in the window and 2 of n2's
40 states had not arrived by its end.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import require_tool, unavailable
from tests.site_fixtures import tiny_site
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.broker.mosquitto.firewall import NODE_BURST_KBYTES, NODE_RATE_KBYTES, nft_rules
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.site import load_site

PREFIX = "10.99.37"
BROKER_NS, NODES_NS = f"wsnav-b{os.getpid()}", f"wsnav-n{os.getpid()}"
SECONDS = 6.0


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


@pytest.fixture
def namespaces() -> Iterator[None]:
    require_tool("ip")
    require_tool("nft")
    if os.geteuid() != 0:
        unavailable("network namespaces need root (CI runs as root)")
    veth = f"w{os.getpid() % 100000}"
    try:
        ip("netns", "add", BROKER_NS)
        ip("netns", "add", NODES_NS)
        ip("link", "add", f"{veth}a", "type", "veth", "peer", "name", f"{veth}b")
        ip("link", "set", f"{veth}a", "netns", BROKER_NS)
        ip("link", "set", f"{veth}b", "netns", NODES_NS)
        ip("-n", BROKER_NS, "addr", "add", f"{PREFIX}.1/24", "dev", f"{veth}a")
        for host in (2, 3):
            ip("-n", NODES_NS, "addr", "add", f"{PREFIX}.{host}/24", "dev", f"{veth}b")
        for ns, dev in ((BROKER_NS, f"{veth}a"), (NODES_NS, f"{veth}b")):
            ip("-n", ns, "link", "set", dev, "up")
            ip("-n", ns, "link", "set", "lo", "up")
    except subprocess.CalledProcessError as exc:
        unavailable(f"cannot make network namespaces here: {exc.stderr.decode(errors='replace').strip()}")
    try:
        yield
    finally:
        for ns in (BROKER_NS, NODES_NS):
            subprocess.run(["ip", "netns", "del", ns], check=False, capture_output=True)


def peer(ns: str, *args: str) -> subprocess.Popen[str]:
    command = ["ip", "netns", "exec", ns, sys.executable, "-m", "tests.netns_peer", *args]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def result(proc: subprocess.Popen[str]) -> dict[str, int]:
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    return dict(json.loads(out.splitlines()[-1]))


def test_a_flooding_node_is_held_to_its_byte_rate_and_the_other_node_gets_through(
    namespaces: None, tmp_path: Path
) -> None:
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    password = {i: load_credentials(creds / f"{i}.json").password for i in ("n1", "n2", "robot1")}
    options = MosquittoOptions(bind=("0.0.0.0", 1883), data_dir=tmp_path / "data", user="root")
    write_mosquitto_config(load_site(site).spec, creds, tmp_path / "mq", options)
    rules = tmp_path / "mqtt.nft"
    rules.write_text(nft_rules(f"{PREFIX}.0/24"))
    subprocess.run(["ip", "netns", "exec", BROKER_NS, "nft", "-f", str(rules)], check=True)
    mosquitto = require_tool("mosquitto")
    broker = subprocess.Popen(
        ["ip", "netns", "exec", BROKER_NS, mosquitto, "-c", str(tmp_path / "mq" / CONF)],
        stderr=subprocess.PIPE,
    )
    try:
        subprocess.run(  # until it listens
            ["ip", "netns", "exec", BROKER_NS, sys.executable, "-c",
             "import socket,time\nfor _ in range(300):\n    try:\n        socket.create_connection(('127.0.0.1', 1883), 1).close(); break\n"
             "    except OSError: time.sleep(0.05)"],
            check=True, timeout=60,
        )  # fmt: skip
        watch = peer(BROKER_NS, "watch", "127.0.0.1", "robot1", password["robot1"], str(SECONDS + 4))
        assert watch.stdout is not None and watch.stdout.readline().strip() == "subscribed", result(watch)
        flood = peer(NODES_NS, "flood", f"{PREFIX}.1", "n1", password["n1"], str(SECONDS))
        probe = peer(NODES_NS, "probe", f"{PREFIX}.1", "n2", password["n2"], "40", f"{PREFIX}.3")
        flooded, probed, seen = result(flood), result(probe), result(watch)
    finally:
        broker.terminate()
        broker.wait(30)
    assert probed == {"sent": 40, "acknowledged": 40}
    assert seen.get("wsn/tiny/zones/z2/state/n2") == 40, seen  # every state of the other node
    allowed_bytes = (NODE_BURST_KBYTES + NODE_RATE_KBYTES * (SECONDS + 4)) * 1024
    n1 = seen.get("wsn/tiny/zones/z1/state/n1", 0)
    assert 0 < n1 <= allowed_bytes / 80, (n1, flooded)  # a flood message is over 80 bytes on the wire
    assert flooded["sent"] > 10 * n1
