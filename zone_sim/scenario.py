"""Scenario files: what happens in the simulated world and to the nodes, when (YAML, validated with pydantic).

    duration_s: 90                   # optional; the command's --duration wins
    seed: 7                          # optional; the command's --seed wins
    sensor: {detection_delay_s: 0.5, miss_rate: 0.0}
    blocks:                          # scripted obstacles: z4 blocked from t=5 s to t=60 s
      - {zone: z4, from_s: 5, to_s: 60}
    raffles:                         # the paper's raffles: every 30 s block one of route A->B's zone sets for 20 s
      - {route: A->B, start_s: 0, every_s: 30, hold_s: 20, count: 3}
    failures:                        # kill: power cut (link dropped); hang: silent until the broker drops it
      - {node: n5, at_s: 30, kind: kill}
      - {node: n5, at_s: 45, kind: reboot}

`load_scenario` checks the file against the site too; every error is one line naming file, key and problem.
Times are seconds on the simulator's clock from its start. `timeline(seed)` turns a scenario into the sorted
list of events the simulator applies, deterministically.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from wsnav.schemas.ids import Id
from wsnav.schemas.site_file import SiteFile
from wsnav.schemas.yaml_file import read_yaml_mapping
from wsnav.zone_sim.raffle import RaffleError, draws, find_route

Seconds = Annotated[float, Field(ge=0, allow_inf_nan=False)]


class ScenarioError(ValueError):
    """A scenario that cannot be used; str() is one line: `<file>: <key>: <problem>`."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SensorSpec(_Strict):
    detection_delay_s: Seconds = 0.5
    miss_rate: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.0


class Block(_Strict):
    zone: Id
    from_s: Seconds = 0.0
    to_s: Seconds | None = None
    """None: until the end of the run."""

    @model_validator(mode="after")
    def _ordered(self) -> Block:
        if self.to_s is not None and self.to_s <= self.from_s:
            raise ValueError("to_s must be after from_s")
        return self


class Raffle(_Strict):
    route: Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]{1,32}->[A-Za-z0-9_-]{1,32}$")]
    """`A->B`, a route of the site file."""
    start_s: Seconds = 0.0
    every_s: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    hold_s: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    """How long each draw's zones stay blocked; default: until the next draw."""
    count: Annotated[int, Field(ge=1, le=100_000)]

    @model_validator(mode="after")
    def _hold_fits(self) -> Raffle:
        if self.hold_s is not None and self.hold_s > self.every_s:
            raise ValueError("hold_s must not exceed every_s (draws would overlap)")
        return self


class Failure(_Strict):
    node: Id
    at_s: Seconds
    kind: Literal["kill", "hang", "reboot"]


class Scenario(_Strict):
    duration_s: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    seed: int | None = None
    sensor: SensorSpec = SensorSpec()
    blocks: list[Block] = Field(default_factory=list)
    raffles: list[Raffle] = Field(default_factory=list)
    failures: list[Failure] = Field(default_factory=list)

    def check_against(self, spec: SiteFile) -> None:
        """Raise ValueError naming the key of the first zone, node or route the site does not have."""
        zones = {z.id for z in spec.zones}
        nodes = {n.id for n in spec.nodes}
        for i, block in enumerate(self.blocks):
            if block.zone not in zones:
                raise ValueError(f"blocks[{i}].zone: unknown zone {block.zone!r} (site {spec.name})")
        for i, raffle in enumerate(self.raffles):
            try:
                find_route(spec, raffle.route)
            except RaffleError as exc:
                raise ValueError(f"raffles[{i}].route: {exc}") from None
        for i, failure in enumerate(self.failures):
            if failure.node not in nodes:
                raise ValueError(f"failures[{i}].node: unknown node {failure.node!r} (site {spec.name})")

    def timeline(self, spec: SiteFile, seed: int) -> list[Event]:
        """Every event of the scenario, sorted by time (a clear before a block at the same instant)."""
        events: list[Event] = []
        for block in self.blocks:
            events.append(Event(block.from_s, "block", block.zone))
            if block.to_s is not None:
                events.append(Event(block.to_s, "clear", block.zone))
        for raffle in self.raffles:
            hold = raffle.hold_s if raffle.hold_s is not None else raffle.every_s
            for k, zone_set in enumerate(draws(spec, raffle.route, seed, raffle.count)):
                start = raffle.start_s + k * raffle.every_s
                for zone in zone_set:
                    events.append(Event(start, "block", zone, f"{raffle.route} draw {k}"))
                    events.append(Event(start + hold, "clear", zone, f"{raffle.route} draw {k}"))
        for failure in self.failures:
            events.append(Event(failure.at_s, failure.kind, failure.node))
        order = {"clear": 0, "block": 1, "kill": 2, "hang": 2, "reboot": 3}
        return sorted(events, key=lambda e: (e.t, order[e.kind]))


@dataclass(frozen=True)
class Event:
    t: float
    kind: Literal["block", "clear", "kill", "hang", "reboot"]
    target: str
    """A zone for block/clear, a node otherwise."""
    why: str = ""


def blocks_scenario(zones: list[str], duration_s: float | None = None) -> Scenario:
    """`--block z4 ...`: the zones blocked from the start to the end."""
    return Scenario(duration_s=duration_s, blocks=[Block(zone=z) for z in zones])


def load_scenario(path: Path, spec: SiteFile) -> Scenario:
    """Parse and check a scenario file against the site; raises ScenarioError (one line) on any problem."""
    raw = read_yaml_mapping(path, ScenarioError, "a scenario file")
    try:
        scenario = Scenario.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in err["loc"]).lstrip(".")
        msg = str(err["msg"]).removeprefix("Value error, ")
        raise ScenarioError(f"{path}: {key or '(file)'}: {msg}") from None
    try:
        scenario.check_against(spec)
    except ValueError as exc:
        raise ScenarioError(f"{path}: {exc}") from None
    return scenario
