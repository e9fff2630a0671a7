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

    @model_validator(mode="after")
    def _is_node(self) -> NodeConfig:
        if self.role != "node":
            raise ValueError("a node config must have role 'node'")
        return self


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
