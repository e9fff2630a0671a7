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
from wsnav.zones.cost_values import FREE_SPACE, LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import Bounds, CellWindow, GridFrame
from wsnav.zones.intake import ZoneIntake
from wsnav.zones.last_known import LastKnownZones
from wsnav.zones.zone_rule import BlockedArea, ZoneRule

ESCAPE_COST = 200
"""What a cell lethal only because of an area the robot stands in is sent as while it drives out: passable for
navfn, but dear, as in wsnav's own navigator (navigation/behaviors/escape.py)."""


@dataclass(frozen=True)
class ZoneChange:
    window: Bounds
    cheaper: bool
    """Some cell of the window got cheaper (a zone cleared): a shorter way may have opened."""


class ZoneFeed:
    def __init__(
        self, spec: SiteFile, frame: GridFrame, memory: LastKnownZones | None = None, now: float = 0.0
    ) -> None:
        """`memory`: the last known zone states on disk (`--state-dir`), served from the start, read at `now`."""
        self.frame = frame
        self.layer = ZoneRule(spec, frame, spec.policy)
        self.intake = ZoneIntake(spec, self.layer, memory=memory)
        self.intake.restore(now)
        self.costs: NDArray[np.uint8] = self.layer.paint(
            Bounds(0, 0, frame.height, frame.width), outside=NO_INFORMATION
        )
        """The zone layer's cost of every cell of the map, as last sent: NO_INFORMATION (-1 on the grid) outside
        every zone and block, as the agent's own zone layer offers it, so costmap_2d's updateWithMax leaves the
        map there as it is (a 0 would make the map's unknown space free in move_base's master). Painted whole at
        the start: the layer starts every zone clear (or as last known), and a zone that stays so is no change."""
        self.escaping: frozenset[BlockedArea] = frozenset()
        """Blocked areas sent at ESCAPE_COST instead of lethal: the robot stands in them (`set_escape`)."""

    def subscriptions(self) -> list[str]:
        return self.intake.subscriptions()

    def take(self, messages: list[Message], now: float) -> list[ZoneChange]:
        """Apply the messages, age the layer to `now`, and return the windows whose costs changed."""
        for message in messages:
            self.intake.handle(message)
        self.layer.refresh(now)
        return self._repaint(self.layer.take_changes())

    def set_escape(self, areas: frozenset[BlockedArea]) -> list[ZoneChange]:
        """Send `areas` (and no others) at ESCAPE_COST where only they make a cell lethal; the changed windows."""
        changed = areas ^ self.escaping
        self.escaping = areas
        windows = {area: window for area, window in self.layer.blocked_areas()}
        return self._repaint([window_bounds(windows[a]) for a in changed if a in windows])

    def _repaint(self, windows: list[Bounds]) -> list[ZoneChange]:
        out: list[ZoneChange] = []
        for window in windows:
            old = self.costs[window.rows, window.cols]
            new = self.layer.paint(window, outside=NO_INFORMATION)
            if self.escaping:
                without = self.layer.paint(window, exclude=self.escaping, outside=NO_INFORMATION)
                only_theirs = (new == LETHAL_OBSTACLE) & (without != LETHAL_OBSTACLE)
                kept = np.where(without == NO_INFORMATION, 0, without)
                new = np.where(only_theirs, np.maximum(kept, ESCAPE_COST), new).astype(np.uint8)
            if np.array_equal(old, new):
                continue
            cheaper = bool((_in_master(new) < _in_master(old)).any())
            self.costs[window.rows, window.cols] = new
            out.append(ZoneChange(window, cheaper))
        return out

    def blocked_mask(self, areas: list[BlockedArea]) -> NDArray[np.bool_]:
        """The cells of `areas`, as a whole-grid mask."""
        mask = np.zeros((self.frame.height, self.frame.width), dtype=bool)
        for area, window in self.layer.blocked_areas():
            if area in areas:
                mask[window.rows, window.cols] |= window.mask
        return mask

    def blocked_areas_at(self, x: float, y: float) -> list[BlockedArea]:
        """The blocked areas whose cells hold the point."""
        row, col = self.frame.world_to_cell(x, y)
        if not self.frame.contains_cell(row, col):
            return []
        return [area for area, window in self.layer.blocked_areas() if _in_window(window, row, col)]

    def blocked_zones_at(self, x: float, y: float) -> list[str]:
        """Blocked zones and operator polygon blocks whose cells hold the point, by their display names."""
        row, col = self.frame.world_to_cell(x, y)
        if not self.frame.contains_cell(row, col):
            return []
        return [area.name for area, window in self.layer.blocked_areas() if _in_window(window, row, col)]


def window_bounds(window: CellWindow) -> Bounds:
    """The rectangle of cells a polygon's window spans."""
    return Bounds(
        window.row0, window.col0, window.row0 + window.mask.shape[0], window.col0 + window.mask.shape[1]
    )


def _in_master(costs: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """What a cost adds to move_base's master under updateWithMax: NO_INFORMATION adds nothing (as a 0 would), so a
    blocked cell turning unknown (a block lifted outside the zones, a zone gone stale) is a way that may open."""
    return np.where(costs == NO_INFORMATION, np.uint8(FREE_SPACE), costs)


def _in_window(window: CellWindow, row: int, col: int) -> bool:
    r, c = row - window.row0, col - window.col0
    return 0 <= r < window.mask.shape[0] and 0 <= c < window.mask.shape[1] and bool(window.mask[r, c])
