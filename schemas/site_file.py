"""Pydantic model of `sites/<name>/site.yaml`: zones, the nodes that watch them, robots, points and routes.

Checks that need only the file live here; checks that need the map (zone outside it, point in a wall) live in
schemas.site, which loads both.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from wsnav.schemas.ids import Id

Point2 = tuple[float, float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


SAFE_PINS = "4, 5, 12, 13 or 14"


def pin_problem(pin: int, is_input: bool, pull_up: bool = False) -> str | None:
    """Why an ESP8266 GPIO cannot take this sensor line (None: it can). The firmware's config check
    (firmware/device/nodeconfig.py `pin_problem`) says the same; tests/test_firmware_logic.py keeps them in step."""
    if pin in (1, 3):
        return f"is the serial console ({'TX' if pin == 1 else 'RX'})"
    if 6 <= pin <= 11:
        return "is wired to the SPI flash"
    if is_input and pin in (0, 2, 15):
        return "selects the boot mode: a sensor driving it at power-on can keep the board from starting"
    if pull_up and pin == 16:
        return "has no pull-up for the IR receiver"
    return None


def _checked_pin(pin: int, is_input: bool, pull_up: bool = False) -> int:
    why = pin_problem(pin, is_input, pull_up)
    if why is not None:
        raise ValueError(f"GPIO{pin} {why} (use {SAFE_PINS})")
    return pin


GpioPin = Annotated[int, Field(ge=0, le=16)]
MAX_DELAY_MS = 600_000
"""A zone's debounce delays (site file, node config) are at most 10 minutes."""


class DigitalSensor(_Strict):
    """PIR motion sensor or IR break-beam: one digital pin; `invert` when the module is active-low."""

    type: Literal["pir", "ir_beam"]
    pin: GpioPin
    invert: bool = False
    warmup_s: Annotated[float, Field(ge=0, le=600)] | None = None
    """PIR only: how long after power-on the node ignores the sensor and publishes no zone state (an HC-SR501
    fires at random for 30-60 s). Absent: 60 s."""

    @model_validator(mode="after")
    def _warmup_for_a_pir(self) -> DigitalSensor:
        if self.warmup_s is not None and self.type != "pir":
            raise ValueError("warmup_s is for a PIR only")
        return self

    @field_validator("pin")
    @classmethod
    def _safe_pin(cls, pin: int, info: ValidationInfo) -> int:
        return _checked_pin(pin, True, pull_up=info.data.get("type") == "ir_beam")


class UltrasonicSensor(_Strict):
    """HC-SR04: an object nearer than `threshold_m` means the passage is blocked; median of `samples` pings."""

    type: Literal["hcsr04"]
    trigger_pin: GpioPin
    echo_pin: GpioPin
    threshold_m: Annotated[float, Field(gt=0.02, le=4.0)] = 1.0
    samples: Annotated[int, Field(ge=1, le=15)] = 5
    caution_m: Annotated[float, Field(le=4.0)] | None = None
    """An object between `threshold_m` and this distance narrows the passage: the node says `caution`.
    Absent: the node only ever says `blocked` or `clear`."""

    @field_validator("trigger_pin", "echo_pin")
    @classmethod
    def _safe_pins(cls, pin: int, info: ValidationInfo) -> int:
        if info.field_name == "echo_pin" and pin == info.data.get("trigger_pin"):
            raise ValueError("must differ from trigger_pin")
        return _checked_pin(pin, is_input=info.field_name == "echo_pin")

    @model_validator(mode="after")
    def _caution_beyond_threshold(self) -> UltrasonicSensor:
        if self.caution_m is not None and not self.caution_m > self.threshold_m:
            raise ValueError(
                f"caution_m ({self.caution_m}) must be farther than threshold_m ({self.threshold_m})"
            )
        return self


Sensor = Annotated[DigitalSensor | UltrasonicSensor, Field(discriminator="type")]


class Zone(_Strict):
    id: Id
    polygon: Annotated[list[Point2], Field(min_length=3)]
    name: str | None = None


