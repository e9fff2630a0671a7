"""`wsnav firmware config`: a new configuration (Wi-Fi, broker address, MQTT password) for running nodes over MQTT, the
operator's side (the node's: device/otaconfig.py).

Each node gets its settings sealed under its own update key (schemas.credentials.seal_config: robots and
dashboards read nodes/#, where the node fetches them) and a `config` command carrying their HMAC; it fetches them
in update mode as it fetches a manifest (`ConfigServer` answers its `ota/request`), tries them at its next boot
(a trial), and keeps them once it has run online and healthy with them (`info` without `trial`), or goes back to
its old configuration if it is not online with them in time and says so (`info` error ROLLED_BACK).
"""

from __future__ import annotations

import json
import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass

from wsnav.firmware.ota import NodeProgress, NodeTransfer
from wsnav.runtime.mqtt_bus import MqttBus
from wsnav.schemas.credentials import (
    CONFIG_MAX_BYTES,
    CONFIG_NONCE_BYTES,
    config_seq,
    seal_config,
    sign_manifest,
)
from wsnav.schemas.messages import NodeInfo, PayloadError, parse_payload

ROLLED_BACK = "config: rolled back"
"""What a node's `info` says after it went back to its old configuration (device/otaboot.py)."""
TRIAL_OFFLINE_S = 120
"""How long a node tries a configuration before it goes back (device/health.py's _OFFLINE_S)."""


class ConfigError(Exception):
    """Settings that a node would refuse: one line for the user."""


@dataclass(frozen=True)
class Settings:
    """What a configuration changes: the Wi-Fi network (SSID and key), the broker's address and the node's MQTT
    password (one node's: the broker must take it beside the old one first, broker/credentials.py add_pending),
    each optional."""

    wifi: tuple[str, str] | None = None
    broker: tuple[str, int] | None = None
    password: str | None = None
    seq: int | None = None
    """The configuration's number (schemas.credentials.config_seq; None: from the clock now): a node takes only
    a number above the last it took, so an older configuration cannot be replayed."""

    def payload(self) -> bytes:
        """The JSON the node merges into its config.json (schemas.credentials.CONFIG_KEYS), checked as a
        NodeConfig would check it, with its `seq`."""
        d: dict[str, object] = {}
        if self.wifi is not None:
            ssid, key = self.wifi
            if not 1 <= len(ssid.encode()) <= 32:
                raise ConfigError(f"Wi-Fi SSID {ssid!r}: 1 to 32 bytes")
            if key and not 8 <= len(key) <= 63:
                raise ConfigError("Wi-Fi key: 8 to 63 characters (WPA2), or empty for an open network")
            d["wifi"] = {"ssid": ssid, "password": key}
        if self.broker is not None:
            host, port = self.broker
            if not host or len(host) > 64 or not 0 < port < 65536:
                raise ConfigError(f"broker {host}:{port}: a host name or address and a port 1..65535")
            d["broker"] = {"host": host, "port": port}
        if self.password is not None:
            if not 16 <= len(self.password) <= 64 or not self.password.isascii():
                raise ConfigError("an MQTT password: 16 to 64 ASCII characters")
            d["password"] = self.password
        if not d:
            raise ConfigError("nothing to change: give --wifi, --node-broker, --new-password or some of them")
        d["seq"] = self.seq if self.seq is not None else config_seq(time.time())
        data = json.dumps(d, separators=(",", ":")).encode()
        if len(data) + CONFIG_NONCE_BYTES > CONFIG_MAX_BYTES:
            raise ConfigError(f"the settings take {len(data)} B, more than a node fetches in one piece")
        return data


def seal_for(node_key: str, settings: bytes) -> tuple[bytes, str]:
    """(sealed settings, the `config` command's `manifest`) for the node whose update key is `node_key`."""
    sealed = seal_config(node_key, settings, secrets.token_bytes(CONFIG_NONCE_BYTES))
    return sealed, sign_manifest(node_key, sealed)


class ConfigServer(NodeTransfer):
    """Serves each node its sealed configuration and follows it: trying (an `info` with `trial`), kept (an
    `info` without, after), gone back (ROLLED_BACK) or refused (an `ota:` error: a bad signature, settings its
    checks refuse)."""

    what = "configuration"

    def __init__(
        self, bus: MqttBus, site: str, sealed: dict[str, bytes], say: Callable[[str], None] = print
    ) -> None:
        super().__init__(bus, site, list(sealed), say)
        self.sealed = sealed

    def payloads(self, node: str) -> list[bytes]:
        return [self.sealed[node]]

    def _info(self, prog: NodeProgress, payload: bytes) -> None:
        try:
            info = parse_payload(NodeInfo, payload)
        except PayloadError:
            return
        error = info.error or ""
        if not prog.started and not error.startswith("ota:"):
            return  # its infos before it asked for anything say nothing of this configuration
        if error == ROLLED_BACK:
            prog.error = (
                f"{prog.node}: rolled back to its old configuration (not online with the new one within "
                f"{TRIAL_OFFLINE_S} s)"
            )
        elif error.startswith(("ota:", "safe:")):
            prog.error = f"{prog.node}: configuration refused: {error}"
        elif info.trial:
            if not prog.trial:
                prog.trial = True
                self.say(f"{prog.node}: online with the new configuration, waiting for it to confirm")
        elif prog.trial:
            prog.done = True
            self.say(f"{prog.node}: new configuration confirmed")
        if prog.error is not None:
            self.say(prog.error)
