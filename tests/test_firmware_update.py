"""Updating a running node (`wsnav firmware deploy`'s logic, firmware/deploy.py) against a board whose watchdog
behaves as the ESP8266's: once started it cannot be stopped, nothing feeds it once the application is stopped,
and 3.2 s after the last feed it resets the board (firmware/unix_board.py: the MicroPython unix port running the
real firmware, main.py and maintenance code; only the serial line between host and board is simulated, and
the real mpremote talks to it through a pseudo-terminal).

The node runs with its broker away (a closed port): its loop still runs and feeds the watchdog.
"""

from __future__ import annotations

import hashlib
import json
import os
import pty
import shutil
import socket
import threading
import time
import tty
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from wsnav.firmware.board import BoardError, MpremoteBoard
from wsnav.firmware.build import build
from wsnav.firmware.deploy import Deployer, DeployError, firmware_files, module_names
from wsnav.firmware.testing import (
    DEVICE,
    SiteBroker,
    build_for_host,
    fake_flash,
    write_credentials,
)
from wsnav.firmware.unix_board import CHUNK, WDT_TIMEOUT_S, UnixBoard

WAIT = 60.0


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def node_config(path: Path, heartbeat_s: int) -> Path:
    data = {
        "username": "n1",
        "password": "p" * 24,
        "role": "node",
        "site": "school",
        "broker": {"host": "127.0.0.1", "port": closed_port()},
        "node": "n1",
        "zone": "z1",
        "sensor": {"type": "pir", "pin": 5},
        "heartbeat_s": heartbeat_s,
        "on_delay_ms": 500,
        "off_delay_ms": 3000,
        "wifi": {"ssid": "", "password": ""},
    }
    path.write_text(json.dumps(data))
    return path