class Node(_Strict):
    """One ESP8266 watching one zone; many nodes may watch the same zone."""

    id: Id
    zone: Id
    sensor: Sensor
    position: Point2 | None = None
    """Where the node hangs, for pictures; the zone's centre when absent."""
    heartbeat_s: Annotated[float, Field(gt=0, le=3600)] | None = None
    """Overrides the site's heartbeat period for this node."""
    on_delay_ms: Annotated[int, Field(ge=0, le=MAX_DELAY_MS)] = 500
    """Debounce: the sensor must read 'occupied' this long before the node says `blocked`."""
    off_delay_ms: Annotated[int, Field(ge=0, le=MAX_DELAY_MS)] = 3000
    """Debounce: the sensor must read 'free' this long before the node says `clear`."""


class Robot(_Strict):
    id: Id
    footprint_radius: Annotated[float, Field(gt=0, le=2.0)] = 0.105
    start: Id | None = None
    """The named point where the robot stands when a simulated fleet starts (`wsnav fleet --sim`)."""


class Route(_Strict):
    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    from_: Id = Field(alias="from")
    to: Id
    raffle: Annotated[list[Annotated[list[Id], Field(min_length=1)]], Field(min_length=1)]
    """The zone sets, one of which is blocked per run (the paper's raffle)."""


class ZonePolicy(_Strict):
    """How the robot's zone layer reads zone states (docs/architecture.md, "The costmap's layers")."""

    caution_cost: Annotated[int, Field(ge=1, le=252)] = 200
    stale_after_heartbeats: Annotated[float, Field(gt=1)] = 3.0
    stale: Literal["keep", "unknown", "lethal"] = "keep"
    fuse: Literal["any_blocked", "majority"] = "any_blocked"


class SiteFile(_Strict):
    name: Id
    map: str
    heartbeat_s: Annotated[float, Field(gt=0, le=3600)] = 5.0
    policy: ZonePolicy = ZonePolicy()
    zones: list[Zone]
    nodes: list[Node] = Field(default_factory=list)
    robots: list[Robot] = Field(default_factory=list)
    points: dict[Id, Annotated[list[float], Field(min_length=2, max_length=3)]] = Field(default_factory=dict)
    routes: list[Route] = Field(default_factory=list)

    @field_validator("points")
    @classmethod
    def _yaw_default(cls, points: dict[str, list[float]]) -> dict[str, list[float]]:
        return {name: [*xy, 0.0] if len(xy) == 2 else xy for name, xy in points.items()}

    @model_validator(mode="after")
    def _references(self) -> SiteFile:
        _unique("zones", [z.id for z in self.zones])
        _unique("nodes", [n.id for n in self.nodes])
        _unique("robots", [r.id for r in self.robots])
        clash = {n.id for n in self.nodes} & {r.id for r in self.robots}
        if clash:
            raise ValueError(
                f"ids used by both a node and a robot (they share one credentials folder): {sorted(clash)}"
            )
        zones = {z.id for z in self.zones}
        for i, robot in enumerate(self.robots):
            if robot.start is not None and robot.start not in self.points:
                raise ValueError(f"robots[{i}] ({robot.id}): unknown start point {robot.start!r}")
        for i, node in enumerate(self.nodes):
            if node.zone not in zones:
                raise ValueError(f"nodes[{i}] ({node.id}): unknown zone {node.zone!r}")
        for i, route in enumerate(self.routes):
            for end in (route.from_, route.to):
                if end not in self.points:
                    raise ValueError(f"routes[{i}]: unknown point {end!r}")
            for zone_set in route.raffle:
                for zone in zone_set:
                    if zone not in zones:
                        raise ValueError(f"routes[{i}].raffle: unknown zone {zone!r}")
        return self

    def zone(self, zone_id: str) -> Zone:
        return next(z for z in self.zones if z.id == zone_id)

    def heartbeat_of(self, node: Node) -> float:
        return node.heartbeat_s if node.heartbeat_s is not None else self.heartbeat_s


def _unique(key: str, ids: list[str]) -> None:
    seen: set[str] = set()
    for i, value in enumerate(ids):
        if value in seen:
            raise ValueError(f"{key}[{i}]: duplicate id {value!r}")
        seen.add(value)
