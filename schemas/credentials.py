"""The per-id credentials files written by `wsnav broker credentials` (one `<id>.json` each).

A node's file doubles as its firmware `config.json`: everything the ESP8266 needs to join the site, so the
firmware reads exactly these keys (see schemas/json/node_config.json).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from wsnav.schemas.ids import Id
from wsnav.schemas.site_file import MAX_DELAY_MS, Sensor

Role = Literal["node", "robot", "operator", "dashboard"]


class BrokerAddress(BaseModel):
    model_config = ConfigDict(extra="forbid")

    host: str = ""
    """Empty until deploy time, when the installer knows where the Raspberry Pi lives."""
    port: Annotated[int, Field(ge=1, le=65535)] = 1883


class WifiConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    ssid: str = ""
    password: str = ""
    fallback_ap: bool = Field(default=True, exclude_if=lambda v: v is True)
    """False: the node never opens its fallback access point (firmware/device/fallback_ap.py, after 5 minutes
    without a network: app._FALLBACK_AP_MS); it keeps retrying, as before. Left out of config.json when true:
    on the board even a key the firmware does not use costs heap while main.py parses the file (a null one
    cost 48 B after setup, bench.firmware_heap's 32-bit port)."""


class Credentials(BaseModel):
    """A robot's or the operator's file: who it is and how it logs in."""

    model_config = ConfigDict(extra="forbid")

    username: Id
    password: Annotated[str, Field(min_length=16)]
    role: Role
    site: Id
    broker: BrokerAddress = BrokerAddress()


class NodeConfig(Credentials):
    """A node's file, also its firmware config.json."""

    node: Id
    zone: Id
    sensor: Sensor
    heartbeat_s: Annotated[float, Field(gt=0, le=3600)]
    on_delay_ms: Annotated[int, Field(ge=0, le=MAX_DELAY_MS)]
    off_delay_ms: Annotated[int, Field(ge=0, le=MAX_DELAY_MS)]
    keepalive_s: Annotated[int, Field(ge=5, le=3600)] = 30
    wifi: WifiConfig = WifiConfig()
    update_key: Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")] | None = None
    """This node's key for over-the-air updates (`node_update_key` of the site's UPDATE_KEY_FILE): the node takes
    an update only if the `update` command carries its manifest's HMAC under this key. Without it, no update
    over the air (a USB deploy still works)."""

    @model_validator(mode="after")
    def _is_node(self) -> NodeConfig:
        if self.role != "node":
            raise ValueError("a node config must have role 'node'")
        return self


UPDATE_KEY_FILE = "update.key"
"""The site's update key in the credentials folder (`wsnav broker credentials` makes it): 64 hex digits, read by
`wsnav firmware ota` only. It is not the operator's MQTT password: a stolen operator login can send commands but
cannot sign an update, so it cannot reprogram a node."""


def node_update_key(site_key: str, node: str) -> str:
    """A node's update key (NodeConfig.update_key): HMAC-SHA256 of its id under the site's key, so a node taken
    off the ceiling gives away its own key only, and the operator's tool needs only the site's."""
    import hashlib
    import hmac

    return hmac.new(site_key.encode(), b"wsnav-ota " + node.encode(), hashlib.sha256).hexdigest()


def sign_manifest(node_key: str, manifest: bytes) -> str:
    """What an `update` command carries for a node (NodeCommand.manifest): HMAC-SHA256 of the manifest's bytes
    under the node's key as ASCII (64 bytes: one SHA-256 block, which the board's updater uses as it is)."""
    import hashlib
    import hmac

    return hmac.new(node_key.encode(), manifest, hashlib.sha256).hexdigest()


def fallback_ap_ssid(node: str) -> str:
    """The name of a node's fallback access point (firmware/device/fallback_ap.py): at most 32 bytes, as Wi-Fi's."""
    return ("wsnav-" + node)[:32]


def fallback_ap_key(node_key: str) -> str:
    """A node's fallback access point's WPA2 key, from its update key (NodeConfig.update_key): 16 hex digits of
    sha256(key, "wsnav-ap"), what the board computes (fallback_ap.key). Who has the site's update key can print it
    (`wsnav firmware fallback-ap`); a node taken off the ceiling gives away its own only."""
    import hashlib

    return hashlib.sha256(node_key.encode() + b"wsnav-ap").hexdigest()[:16]


CONFIG_KEYS = ("wifi", "broker", "password")
"""What a configuration over the air may change in a node's config.json (`wsnav firmware config`): its Wi-Fi, its
broker's address and its MQTT password; the node refuses any other key (firmware/device/otaconfig.py)."""
CONFIG_SEQ_EPOCH = 1_577_836_800
"""2020-01-01 UTC: a configuration's `seq` counts seconds from it (a small int on the ESP8266 until 2054)."""


def config_seq(now: float) -> int:
    """A configuration's number (`seq` in its settings, `wsnav firmware config`): the operator's clock in seconds
    since CONFIG_SEQ_EPOCH. The node keeps the last one it took (`config.seq`) and refuses one not above it, so a
    captured older configuration cannot be replayed (firmware/device/otaconfig.py)."""
    return int(now) - CONFIG_SEQ_EPOCH


CONFIG_NONCE_BYTES = 16
CONFIG_MAX_BYTES = 512
"""A sealed configuration's size limit: one OTA chunk, what the node fetches in one piece."""


def config_keystream(node_key: str, nonce: bytes, n: int) -> bytes:
    """`n` bytes of SHA-256 in counter mode under the node's key: block i is sha256(key, "wsnav-config", nonce,
    i). What the board has (hashlib) and nothing more; the node computes the same (device/otaconfig.py)."""
    import hashlib

    out = b""
    for i in range((n + 31) // 32):
        out += hashlib.sha256(node_key.encode() + b"wsnav-config" + nonce + bytes([i])).digest()
    return out[:n]


def seal_config(node_key: str, settings: bytes, nonce: bytes) -> bytes:
    """A configuration for one node (`wsnav firmware config`): `nonce` then `settings` (JSON) XORed with
    config_keystream, so the Wi-Fi key and broker address are unreadable on the bus (every reader of nodes/#
    sees the chunk); the `config` command carries its HMAC (sign_manifest), so only the site's operator tool can
    make one. A fresh random nonce per configuration: the same keystream is never used twice."""
    stream = config_keystream(node_key, nonce, len(settings))
    return nonce + bytes(a ^ b for a, b in zip(settings, stream, strict=True))


def open_config(node_key: str, sealed: bytes) -> bytes:
    """seal_config's settings back (the node's side, for tests and tools)."""
    nonce, body = sealed[:CONFIG_NONCE_BYTES], sealed[CONFIG_NONCE_BYTES:]
    stream = config_keystream(node_key, nonce, len(body))
    return bytes(a ^ b for a, b in zip(body, stream, strict=True))


OPERATOR_TOOLS = ("console", "watch", "status", "command", "zone-sim", "health", "ota", "ha-discovery")
"""The operator's tools that may run at once. Each logs in under a name of its own (`operator.watch`), with the
operator's password and rights: Mosquitto binds a client id to its username (`use_username_as_clientid`), so
one shared username let them knock each other off. `command` is every short-lived verb (block, goal, ...)."""


TOOL_COPIES = 8
"""How many copies of one operator tool may be logged in at once (two consoles, two `wsnav watch`), each under a
login of its own: `operator.watch`, then `operator.watch.2` ... `operator.watch.8` (runtime.login_copies picks
one); under one login the second copy took the first over on Mosquitto."""


def tool_login_name(username: str, tool: str, copy: int = 1) -> str:
    """The login of one copy of an operator tool: site ids hold no '.', so it can never be another identity's."""
    if tool not in OPERATOR_TOOLS:
        raise ValueError(f"not an operator tool: {tool!r}")
    if not 1 <= copy <= TOOL_COPIES:
        raise ValueError(f"copy {copy} of {tool}: 1 to {TOOL_COPIES}")
    return f"{username}.{tool}" + ("" if copy == 1 else f".{copy}")


def tool_copies(creds: Credentials) -> list[str]:
    """The logins of every copy of the tool whose credentials `tool_login` made; a non-tool login alone."""
    user, _, tool = creds.username.partition(".")
    if creds.role != "operator" or tool not in OPERATOR_TOOLS:
        return [creds.username]
    return [tool_login_name(user, tool, copy) for copy in range(1, TOOL_COPIES + 1)]


def operator_logins(username: str) -> list[str]:
    """Every name the operator's password logs in under: its own and each copy of each tool's (password file, ACL)."""
    tools = (tool_login_name(username, t, c) for t in OPERATOR_TOOLS for c in range(1, TOOL_COPIES + 1))
    return [username, *tools]


def tool_login(creds: Credentials, tool: str) -> Credentials:
    """The operator's credentials as `tool` logs in with them; any other role's are returned as they are."""
    if creds.role != "operator":
        return creds
    return creds.model_copy(update={"username": tool_login_name(creds.username, tool)})


class CredentialsError(ValueError):
    """A credentials folder or file that cannot be used; str() is one line naming the file."""


def read_json_object(path: Path) -> dict[str, object]:
    """A JSON object from a file, or CredentialsError with a one-line reason."""
    try:
        raw = json.loads(path.read_text())
    except OSError as exc:
        raise CredentialsError(f"{path}: cannot read: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise CredentialsError(
            f"{path}: not valid JSON: {exc.msg} (line {exc.lineno}); fix or remove it"
        ) from None
    if not isinstance(raw, dict):
        raise CredentialsError(f"{path}: expected a JSON object")
    return raw


def load_credentials(path: Path) -> Credentials:
    """One `<id>.json` (a NodeConfig when its role is node); raises CredentialsError with a one-line reason."""
    raw = read_json_object(path)
    try:
        return (
            NodeConfig.model_validate(raw) if raw.get("role") == "node" else Credentials.model_validate(raw)
        )
    except ValidationError as exc:
        err = exc.errors()[0]
        key = ".".join(str(p) for p in err["loc"]) or "(file)"
        raise CredentialsError(f"{path}: {key}: {err['msg']}") from None


def credentials_for(path: Path, *, role: Role, site: str, ids: list[str]) -> Credentials:
    """The credentials file of one `role` of `site` (a robot's, the operator's...), checked before any login:
    the file is that role's, that site's, and its username one of `ids`."""
    creds = load_credentials(path)
    if creds.role != role:
        raise CredentialsError(f"{path}: these are {creds.role} credentials, not {role} credentials")
    if creds.site != site:
        raise CredentialsError(f"{path}: credentials for site {creds.site!r}, not {site!r}")
    if creds.username not in ids:
        raise CredentialsError(f"{path}: {role} {creds.username!r} is not in site {site!r} ({role}s: {ids})")
    return creds
