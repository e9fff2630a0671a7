"""The simulated world: the site's map plus the obstacles a scenario placed in zones, with when and for how long.

An obstacle fills its zone's polygon (the paper's obstacles close the corridor completely). The history is
kept as time intervals per zone, so a sensor can be asked what it saw at any past instant of the clock: the
simulator applies a scripted event at its own time even when it is stepped a little later.
"""

from __future__ import annotations

from dataclasses import dataclass

from wsnav.schemas.messages import SimObstacle, SimWorld
from wsnav.schemas.site_file import SiteFile


class WorldError(ValueError):
    """A request the world cannot honour (unknown zone); one line."""


@dataclass
class Interval:
    start: float
    end: float | None = None
    """None while the obstacle is still there."""


class World:
    """Obstacles by zone over clock time; `message()` is what simulated lidars need, as a SimWorld."""

    def __init__(self, spec: SiteFile) -> None:
        self._spec = spec
        self._polygons = {z.id: list(z.polygon) for z in spec.zones}
        self._history: dict[str, list[Interval]] = {z.id: [] for z in spec.zones}
        self.changed_at: float | None = None
        """Clock time of the last change (None before any)."""

    @property
    def zones(self) -> list[str]:
        return list(self._polygons)

    def _check(self, zone: str) -> list[Interval]:
        if zone not in self._history:
            raise WorldError(f"unknown zone {zone!r} (the site has {', '.join(self._polygons)})")
        return self._history[zone]

    def place(self, zone: str, t: float) -> bool:
        """Put an obstacle in `zone` from time `t`; False if one is already there."""
        history = self._check(zone)
        if history and history[-1].end is None:
            return False
        if history and history[-1].end is not None and t < history[-1].end:
            raise WorldError(f"zone {zone}: obstacle placed at t={t:g} before the last one left")
        history.append(Interval(t))
        self.changed_at = t
        return True

    def remove(self, zone: str, t: float) -> bool:
        """Take the obstacle out of `zone` at time `t`; False if there was none."""
        history = self._check(zone)
        if not history or history[-1].end is not None:
            return False
        history[-1].end = max(t, history[-1].start)
        self.changed_at = t
        return True

    def blocked(self, zone: str) -> bool:
        """Whether an obstacle is in `zone` now (after the last change)."""
        history = self._check(zone)
        return bool(history) and history[-1].end is None

    def blocked_zones(self) -> list[str]:
        return [z for z in self._polygons if self.blocked(z)]

    def was_blocked(self, zone: str, t: float) -> bool:
        """Whether an obstacle stood in `zone` at time `t` (intervals are [start, end))."""
        for interval in reversed(self._history[zone]):
            if interval.start <= t:
                return interval.end is None or t < interval.end
        return False

    def message(self, t: float) -> SimWorld:
        """The whole obstacle set now: each blocked zone's polygon, the obstacle named after its zone."""
        obstacles = [SimObstacle(id=z, zone=z, polygon=self._polygons[z]) for z in self.blocked_zones()]
        return SimWorld(t=t, obstacles=obstacles)