@pytest.fixture(scope="module")
def builds(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """(new build, old build, host stubs): the old one is the same firmware with one more constant per file,
    so every file differs and both run."""
    root = tmp_path_factory.mktemp("fw")
    new, stubs = build_for_host(root / "new")
    src = root / "old-src"
    src.mkdir()
    for py in DEVICE.glob("*.py"):
        (src / py.name).write_text(py.read_text() + "\n_OLD = 1\n")
    build(root / "old", src)
    return new, root / "old", stubs


def wait_until(check: Callable[[], bool], timeout_s: float = WAIT) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(0.05)
    return False


class FlakyLine(UnixBoard):
    """The USB cable pulled halfway through copying the `fail_at`-th file (0: never)."""

    fail_at = 0
    puts = 0

    def put(self, local: Path, remote: str) -> None:
        self.puts += 1
        if self.puts != self.fail_at:
            super().put(local, remote)
            return
        data = local.read_bytes()
        boot = self._session()
        self._exec(boot, f"f=open({remote!r},'wb')\nw=f.write")
        for i in range(0, len(data) // 2, CHUNK):
            self._exec(boot, f"w({data[i : i + CHUNK]!r})")
        raise BoardError("cable pulled")


@pytest.fixture
def board(builds: tuple[Path, Path, Path], tmp_path: Path) -> Iterator[FlakyLine]:
    """A board running the old firmware and config, its watchdog started and fed by the node's loop."""
    _new, old, stubs = builds
    fs = tmp_path / "fs"
    fs.mkdir()
    for name, path in firmware_files(old, node_config(tmp_path / "old.json", 5)).items():
        shutil.copyfile(path, fs / name)
    b = FlakyLine(fs, stubs, tmp_path / "serial.log", tmp_path / "pins")
    (tmp_path / "pins").mkdir()
    b.power_on()
    try:
        assert wait_until(lambda: b.wdt_fed_within(0.5)), (tmp_path / "serial.log").read_text()
        yield b
    finally:
        b.close()


@pytest.fixture
def new_files(builds: tuple[Path, Path, Path], tmp_path: Path) -> dict[str, Path]:
    return firmware_files(builds[0], node_config(tmp_path / "new.json", 6))


def test_deploy_over_a_running_node_completes_and_every_hash_matches(
    board: FlakyLine, new_files: dict[str, Path]
) -> None:
    log: list[str] = []
    start = time.monotonic()
    copied = Deployer(board, log.append).deploy(new_files)
    # Over the serial line a deploy outlasts the watchdog several times: maintenance mode fed it throughout.
    assert time.monotonic() - start > 2 * WDT_TIMEOUT_S
    assert sorted(copied) == sorted(new_files)  # the old firmware differed in every file
    assert {name: sha(board.fs / name) for name in new_files} == {n: sha(p) for n, p in new_files.items()}
    assert not list(board.fs.glob("*.tmp")) and not list(board.fs.glob("*.py.tmp"))
    assert {p.name for p in board.fs.iterdir()} == set(new_files)
    # The only reset is the deploy's own: the watchdog never fired while files were copied.
    assert wait_until(lambda: board.resets == ["reset"]), board.resets
    assert wait_until(lambda: board.wdt_fed_within(0.5))  # the new firmware runs and feeds its watchdog
    assert board.resets == ["reset"]
    assert any("verified" in line for line in log), log


def test_mpremote_updates_a_running_node_over_a_serial_line(
    board: FlakyLine, new_files: dict[str, Path]
) -> None:
    """The real transport: `wsnav firmware deploy`'s MpremoteBoard, one mpremote session per step, against the
    board behind a pseudo-terminal speaking the raw REPL."""
    copied = Deployer(MpremoteBoard(board.serve_pty())).deploy(new_files)
    assert sorted(copied) == sorted(new_files)
    assert {name: sha(board.fs / name) for name in new_files} == {n: sha(p) for n, p in new_files.items()}
    assert wait_until(lambda: board.resets == ["reset"]), board.resets
    assert wait_until(lambda: board.wdt_fed_within(0.5))


def test_an_interrupted_deploy_leaves_whole_files_and_a_rerun_finishes(
    board: FlakyLine, new_files: dict[str, Path], builds: tuple[Path, Path, Path]
) -> None:
    old = {name: sha(board.fs / name) for name in new_files}
    new = {name: sha(path) for name, path in new_files.items()}
    board.fail_at = len(new_files) // 2
    with pytest.raises(DeployError, match="cable pulled"):
        Deployer(board, hold_ms=4000).deploy(new_files)
    # Under its real name every file is whole, old or new; the half-copied one is only a .tmp.
    for name in new_files:
        assert sha(board.fs / name) in (old[name], new[name]), name
    half = list(board.fs.glob("*.tmp"))
    assert len(half) == 1 and half[0].stat().st_size < new_files[half[0].name[: -len(".tmp")]].stat().st_size
    done = [n for n in new_files if sha(board.fs / n) == new[n]]
    assert 0 < len(done) < len(new_files)
    # Nobody keeps the board in maintenance any more: the watchdog resets it, and the node runs again.
    assert wait_until(lambda: board.resets == ["watchdog"], 4 + WDT_TIMEOUT_S + WAIT), board.resets
    assert wait_until(lambda: board.wdt_fed_within(0.5))
    board.fail_at = 0
    copied = Deployer(board).deploy(new_files)
    assert sorted(copied) == sorted(set(new_files) - set(done))
    assert {name: sha(board.fs / name) for name in new_files} == new
    assert not list(board.fs.glob("*.tmp"))
    assert wait_until(lambda: board.resets == ["watchdog", "reset"]), board.resets


def test_a_node_stopped_at_the_repl_without_maintenance_is_reset_by_its_watchdog(board: FlakyLine) -> None:
    board.interrupt()  # Ctrl-C: the node's loop stops, the REPL answers, nothing feeds the watchdog
    stopped = time.monotonic()
    assert wait_until(lambda: board.resets == ["watchdog"]), board.resets
    assert time.monotonic() - stopped >= WDT_TIMEOUT_S - 0.5
    assert wait_until(lambda: board.wdt_fed_within(0.5))  # booted into the node again


def test_the_first_deploy_on_a_fresh_board(
    builds: tuple[Path, Path, Path], new_files: dict[str, Path], tmp_path: Path
) -> None:
    """MicroPython only, nothing on the board: no watchdog runs until maintenance mode starts one (and feeds
    it); after the reset the node starts."""
    fs = tmp_path / "fresh"
    fs.mkdir()
    (tmp_path / "pins").mkdir()
    board = UnixBoard(fs, builds[2], tmp_path / "fresh.log", tmp_path / "pins")
    board.power_on()
    try:
        assert not board.wdt_fed_within(60)
        copied = Deployer(board).deploy(new_files)
        assert sorted(copied) == sorted(new_files)
        assert {name: sha(fs / name) for name in new_files} == {n: sha(p) for n, p in new_files.items()}
        assert wait_until(lambda: board.resets == ["reset"]), board.resets
        assert wait_until(lambda: board.wdt_fed_within(0.5))  # the node runs and feeds its watchdog
    finally:
        board.close()


@pytest.mark.parametrize("vfs", ["VfsFat", "VfsLfs2"])
def test_deploy_refuses_a_board_whose_flash_is_fat_before_touching_anything(
    board: FlakyLine, new_files: dict[str, Path], vfs: str
) -> None:
    """The board's flash as MicroPython's VfsFat or VfsLfs2 formats it (testing.fake_flash, read by `flashbdev`):
    on FAT, renaming files in is not power-cut safe, so the deploy stops with one line and copies nothing; on
    littlefs it goes ahead."""
    fake_flash(board.fs, vfs)
    if vfs == "VfsFat":
        with pytest.raises(DeployError, match=r"^board: its flash is FAT, .* `wsnav firmware flash`"):
            Deployer(board).deploy(new_files)
        assert board.puts == 0
        assert {name: sha(board.fs / name) for name in new_files} != {n: sha(p) for n, p in new_files.items()}
    else:
        assert sorted(Deployer(board).deploy(new_files)) == sorted(new_files)


def test_deploy_refuses_a_board_that_left_maintenance(board: FlakyLine, new_files: dict[str, Path]) -> None:
    """A board reset between two steps is no longer in maintenance: the deploy stops with one line."""
    deployer = Deployer(board)
    deployer.enter()
    board.reset()
    assert wait_until(lambda: board.resets == ["reset"]), board.resets
    with pytest.raises(DeployError, match="left maintenance mode"):
        deployer.hashes(sorted(new_files))
    assert module_names()  # the firmware's module list is what the deploy copies


@pytest.mark.slow
@pytest.mark.parametrize("password_ok", [True, False], ids=["right-password", "wrong-password"])
def test_deploy_waits_until_the_node_reaches_its_broker_or_says_why_not(
    board: FlakyLine, builds: tuple[Path, Path, Path], tmp_path: Path, password_ok: bool
) -> None:
    """After the reset the deploy reads the board's console: with the site's credentials the node reaches the
    project's broker and the deploy says so; with a password the broker refuses, the deploy fails with the
    node's own words (the refused CONNACK) instead of leaving the installer to find out at the robot."""
    site = Path(__file__).resolve().parent.parent / "sites" / "school"
    creds = tmp_path / "creds"
    write_credentials(site, creds)
    broker = SiteBroker(site, creds, tmp_path / "broker-data")
    broker.start()
    try:
        data = json.loads((creds / "n1.json").read_text())
        data["broker"] = {"host": broker.host, "port": broker.port}
        if not password_ok:
            data["password"] = "x" * 24
        cfg = tmp_path / "site.json"
        cfg.write_text(json.dumps(data))
        deployer = Deployer(board)
        deployer.deploy(firmware_files(builds[0], cfg))
        if password_ok:
            assert 0 < deployer.wait_online(60) < 60
        else:
            with pytest.raises(DeployError, match=r"did not reach its broker within 20 s .*refused"):
                deployer.wait_online(20)
    finally:
        broker.kill()


@pytest.mark.parametrize(
    ("console", "online"),
    [
        (b"\x00\xffets Jan  8 2013\r\nmqtt down: [Errno 113] EHOSTUNREACH\r\nmqtt up 1\r\n", True),
        (b"mqtt down: connection refused, code 5\r\n\x1b\x00\r\n", False),
    ],
    ids=["online", "refused"],
)
def test_deploy_reads_the_real_serial_console_for_the_nodes_word(console: bytes, online: bool) -> None:
    """`MpremoteBoard.console` (pyserial on the port, as on a USB board) over a pseudo-terminal: the deploy takes
    `mqtt up` as the node online; otherwise it reports the last readable line, not boot noise or binary."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    threading.Timer(0.3, os.write, (master, console)).start()
    deployer = Deployer(MpremoteBoard(os.ttyname(slave)))
    try:
        if online:
            assert deployer.wait_online(10) < 10
        else:
            with pytest.raises(DeployError, match="last words: 'mqtt down: connection refused, code 5'"):
                deployer.wait_online(2)
    finally:
        os.close(master)
        os.close(slave)


@dataclass
class OldMicroPython:
    """The board as a MicroPython older than 1.19 would answer (its .mpy format is 5): what cannot be run here."""

    board: FlakyLine

    def run(self, code: str) -> str:
        return self.board.run(code).replace("wsnav-mpy 6", "wsnav-mpy 5")

    def put(self, local: Path, remote: str) -> None:
        self.board.put(local, remote)

    def reset(self) -> None:
        self.board.reset()

    def console(self, timeout_s: float) -> Iterator[str]:
        return self.board.console(timeout_s)


def test_deploy_refuses_a_micropython_that_cannot_load_our_files_before_touching_anything(
    board: FlakyLine, new_files: dict[str, Path]
) -> None:
    with pytest.raises(DeployError, match=r"loads \.mpy version 5, ours are version 6"):
        Deployer(OldMicroPython(board)).deploy(new_files)
    assert board.puts == 0
    assert Deployer(board).deploy(new_files), "the real unix port (mpy 6) passes the same check"
