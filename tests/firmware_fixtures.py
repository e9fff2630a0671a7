"""Shared by the firmware's tests: the operator's subscriber that collects what a node on the MicroPython unix port
publishes through the project's broker, and the checks of each payload's exact bytes against the contract; the
site's credentials, `wsnav broker run` with them and a node on `unix_board.UnixBoard` (the OTA and fallback access
point tests)."""

from __future__ import annotations

import json
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from tests.conftest import REPO
from wsnav.firmware.deploy import firmware_files
from wsnav.firmware.testing import SiteBroker, write_credentials
from wsnav.firmware.unix_board import UnixBoard
from wsnav.schemas import topics
from wsnav.schemas.credentials import Credentials, NodeConfig
from wsnav.schemas.messages import NodeInfo, NodeStatus, ZoneState, parse_payload

SITE_DIR = REPO / "sites" / "school"
SITE = "school"
NODE, ZONE, PIN = "n1", "z1", 5
STATE_TOPIC = topics.zone_state(SITE, ZONE, NODE)
STATUS_TOPIC = topics.node_status(SITE, NODE)
INFO_TOPIC = topics.node_info(SITE, NODE)
WAIT = 60.0
OTA_WAIT = 120.0
"""A board's wait through resets, update mode and a trial (OTA, fallback access point)."""


@dataclass
class Msg:
    topic: str
    payload: bytes
    retain: bool


class Subscriber:
    """The operator's paho client over TCP, subscribed to the whole site; collects every message."""

    def __init__(self, broker: SiteBroker, creds: Path) -> None:
        op = Credentials.model_validate_json((creds / "operator.json").read_text())
        self.messages: list[Msg] = []
        self._lock = threading.Lock()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"fwtest-{time.monotonic_ns()}")
        self.client.username_pw_set(op.username, op.password)
        self.client.on_message = self._on_message
        subscribed = threading.Event()
        self.client.on_subscribe = lambda *_a: subscribed.set()
        self.client.connect(broker.host, broker.port)
        self.client.loop_start()
        self.client.subscribe(f"wsn/{SITE}/#", qos=1)
        assert subscribed.wait(WAIT), "subscription not acknowledged"

    def _on_message(self, _c: object, _u: object, msg: mqtt.MQTTMessage) -> None:
        with self._lock:
            self.messages.append(Msg(msg.topic, bytes(msg.payload), bool(msg.retain)))

    def snapshot(self) -> list[Msg]:
        with self._lock:
            return list(self.messages)

    def wait(self, pred: Callable[[Msg], bool], timeout: float = WAIT, after: int = 0) -> Msg:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for m in self.snapshot()[after:]:
                if pred(m):
                    return m
            time.sleep(0.05)
        raise AssertionError(f"no matching message within {timeout} s; got {self.snapshot()[after:]}")

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def state_of(m: Msg) -> ZoneState | None:
    """The validated zone state, checking the exact bytes the firmware sent against the model's own."""
    if m.topic != STATE_TOPIC or not m.payload:
        return None
    zs = parse_payload(ZoneState, m.payload)
    assert zs.to_payload() == m.payload, m.payload
    return zs


def info_of(m: Msg) -> NodeInfo | None:
    """The node's validated diagnostics, its exact bytes checked against the model's own serialisation."""
    if m.topic != INFO_TOPIC or not m.payload:
        return None
    info = parse_payload(NodeInfo, m.payload)
    assert info.to_payload() == m.payload, m.payload
    return info


def is_info(pred: Callable[[NodeInfo], bool] = lambda _i: True) -> Callable[[Msg], bool]:
    return lambda m: (i := info_of(m)) is not None and pred(i)


def is_state(value: str) -> Callable[[Msg], bool]:
    return lambda m: (s := state_of(m)) is not None and s.state == value


def is_status(value: str) -> Callable[[Msg], bool]:
    def pred(m: Msg) -> bool:
        if m.topic != STATUS_TOPIC:
            return False
        st = parse_payload(NodeStatus, m.payload)
        assert st.to_payload() == m.payload, m.payload
        return st.status == value

    return pred


@pytest.fixture(scope="module")
def creds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("creds")
    write_credentials(SITE_DIR, out)
    return out


