"""The pending-password plugin of a generated Mosquitto configuration (pending_auth.c): built into the
configuration's folder and loaded by mosquitto.conf's lines (`wsnav broker mosquitto-config --pending-passwords`).
Its file's lines are pending.py's."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

from wsnav.schemas.credentials import CredentialsError

SOURCE = Path(__file__).with_name("pending_auth.c")
PLUGIN = "wsnav_pending.so"
PENDING = "mosquitto.pending"
"""The pending passwords' file the plugin reads at each login (`username:$7$...` lines)."""


def build_plugin(out: Path) -> Path:
    """Compile the plugin into `out`; one line naming what is missing when it cannot be built."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise CredentialsError(
            "--pending-passwords: no C compiler (apt-get install gcc mosquitto-dev libssl-dev)"
        )
    target = out / PLUGIN
    cmd = [cc, "-O2", "-Wall", "-shared", "-fPIC", "-o", str(target), str(SOURCE), "-lcrypto"]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        first = next((line for line in done.stderr.splitlines() if "error" in line), done.stderr.strip())
        raise CredentialsError(
            f"--pending-passwords: cannot build the plugin (needs mosquitto-dev and libssl-dev): {first}"
        )
    return target


def conf_lines(out: Path) -> list[str]:
    """mosquitto.conf's lines that load the plugin (before the password file is consulted: it defers)."""
    return [
        "# wsnav's pending passwords (a node changing its password): accepted beside the password file",
        f"plugin {out / PLUGIN}",
        f"plugin_opt_pending_file {out / PENDING}",
    ]
