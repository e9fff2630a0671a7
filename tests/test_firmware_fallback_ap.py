"""The fallback access point end to end (firmware/device/fallback_ap.py): a node on the MicroPython unix port
(firmware/unix_board.py: boot.py and main.py at each reset) that joins no known network opens its access point,
whose page a real HTTP client (http.client, over a real socket) drives; good settings are tried as a configuration
trial and kept once the node is online through the project's broker (`wsnav broker run`).

What the fake radio (host_stubs/network.py) leaves out: the access point is the host's loopback, so there is no
WPA2 and no association; the test checks the name, key and auth mode the firmware gives the radio (and that the
operator's `wsnav firmware fallback-ap` prints the same), not that a radio enforces them.
"""

from __future__ import annotations

import http.client
import json
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests import ota_fixtures
from tests.conftest import REPO
from tests.ota_fixtures import NODE, Board, node_key
from tests.ota_fixtures import WAIT as OTA_WAIT
from wsnav.firmware.build import build
from wsnav.firmware.testing import SHORT_TRIAL, build_for_host, versioned_sources
from wsnav.schemas.credentials import fallback_ap_key, fallback_ap_ssid

pytestmark = pytest.mark.slow

creds, broker, infos = ota_fixtures.creds, ota_fixtures.broker, ota_fixtures.infos
"""The site's credentials, `wsnav broker run` with them, the node's `info` as the operator sees it."""
VERSION = "1.0.0-ap"
QUICK_AP = {**SHORT_TRIAL, "_WIFI_JOIN_TIMEOUT_MS": 2000, "_FALLBACK_AP_MS": 10000}
"""A quick trial, Wi-Fi joins given up after 2 s and the access point opened after 10 s offline (the board: 20 s
and 5 minutes): seconds, not minutes."""
NETWORKS = {"school-old": "old-key-1234", "school-new": "new-key-5678"}


