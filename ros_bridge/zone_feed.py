"""MQTT zone messages through the robot agent's own validating intake into its zone layer, as changed windows.

The ROS bridge keeps exactly the layer a wsnav robot keeps (same intake, same staleness and fusion rules); this is
only the bookkeeping the ROS side needs: the current costs of the whole grid, and which windows really changed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wsnav.runtime.bus import Message
from wsnav.schemas.site_file import SiteFile
from wsnav.zones.cost_values import FREE_SPACE, NO_INFORMATION
from wsnav.zones.geometry import Bounds, CellWindow, GridFrame
from wsnav.zones.intake import ZoneIntake
from wsnav.zones.zone_layer import ZoneLayer


@dataclass(frozen=True)
class ZoneChange:
    window: Bounds
    cheaper: bool
    """Some cell of the window got cheaper (a zone cleared): a shorter way may have opened."""


class ZoneFeed:
    def __init__(self, spec: SiteFile, frame: GridFrame) -> None:
        self.frame = frame
        self.layer = ZoneLayer(spec, frame, spec.policy)
        self.intake = ZoneIntake(spec, self.layer)
        self.costs: NDArray[np.uint8] = np.full((frame.height, frame.width), NO_INFORMATION, dtype=np.uint8)
        """The zone layer's cost of every cell of the map, as last sent: NO_INFORMATION (-1 on the grid) outside
        every zone and block, as the agent's own zone layer offers it, so costmap_2d's updateWithMax leaves the
        map there as it is (a 0 would make the map's unknown space free in move_base's master)."""

    def subscriptions(self) -> list[str]:
        return self.intake.subscriptions()

    def take(self, messages: list[Message], now: float) -> list[ZoneChange]:
        """Apply the messages, age the layer to `now`, and return the windows whose costs changed."""
        for message in messages:
            self.intake.handle(message)
        self.layer.refresh(now)
        out: list[ZoneChange] = []
        for window in self.layer.take_changes():
            old = self.costs[window.rows, window.cols]
            new = self.layer.paint(window, outside=NO_INFORMATION)
            if np.array_equal(old, new):
                continue
            cheaper = bool((_in_master(new) < _in_master(old)).any())
            self.costs[window.rows, window.cols] = new
            out.append(ZoneChange(window, cheaper))
        return out

    def blocked_zones_at(self, x: float, y: float) -> list[str]:
        """Blocked zones and operator polygon blocks whose cells hold the point, by their display names."""
        row, col = self.frame.world_to_cell(x, y)
        if not self.frame.contains_cell(row, col):
            return []
        return [area.name for area, window in self.layer.blocked_areas() if _in_window(window, row, col)]


def _in_master(costs: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """What a cost adds to move_base's master under updateWithMax: NO_INFORMATION adds nothing (as a 0 would), so a
    blocked cell turning unknown (a block lifted outside the zones, a zone gone stale) is a way that may open."""
    return np.where(costs == NO_INFORMATION, np.uint8(FREE_SPACE), costs)


def _in_window(window: CellWindow, row: int, col: int) -> bool:
    r, c = row - window.row0, col - window.col0
    return 0 <= r < window.mask.shape[0] and 0 <= c < window.mask.shape[1] and bool(window.mask[r, c])
