"""`wsnav firmware deploy` and `wsnav firmware flash`.

Deploy updates a node safely, whether it runs or not (docs/firmware-esp8266.md, "Updating a node"):
1. maintenance mode: the node's loop is stopped (Ctrl-C) and `device/maintenance.py` is run at its REPL, which
   keeps feeding the ESP8266's watchdog (it cannot be stopped) for as long as the host keeps asking; a board
   whose MicroPython cannot load our files, or whose flash is FAT (`device/fscheck.py`), is refused there;
2. stale `.py` copies of the modules are deleted (MicroPython imports `app.py` before `app.mpy`, so a forgotten
   source file would silently shadow the new build), and leftover `.tmp` files of an interrupted deploy;
3. each file whose sha256 on the board differs from the host's is copied under a temporary name, its hash
   checked on the board, then renamed over the old one: a file under its real name is always whole, old or new;
4. every file's hash is checked on the board once more, then the board is reset into the new firmware;
5. the board's serial console is read until the node says it reached the broker (`mqtt up`), so an installer on
   the ladder learns there and then that the node joined (or, from its last words, why not).
An interrupted deploy (cable pulled, host killed) leaves the old or new version of each file, and the board,
no longer kept in maintenance, resets into its application a few minutes later; running deploy again copies
what still differs and finishes. The board is reached through `firmware.board.Board` (mpremote for real).
Flash erases the ESP8266 and writes a MicroPython image at offset 0 (what micropython.org documents for ESP8266).
"""

from __future__ import annotations

import hashlib
import shlex
import time
from collections.abc import Callable
from pathlib import Path

from pydantic import ValidationError

from wsnav.firmware.board import Board, BoardError, MpremoteBoard
from wsnav.firmware.build import DEVICE, REPL_ONLY, SOURCE_ONLY, tool_path
from wsnav.firmware.ota import FAT_ADVICE
from wsnav.schemas.credentials import NodeConfig

MAINTENANCE = DEVICE / "maintenance.py"
FSCHECK = DEVICE / "fscheck.py"
HOLD_MS = 300_000
"""How long the board stays in maintenance after the host's last command (then its watchdog resets it)."""
FLASH_BAUD = 460800
"""Fast and reliable on CH340/CP2102 USB-serial bridges; esptool falls back to nothing, so lower it if it fails."""


MPY_VERSION = 6
"""The .mpy format mpy-cross writes (MicroPython 1.19 and later read it); a board reports its own in
sys.implementation._mpy."""
ONLINE_S = 90.0
"""How long after the reset the deploy waits for the node to reach its broker: a boot, a Wi-Fi join (up to the
node's 20 s join timeout, twice) and a connect with its backoff."""
ONLINE_LINE = "mqtt up"
"""What the node prints on its console when the broker accepted it (app.py)."""
ESP8266_IRAM = (0x40100000, 0x40140000)
"""Where an ESP8266 image's entry point lies (its instruction RAM); an ESP32's lies in 0x40080000..0x400A0000."""
FLASH_MODES = ("keep", "qio", "qout", "dio", "dout")
"""esptool's --flash-mode; `keep` leaves the image's; `dout` is the one every ESP8266 module boots with (ESP-01S,
some 16 MB boards)."""


class DeployError(Exception):
    """A bad config or image file, or a missing tool; one line."""


def check_config(path: Path, keep_wifi: bool = False) -> NodeConfig:
    """The node config must be a valid NodeConfig with a broker host: the board cannot tell us otherwise."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise DeployError(f"{path}: cannot read config: {exc.strerror}") from None
    try:
        cfg = NodeConfig.model_validate_json(text)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ())) or "config"
        raise DeployError(f"{path}: {where}: {first.get('msg', 'invalid')}") from None
    if not cfg.broker.host:
        raise DeployError(f"{path}: broker.host is empty: set the broker's address before deploying")
    if not cfg.wifi.ssid and not keep_wifi:
        raise DeployError(
            f"{path}: wifi.ssid is empty: a new board could never join (`wsnav broker credentials --wifi-ssid "
            "NAME --wifi-password PASS` writes it into every node's config; --keep-wifi keeps the network a "
            "board already joined)"
        )
    return cfg


def module_names(source: Path = DEVICE) -> list[str]:
    """Module names that become .mpy files (everything in device/ but main.py, boot.py, maintenance.py)."""
    return sorted(p.stem for p in source.glob("*.py") if p.name not in SOURCE_ONLY + REPL_ONLY)


def firmware_files(build_dir: Path, config: Path, source: Path = DEVICE) -> dict[str, Path]:
    """What goes on the board, by its name there: the .mpy modules, main.py, boot.py and config.json."""
    files = {n + ".mpy": build_dir / (n + ".mpy") for n in module_names(source)}
    files.update({n: build_dir / n for n in SOURCE_ONLY})
    files["config.json"] = config
    return files


def sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def maintenance_code(hold_ms: int = HOLD_MS) -> str:
    """device/maintenance.py with the hold time filled in, as sent to the board's REPL."""
    text = MAINTENANCE.read_text()
    default = f"_WSNAV_HOLD_MS = {HOLD_MS}\n"
    if default not in text:
        raise DeployError(f"{MAINTENANCE}: no '{default.strip()}' line to set the hold time")
    return text.replace(default, f"_WSNAV_HOLD_MS = {int(hold_ms)}\n")


