"""Builds wsnav's Mosquitto plugins on the machine that runs Mosquitto, against its mosquitto-dev: the store guard
(`store_guard.c`) and the pending-password check (`pending_auth.c`, pending_plugin.py).

Why a plugin: Mosquitto acknowledges before it saves, so only code inside Mosquitto can make an operator block
durable before its PUBACK, and only Mosquitto's own log is where an operator looks when its store goes bad. The
source ships with wsnav and is compiled here, with the system's C compiler, so nothing prebuilt is committed.
"""

from __future__ import annotations

import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class PluginSource:
    """One plugin: its C source beside this module, the library it builds, what it needs to build."""

    source: str
    library: str
    links: tuple[str, ...] = ()
    headers: tuple[str, ...] = ("/usr/include/mosquitto_broker.h", "/usr/include/mosquitto.h")
    packages: str = "mosquitto-dev libmosquitto-dev"


STORE_GUARD = PluginSource("store_guard.c", "wsnav_store_guard.so")
PENDING_AUTH = PluginSource(
    "pending_auth.c",
    "wsnav_pending.so",
    links=("-lcrypto",),
    headers=(*STORE_GUARD.headers, "/usr/include/openssl/evp.h"),
    packages="mosquitto-dev libmosquitto-dev libssl-dev",
)
PLUGIN = STORE_GUARD.library
JOURNAL = "operator-blocks.journal"
"""In Mosquitto's persistence folder, beside `mosquitto.db`."""


class PluginBuildError(RuntimeError):
    """The plugin cannot be built here (one line for the user)."""


def build_plugin(out: Path, plugin: PluginSource = STORE_GUARD) -> Path:
    """Compile `plugin` into `out` (created) and return its path; raises PluginBuildError."""
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise PluginBuildError("no C compiler (Debian: apt-get install gcc libc6-dev)")
    missing = [h for h in plugin.headers if not Path(h).is_file()]
    if missing:
        raise PluginBuildError(f"{', '.join(missing)} missing (Debian: apt-get install {plugin.packages})")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PluginBuildError(f"{out}: cannot create the folder: {exc.strerror}") from None
    target = out / plugin.library
    source = Path(__file__).with_name(plugin.source)
    built = subprocess.run(
        [compiler, "-shared", "-fPIC", "-O2", "-Wall", "-o", str(target), str(source), *plugin.links],
        capture_output=True,
        text=True,
        check=False,
    )
    if built.returncode != 0:
        first = next((line for line in built.stderr.splitlines() if "error" in line), built.stderr.strip())
        raise PluginBuildError(f"the plugin did not compile: {first}")
    target.chmod(0o755)
    return target
