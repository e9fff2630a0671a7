"""The per-id credentials files written by `wsnav broker credentials` (one `<id>.json` each).

A node's file doubles as its firmware `config.json`: everything the ESP8266 needs to join the site, so the
firmware reads exactly these keys (see schemas/json/node_config.json).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from wsnav.schemas.ids import Id
from wsnav.schemas.site_file import Sensor

Role = Literal["node", "robot", "operator"]


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
    on_delay_ms: Annotated[int, Field(ge=0)]
    off_delay_ms: Annotated[int, Field(ge=0)]
    keepalive_s: Annotated[int, Field(ge=5, le=3600)] = 30
    wifi: WifiConfig = WifiConfig()

    @model_validator(mode="after")
    def _is_node(self) -> NodeConfig:
        if self.role != "node":
            raise ValueError("a node config must have role 'node'")
        return self