def _names(names: list[str]) -> str:
    return "(" + "".join(repr(n) + "," for n in names) + ")"


def _step(code: str) -> str:
    """A command in maintenance mode: extends the hold first, and fails with a NameError on a board that left it."""
    return "_wsnav_keep();" + code


def _sha_step(names: list[str]) -> str:
    return _step(f"_wsnav_sha({_names(names)})")


def _rm_step(names: list[str]) -> str:
    """Stale `.py` copies of the modules (they would shadow the .mpy) and an interrupted deploy's `.tmp` files."""
    stale = [n[: -len(".mpy")] + ".py" for n in names if n.endswith(".mpy")] + [n + ".tmp" for n in names]
    return _step(f"_wsnav_rm({_names(stale)})")


def _rename_step(name: str) -> str:
    return _step(f"os.rename({name + '.tmp'!r},{name!r})")


class Deployer:
    """One deploy to one board: the steps of the module docstring, each a command at the board's REPL."""

    def __init__(self, board: Board, log: Callable[[str], None] = print, hold_ms: int = HOLD_MS) -> None:
        self.board = board
        self.log = log
        self.hold_ms = hold_ms

    def _run(self, code: str) -> str:
        """Run code in maintenance mode (which each command extends); fails if the board left it (a reset)."""
        try:
            return self.board.run(code)
        except BoardError as exc:
            if "_wsnav_keep" in str(exc):
                raise DeployError(
                    "the board left maintenance mode (it reset?): run the deploy again"
                ) from None
            raise DeployError(f"board: {exc}") from None

    def hashes(self, names: list[str]) -> dict[str, str]:
        """sha256 of each file on the board ("-" if it is missing), computed there."""
        found: dict[str, str] = {}
        for line in self._run(_sha_step(names)).splitlines():
            words = line.split()
            if len(words) == 2 and words[0] in names:
                found[words[0]] = words[1]
        missing = [n for n in names if n not in found]
        if missing:
            raise DeployError(f"board: no hash for {', '.join(missing)}")
        return found

    def enter(self) -> None:
        try:
            out = self.board.run(maintenance_code(self.hold_ms))
        except BoardError as exc:
            raise DeployError(f"board: cannot enter maintenance mode: {exc}") from None
        if "wsnav maintenance" not in out:
            raise DeployError(f"board: maintenance mode did not start ({out.strip()[-80:] or 'no answer'})")
        self.log(
            f"maintenance mode (the board's watchdog is fed for {self.hold_ms // 1000} s after each step)"
        )
        self.check_mpy()
        self.check_fs()

    def check_fs(self) -> None:
        """Refuse a board whose flash is FAT (device/fscheck.py, its text run here: the board may have none of
        our files yet) before anything on it is touched: renaming files in is not power-cut safe on FAT."""
        out = self._run(FSCHECK.read_text() + "\nprint('wsnav-fs', 'fat' if fat() else 'ok')\ndel fat")
        if "wsnav-fs fat" in out:
            raise DeployError(f"board: {FAT_ADVICE}")
        if "wsnav-fs ok" not in out:
            raise DeployError(f"board: cannot tell its filesystem ({out.strip()[-80:]})")

    def check_mpy(self) -> None:
        """Refuse a board whose MicroPython cannot load our .mpy files (another .mpy version: older than 1.19,
        or a future format), before anything on it is touched."""
        out = self._run("import sys;print('wsnav-mpy', sys.implementation._mpy & 0xff, sys.version)")
        words = next(
            (line.split(maxsplit=2) for line in out.splitlines() if line.startswith("wsnav-mpy")), []
        )
        if len(words) < 2 or not words[1].isdigit():
            raise DeployError(f"board: cannot tell its MicroPython's .mpy version ({out.strip()[-80:]})")
        if int(words[1]) != MPY_VERSION:
            release = words[2] if len(words) > 2 else "?"
            raise DeployError(
                f"board: its MicroPython ({release}) loads .mpy version {words[1]}, ours are version "
                f"{MPY_VERSION}: flash MicroPython 1.19 or later (`wsnav firmware flash`)"
            )

    def deploy(self, files: dict[str, Path]) -> list[str]:
        """Put `files` (board name -> host file) on the board, verified; returns the names that were copied."""
        want = {name: sha256_file(path) for name, path in files.items()}
        names = sorted(files)
        self.enter()
        self._run(_rm_step(names))
        have = self.hashes(names)
        copied = []
        for name in names:
            if have[name] == want[name]:
                continue
            tmp = name + ".tmp"
            self.log(f"copying {name} ({files[name].stat().st_size} bytes)")
            try:
                self.board.put(files[name], tmp)
            except BoardError as exc:
                raise DeployError(f"board: copying {name}: {exc}") from None
            got = self.hashes([tmp])[tmp]
            if got != want[name]:
                raise DeployError(f"board: {tmp} arrived damaged (sha256 {got[:12]}, sent {want[name][:12]})")
            self._run(_rename_step(name))
            copied.append(name)
        final = self.hashes(names)
        bad = [n for n in names if final[n] != want[n]]
        if bad:
            raise DeployError(f"board: sha256 differs after the copy: {', '.join(bad)}")
        self.log(f"{len(names)} files verified on the board (sha256), {len(copied)} copied; resetting")
        try:
            self.board.reset()
        except BoardError as exc:
            raise DeployError(f"board: reset: {exc}") from None
        return copied

    def wait_online(self, timeout_s: float = ONLINE_S) -> float:
        """Seconds from the reset until the node reached its broker, read from the board's console; DeployError
        with the node's last words (`mqtt down: ...`, a config error, a traceback's last line) if it did not."""
        start = time.monotonic()
        last = ""
        try:
            for line in self.board.console(timeout_s):
                text = line.strip()
                if text.startswith(ONLINE_LINE):
                    return time.monotonic() - start
                if text and text.isprintable():
                    last = text
        except BoardError as exc:
            raise DeployError(f"board: reading its console: {exc}") from None
        said = f"its last words: {last!r}" if last else "it printed nothing"
        raise DeployError(
            f"the files are on the board and verified, but the node did not reach its broker within "
            f"{timeout_s:.0f} s of the reset ({said})"
        )


