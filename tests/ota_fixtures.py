"""What the over-the-air tests share (tests/test_firmware_ota.py, tests/test_firmware_password.py): the node on
the MicroPython unix port with its real config (`Board`), the site's credentials and broker and the node's `info` (fixtures `creds`, `broker`, `infos`; also the fallback access point's tests), the operator's view of its `info` (`Infos`), a transfer
served from the test's process (`follow`), and main.py itself on the board's heap (`update_mode_then_trial`)."""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from tests.conftest import REPO
from tests.firmware_fixtures import Subscriber, info_of
from wsnav.firmware.deploy import firmware_files
from wsnav.firmware.ota import NodeTransfer
from wsnav.firmware.testing import (
    HEAP,
    NodeProcess,
    SiteBroker,
    micropython_env,
    micropython_exe,
    write_credentials,
)
from wsnav.firmware.unix_board import UnixBoard
from wsnav.runtime.mqtt_bus import MqttBus
from wsnav.schemas.credentials import Credentials, NodeConfig
from wsnav.schemas.messages import NodeInfo

SITE_DIR = REPO / "sites" / "school"
SITE, NODE = "school", "n1"
QUICK = "1.0.0-quick"
"""The firmware with a trial of seconds (testing.SHORT_TRIAL), for the configuration tests."""
WAIT = 120.0


class Infos:
    """The node's `nodes/<node>/info` as the operator's subscriber (tests/firmware_fixtures.py) sees it, each payload
    checked against NodeInfo's bytes."""

    def __init__(self, broker: SiteBroker, creds: Path) -> None:
        self.subscriber = Subscriber(broker, creds)

    def wait(self, pred: Callable[[NodeInfo], bool], timeout: float = WAIT) -> NodeInfo:
        info = info_of(self.subscriber.wait(lambda m: (i := info_of(m)) is not None and pred(i), timeout))
        assert info is not None
        return info

    def close(self) -> None:
        self.subscriber.close()


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

    def wait_serial(self, text: str, timeout: float = WAIT) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.serial():
            assert time.monotonic() < deadline, f"no {text!r} on the serial line:\n{self.serial()[-3000:]}"
            time.sleep(0.05)

    def wait_confirmed(self, timeout: float = WAIT) -> None:
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


def follow(broker: SiteBroker, creds: Path, server_of: Callable[[MqttBus], NodeTransfer]) -> list[str]:
    """A firmware.ota server (`server_of` the operator's connection) in this process until its node is done;
    the failures. No command: the test wrote the node's ota.json."""
    op = Credentials.model_validate_json((creds / "operator.json").read_text())
    bus = MqttBus(
        broker.host, broker.port, client_id="ota-test", username=op.username, password=op.password
    ).connect(30)
    try:
        server = server_of(bus)
        server.subscribe()
        return server.run(WAIT)
    finally:
        bus.close()


def main_on_the_boards_heap(board: Board, stubs: Path, tmp_path: Path) -> tuple[list[str], dict[str, str]]:
    """(command, environment) of main.py itself on `micropython -X heapsize=HEAP` in the board's folder, where
    machine.reset ends the process (exit 75) as the ROM's ends a boot."""
    boot = "import machine, sys\nmachine.reset = lambda: sys.exit(75)\nimport main"
    cmd = [micropython_exe(), "-X", f"heapsize={HEAP}", "-c", boot]
    return cmd, micropython_env(board.fs, stubs, tmp_path / "pins")


def update_mode_then_trial(board: Board, stubs: Path, tmp_path: Path) -> NodeProcess:
    """main.py on the board's heap from an ota.json in update mode: asserted to fetch and swap without running
    out of heap and to reset; then the trial boot, running (the caller stops it)."""
    cmd, env = main_on_the_boards_heap(board, stubs, tmp_path)
    with (tmp_path / "update.log").open("wb") as log:
        first = subprocess.run(cmd, cwd=board.fs, env=env, stdout=log, stderr=subprocess.STDOUT, timeout=WAIT)
    out = (tmp_path / "update.log").read_text()
    assert first.returncode == 75 and "ota: swapped" in out and "MemoryError" not in out, out
    return NodeProcess(cmd, env, tmp_path / "trial.log", cwd=board.fs)


NETWORKS = {"school-old": "old-key-1234", "school-new": "new-key-5678"}
"""The site's Wi-Fi networks in the configuration tests: the node starts on the first."""


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


@pytest.fixture
def infos(broker: SiteBroker, creds: Path) -> Iterator[Infos]:
    i = Infos(broker, creds)
    yield i
    i.close()


def node_key(creds: Path) -> str:
    """NODE's update key, as `wsnav broker credentials` wrote it into its config."""
    key = NodeConfig.model_validate_json((creds / f"{NODE}.json").read_text()).update_key
    assert key is not None
    return key