@pytest.fixture(scope="module")
def fw(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("ap-fw")
    src = versioned_sources(root / "src", VERSION, None, QUICK_AP)
    build(root / "build", src)
    return {"stubs": build_for_host(root / "host")[1], f"{VERSION}-build": root / "build"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def ap_board(fw, creds, broker, tmp_path, monkeypatch) -> Iterator[tuple[Board, int]]:
    """A node configured for school-old with a key that network refuses (its key was changed); the board's fake
    access point on a free local port."""
    port = free_port()
    monkeypatch.setenv("WSNAV_AP_PORT", str(port))
    b = Board(fw, VERSION, creds, broker, tmp_path, NETWORKS)
    config = json.loads((b.fs / "config.json").read_text())
    config["wifi"] = {"ssid": "school-old", "password": "stale-key-0000"}
    (b.fs / "config.json").write_text(json.dumps(config))
    b.unix.power_on()
    yield b, port
    b.unix.close()


def request(port: int, method: str, path: str = "/", body: bytes | None = None, headers=None):
    """(status, text) of one request, as a browser's form sends it."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        hdrs = {"Content-Type": "application/x-www-form-urlencoded"} if body is not None else {}
        conn.request(method, path, body=body, headers={**hdrs, **(headers or {})})
        resp = conn.getresponse()
        return resp.status, resp.read().decode()
    finally:
        conn.close()


def raw(port: int, data: bytes) -> str:
    """What the node answers to bytes no HTTP client would send (it may answer and close before it has read them
    all: then the rest of the sending fails, and the answer is still there to read)."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        try:
            s.sendall(data)
            s.shutdown(socket.SHUT_WR)
        except OSError:
            pass
        out = b""
        while chunk := s.recv(4096):
            out += chunk
    return out.decode(errors="replace")


def fallback_ap_cli(creds: Path) -> subprocess.CompletedProcess[str]:
    cmd = [
        *(sys.executable, "-m", "wsnav.cli", "firmware", "fallback-ap"),
        *("--credentials", str(creds / "operator.json"), "--nodes", NODE),
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=REPO)


def test_a_node_without_a_known_network_takes_new_settings_from_its_access_point_page(
    ap_board, creds, infos
) -> None:
    """No known network for 10 s (QUICK_AP): the node resets into its access point (named for it, WPA2 with its per-node key,
    which the operator's command prints), serves the form, refuses bad requests with a 400 and keeps serving,
    then tries the posted network as a configuration trial: online with it and confirmed, config.json kept."""
    b, port = ap_board
    b.wait_serial("ap: open " + fallback_ap_ssid(NODE), OTA_WAIT)
    assert b.serial().index("wifi join timed out") < b.serial().index("ap: open")  # the app ran first
    name, key, auth = (b.unix.pins / "ap").read_text().split()
    assert (name, key, auth) == (fallback_ap_ssid(NODE), fallback_ap_key(node_key(creds)), "3")  # 3: WPA2-PSK
    cli = fallback_ap_cli(creds)
    assert cli.returncode == 0 and f"{NODE}  {name}  {key}" in cli.stdout, (cli.stdout, cli.stderr)
    before = (b.fs / "config.json").read_bytes()

    status, page = request(port, "GET")
    assert status == 200 and "<form method=post>" in page and "name=ssid" in page and "name=key" in page, page
    assert request(port, "GET", "/generate_204")[0] == 404

    bad = {
        b"ssid=school-new": "two fields",
        b"ssid=school-new&key=new-key-5678&admin=1": "two fields",
        b"ssid[a][b]=school-new&key=new-key-5678": "two fields",
        b"ssid=school-new&ssid=x&key=new-key-5678": "two fields",
        b"ssid=%zz&key=new-key-5678": "escape",
        b"ssid=&key=new-key-5678": "SSID",
        b"ssid=" + b"x" * 33 + b"&key=new-key-5678": "SSID",
        b"ssid=school-new&key=short": "key",
        b"ssid=school-new&key=%00%01%02%03%04%05%06%07": "key",
        b"\x00\xff" * 40: "two fields",
    }
    for body, why in bad.items():
        status, text = request(port, "POST", body=body)
        assert status == 400 and why in text and text.count("\n") == 1, (body, status, text)
    status, text = request(port, "POST", body=b"x" * 100_000)
    assert status == 400 and "body too long" in text
    assert "400" in raw(port, b"POST / HTTP/1.1\r\nContent-Length: twelve\r\n\r\nssid=a&key=")
    assert "head too long" in raw(port, b"GET / HTTP/1.1\r\n" + b"X-A: " + b"a" * 5000 + b"\r\n\r\n")
    assert "400" in raw(port, b"\r\n\r\n")
    assert "cut short" in raw(port, b"POST / HTTP/1.1\r\nContent-Length: 30\r\n\r\nssid=sch")
    assert request(port, "PUT", body=b"ssid=a&key=")[0] == 405
    assert request(port, "GET")[0] == 200  # still serving
    assert (b.fs / "config.json").read_bytes() == before

    status, text = request(port, "POST", body=b"ssid=school-new&key=new-key-5678")
    assert status == 200 and "Trying" in text
    b.wait_confirmed(OTA_WAIT)
    after = json.loads((b.fs / "config.json").read_text())
    assert after["wifi"] == {"ssid": "school-new", "password": "new-key-5678"}
    assert {k: v for k, v in after.items() if k != "wifi"} == {
        k: v for k, v in json.loads(before).items() if k != "wifi"
    }
    assert not (b.fs / "wifi.fallback").exists()
    assert infos.wait(lambda i: i.fw == VERSION and not i.trial).error is None
    assert "new-key-5678" not in b.serial() and key not in b.serial()
    assert "MemoryError" not in b.serial() and "Traceback" not in b.serial()


def test_settings_that_do_not_get_the_node_online_bring_the_access_point_back(ap_board, creds) -> None:
    """A key the network refuses, posted on the page: the trial is not online within its bound, the old
    configuration comes back, and the access point opens again for another try."""
    b, port = ap_board
    b.wait_serial("ap: open", OTA_WAIT)
    before = (b.fs / "config.json").read_bytes()
    status, _text = request(port, "POST", body=b"ssid=school-new&key=wrong-key-0000")
    assert status == 200
    b.wait_serial("ota: rollback", OTA_WAIT)
    deadline = time.monotonic() + OTA_WAIT
    while b.serial().count("ap: open") < 2:
        assert time.monotonic() < deadline, b.serial()[-3000:]
        time.sleep(0.1)
    assert (b.fs / "config.json").read_bytes() == before
    assert request(port, "GET")[0] == 200


def test_a_node_told_not_to_open_its_access_point_keeps_it_closed(
    fw, creds, broker, tmp_path, monkeypatch
) -> None:
    """config.json's wifi.fallback_ap false: past the same bound the node resets, keeps its access point closed
    (nothing listens on its port) and runs the app again, still trying its network."""
    port = free_port()
    monkeypatch.setenv("WSNAV_AP_PORT", str(port))
    b = Board(fw, VERSION, creds, broker, tmp_path, NETWORKS)
    config = json.loads((b.fs / "config.json").read_text())
    config["wifi"] = {"ssid": "school-old", "password": "stale-key-0000", "fallback_ap": False}
    (b.fs / "config.json").write_text(json.dumps(config))
    b.unix.power_on()
    try:
        b.wait_serial("ap: off (wifi.fallback_ap)", OTA_WAIT)
        deadline = time.monotonic() + OTA_WAIT
        while "wifi join timed out" not in b.serial().split("ap: off")[1]:  # the app again
            assert time.monotonic() < deadline, b.serial()[-3000:]
            time.sleep(0.1)
        assert not (b.unix.pins / "ap").exists()
        with pytest.raises(ConnectionRefusedError):
            socket.create_connection(("127.0.0.1", port), timeout=5).close()
    finally:
        b.unix.close()


@pytest.mark.parametrize(
    ("nodes", "key_file", "message"),
    [
        ("n1", False, "cannot read the site's update key"),
        ("n1,a/b", True, "'a/b' is not a node id"),
        (",", True, "give node ids, each once"),
    ],
)
def test_fallback_ap_command_refuses_bad_arguments_in_one_line(
    tmp_path: Path, nodes: str, key_file: bool, message: str
) -> None:
    """`wsnav firmware fallback-ap` without the site's update key, or with a bad node id: one line, exit 2, no key
    printed for anyone."""
    if key_file:
        (tmp_path / "update.key").write_text("ab" * 32)
    cmd = [sys.executable, "-m", "wsnav.cli", "firmware", "fallback-ap"]
    cmd += ["--credentials", str(tmp_path / "operator.json"), "--nodes", nodes]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=REPO)
    assert proc.returncode == 2 and proc.stdout == "", (proc.stdout, proc.stderr)
    assert message in proc.stderr and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
