"""`wsnav firmware deploy` and `wsnav firmware flash`: the mpremote and esptool commands, built in one place so
--dry-run prints exactly what a real run executes.

Deploy copies the built .mpy modules, main.py, boot.py and the node's config.json (its credentials file from
`wsnav broker credentials`, with the broker address filled in) to the board's filesystem root, after deleting
stale .py copies of the same modules: MicroPython imports `app.py` before `app.mpy`, so a forgotten source file
would silently shadow the new build.
Flash erases the ESP8266 and writes a MicroPython image at offset 0 (what micropython.org documents for ESP8266).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from pydantic import ValidationError

from firmware.build import DEVICE, SOURCE_ONLY
from schemas.credentials import NodeConfig

FLASH_BAUD = 460800
"""Fast and reliable on CH340/CP2102 USB-serial bridges; esptool falls back to nothing, so lower it if it fails."""


class DeployError(Exception):
    """A bad config or image file, or a missing tool; one line."""


def _tool(name: str) -> str:
    here = Path(sys.executable).parent / name
    if here.exists():
        return str(here)
    return shutil.which(name) or name


def check_config(path: Path) -> NodeConfig:
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
    return cfg


def module_names(source: Path = DEVICE) -> list[str]:
    """Module names that become .mpy files (everything in device/ but main.py and boot.py)."""
    return sorted(p.stem for p in source.glob("*.py") if p.name not in SOURCE_ONLY)


def deploy_commands(port: str, build_dir: Path, config: Path, source: Path = DEVICE) -> list[list[str]]:
    mpremote = _tool("mpremote")
    names = module_names(source)
    stale = ",".join(f'"{n}.py"' for n in names)
    remove = f"import os;[os.remove(f) for f in os.listdir() if f in ({stale},)]"
    files = [str(build_dir / (n + ".mpy")) for n in names] + [str(build_dir / n) for n in SOURCE_ONLY]
    return [
        [mpremote, "connect", port, "exec", remove],
        [mpremote, "connect", port, "fs", "cp", *files, ":"],
        [mpremote, "connect", port, "fs", "cp", str(config), ":config.json"],
        [mpremote, "connect", port, "reset"],
    ]


def check_image(path: Path) -> None:
    if not path.is_file():
        raise DeployError(f"{path}: no such firmware image")
    size = path.stat().st_size
    if size < 64 * 1024 or size > 4 * 1024 * 1024:
        raise DeployError(
            f"{path}: {size} bytes is not an ESP8266 MicroPython image (expected 64 KiB..4 MiB)"
        )
    with path.open("rb") as f:
        if f.read(1) != b"\xe9":
            raise DeployError(f"{path}: not an ESP8266 image (first byte is not 0xE9)")


def flash_commands(port: str, image: Path, baud: int = FLASH_BAUD) -> list[list[str]]:
    esptool = _tool("esptool")
    base = [esptool, "--chip", "esp8266", "--port", port]
    return [
        [*base, "erase-flash"],
        [*base, "--baud", str(baud), "write-flash", "--flash-size=detect", "0", str(image)],
    ]
