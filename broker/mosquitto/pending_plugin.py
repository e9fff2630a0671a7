"""The pending-password plugin of a generated Mosquitto configuration (pending_auth.c): built into the
configuration's folder and loaded by mosquitto.conf's lines (`wsnav broker mosquitto-config --pending-passwords`).
Its file's lines are pending.py's."""

from __future__ import annotations

from pathlib import Path

from wsnav.broker.mosquitto.plugin import PENDING_AUTH, PluginBuildError
from wsnav.broker.mosquitto.plugin import build_plugin as build_any
from wsnav.schemas.credentials import CredentialsError

PLUGIN = PENDING_AUTH.library
PENDING = "mosquitto.pending"
"""The pending passwords' file the plugin reads at each login (`username:$7$...` lines)."""


def build_plugin(out: Path) -> Path:
    """Compile the plugin into `out`; one line naming what is missing when it cannot be built."""
    try:
        return build_any(out, PENDING_AUTH)
    except PluginBuildError as exc:
        raise CredentialsError(f"--pending-passwords: {exc}") from None


def conf_lines(out: Path) -> list[str]:
    """mosquitto.conf's lines that load the plugin (before the password file is consulted: it defers)."""
    return [
        "# wsnav's pending passwords (a node changing its password): accepted beside the password file",
        f"plugin {out / PLUGIN}",
        f"plugin_opt_pending_file {out / PENDING}",
    ]