@pytest.fixture
def broker(creds: Path, tmp_path: Path) -> Iterator[SiteBroker]:
    b = SiteBroker(SITE_DIR, creds, tmp_path / "broker-data")
    b.start()
    yield b
    b.kill()


class Infos:
    """The node's `nodes/<node>/info` as the operator's subscriber (tests/firmware_fixtures.py) sees it, each payload
    checked against NodeInfo's bytes."""

    def __init__(self, broker: SiteBroker, creds: Path) -> None:
        self.subscriber = Subscriber(broker, creds)

    def wait(self, pred: Callable[[NodeInfo], bool], timeout: float = OTA_WAIT) -> NodeInfo:
        info = info_of(self.subscriber.wait(lambda m: (i := info_of(m)) is not None and pred(i), timeout))
        assert info is not None
        return info

    def close(self) -> None:
        self.subscriber.close()


@pytest.fixture
def infos(broker: SiteBroker, creds: Path) -> Iterator[Infos]:
    i = Infos(broker, creds)
    yield i
    i.close()


class Board:
    """The node on the unix port, its filesystem `fs` holding `version`'s build and its real config."""

    def __init__(
        self,
        fw: dict[str, Path],
        version: str,
        creds: Path,
        broker: SiteBroker,
        tmp: Path,
        networks: dict[str, str] | None = None,
    ) -> None:
        """`networks`: the Wi-Fi networks in reach, SSID -> key (the fake radio's, host_stubs/network.py); the node
        is configured for the first. None: its config leaves Wi-Fi to what the board joined before."""
        data = json.loads((creds / f"{NODE}.json").read_text())
        data["broker"] = {"host": broker.host, "port": broker.port}
        data["sensor"]["warmup_s"] = 0
        (tmp / "pins").mkdir()
        for ssid, key in (networks or {}).items():
            (tmp / "pins" / f"wifi_{ssid}").write_text(key)
            data["wifi"] = data["wifi"] if data["wifi"]["ssid"] else {"ssid": ssid, "password": key}
        config = tmp / "config.json"
        config.write_text(NodeConfig.model_validate(data).model_dump_json())
        self.fs = tmp / "fs"
        self.fs.mkdir()
        for name, path in firmware_files(fw[f"{version}-build"], config).items():
            shutil.copyfile(path, self.fs / name)
        self.log = tmp / "serial.log"
        self.unix = UnixBoard(self.fs, fw["stubs"], self.log, tmp / "pins")

    def serial(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def wait_serial(self, text: str, timeout: float = OTA_WAIT) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.serial():
            assert time.monotonic() < deadline, f"no {text!r} on the serial line:\n{self.serial()[-3000:]}"
            time.sleep(0.05)

    def wait_confirmed(self, timeout: float = OTA_WAIT) -> None:
        """Until the app's first connect marked the update good (`ota.json` renamed `ota.ok`: app.py)."""
        deadline = time.monotonic() + timeout
        while not (self.fs / "ota.ok").exists():
            assert time.monotonic() < deadline, f"no ota.ok; serial line:\n{self.serial()[-3000:]}"
            time.sleep(0.05)

    def power_cut(self) -> None:
        """SIGKILL mid-run: nothing flushed, nothing closed; the board supervisor powers it up again."""
        boot = self.unix._boot
        assert boot is not None
        boot.proc.kill()

    def leftovers(self) -> list[str]:
        """What an update leaves on the board's flash: .tmp and .bak files, its state."""
        return sorted(
            p.name
            for p in self.fs.iterdir()
            if p.suffix in (".tmp", ".bak") or p.name in ("ota.json", "ota.ok")
        )

    def unfinished(self) -> list[str]:
        """Leftovers but for a confirmed update's backups, which stay until the next boot removes them."""
        return [n for n in self.leftovers() if not n.endswith(".bak") and n != "ota.ok"]


def node_key(creds: Path) -> str:
    """NODE's update key, as `wsnav broker credentials` wrote it into its config."""
    key = NodeConfig.model_validate_json((creds / f"{NODE}.json").read_text()).update_key
    assert key is not None
    return key