def deploy_plan(port: str, files: dict[str, Path]) -> list[list[str]]:
    """The mpremote sessions of a deploy that finds every file different (what --dry-run prints)."""
    board = MpremoteBoard(port)
    names = sorted(files)
    plan = [
        board.command("exec", f"<{MAINTENANCE.relative_to(DEVICE.parent.parent)}>"),
        board.command("exec", _rm_step(names)),
        board.command("exec", _sha_step(names)),
    ]
    for name in names:
        plan.append(board.command("fs", "cp", str(files[name]), f":{name}.tmp"))
        plan.append(board.command("exec", _sha_step([name + ".tmp"])))
        plan.append(board.command("exec", _rename_step(name)))
    plan.append(board.command("exec", _sha_step(names)))
    plan.append(board.command("reset"))
    return plan


def format_plan(plan: list[list[str]]) -> list[str]:
    return [shlex.join(cmd) for cmd in plan]


def check_image(path: Path) -> None:
    if not path.is_file():
        raise DeployError(f"{path}: no such firmware image")
    size = path.stat().st_size
    if size < 64 * 1024 or size > 4 * 1024 * 1024:
        raise DeployError(
            f"{path}: {size} bytes is not an ESP8266 MicroPython image (expected 64 KiB..4 MiB)"
        )
    with path.open("rb") as f:
        header = f.read(8)
    if header[:1] != b"\xe9":
        raise DeployError(f"{path}: not an ESP8266 image (first byte is not 0xE9)")
    entry = int.from_bytes(header[4:8], "little")
    if not ESP8266_IRAM[0] <= entry < ESP8266_IRAM[1]:
        raise DeployError(
            f"{path}: not an ESP8266 image (its entry point 0x{entry:08x} lies outside the ESP8266's IRAM; "
            "an ESP32 image's lies near 0x40080000): take ESP8266_GENERIC-*.bin"
        )


def flash_commands(
    port: str, image: Path, baud: int = FLASH_BAUD, flash_mode: str = "keep"
) -> list[list[str]]:
    esptool = tool_path("esptool")
    base = [esptool, "--chip", "esp8266", "--port", port]
    write = [*base, "--baud", str(baud), "write-flash", "--flash-size=detect"]
    if flash_mode != "keep":
        write.append(f"--flash-mode={flash_mode}")
    return [[*base, "erase-flash"], [*write, "0", str(image)]]
