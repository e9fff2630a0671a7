"""Builds wsnav's Mosquitto plugin (`store_guard.c`) on the machine that runs Mosquitto, against its mosquitto-dev.

Why a plugin: Mosquitto acknowledges before it saves, so only code inside Mosquitto can make an operator block
durable before its PUBACK, and only Mosquitto's own log is where an operator looks when its store goes bad. The
source ships with wsnav and is compiled here, with the system's C compiler, so nothing prebuilt is committed.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

SOURCE = Path(__file__).with_name("store_guard.c")
PLUGIN = "wsnav_store_guard.so"
HEADERS = (Path("/usr/include/mosquitto_broker.h"), Path("/usr/include/mosquitto.h"))
JOURNAL = "operator-blocks.journal"
"""In Mosquitto's persistence folder, beside `mosquitto.db`."""


class PluginBuildError(RuntimeError):
    """The plugin cannot be built here (one line for the user)."""


def build_plugin(out: Path) -> Path:
    """Compile the plugin into `out` (created) and return its path; raises PluginBuildError."""
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise PluginBuildError("no C compiler (Debian: apt-get install gcc libc6-dev)")
    missing = [str(h) for h in HEADERS if not h.is_file()]
    if missing:
        raise PluginBuildError(
            f"{', '.join(missing)} missing (Debian: apt-get install mosquitto-dev libmosquitto-dev)"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PluginBuildError(f"{out}: cannot create the folder: {exc.strerror}") from None
    target = out / PLUGIN
    built = subprocess.run(
        [compiler, "-shared", "-fPIC", "-O2", "-Wall", "-o", str(target), str(SOURCE)],
        capture_output=True,
        text=True,
        check=False,
    )
    if built.returncode != 0:
        first = next((line for line in built.stderr.splitlines() if "error" in line), built.stderr.strip())
        raise PluginBuildError(f"the plugin did not compile: {first}")
    target.chmod(0o755)
    return target
