"""The zone layer as an OccupancyGrid that costmap_2d's StaticLayer reads back into exactly the zone layer's costs.

ROS has no message for a costmap layer, but every navigation stack reads OccupancyGrids: costmap_2d's StaticLayer
(ROS 1, and Nav2's) and Nav2's KeepoutFilter mask. A StaticLayer configured with `trinary_costmap: false`,
`track_unknown_space: true`, `use_maximum: true` turns an OccupancyGrid value v into a cost by
`interpretValue` (static_layer.cpp): -1 -> NO_INFORMATION, v >= lethal_threshold (100) -> LETHAL, otherwise
floor(v / 100 * 254). So each zone cost is sent as the smallest value that maps back onto it; a cost no value
maps onto (e.g. 1, 3, 6) is refused when the bridge starts, with the nearest ones that work.

Merged with `use_maximum` (updateWithMax), a clear zone (0) leaves walls as they are and a NO_INFORMATION cell
changes nothing in the master: costmap_2d skips it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wsnav.zones.cost_values import FREE_SPACE, LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import Bounds

UNREPRESENTABLE = -128
"""Marks a cost in the encoding table that no OccupancyGrid value turns into."""


@dataclass(frozen=True)
class StaticLayerParams:
    """The costmap_2d StaticLayer parameters that decide how an OccupancyGrid value becomes a cost."""

    track_unknown_space: bool = True
    lethal_cost_threshold: int = 100
    unknown_cost_value: int = -1
    trinary_costmap: bool = False


ZONE_GRID_PARAMS = StaticLayerParams()
"""What docs/ros.md tells users to configure for the zone grid's StaticLayer."""


def interpret_value(value: int, params: StaticLayerParams = ZONE_GRID_PARAMS) -> int:
    """costmap_2d::StaticLayer::interpretValue: one OccupancyGrid value (int8) to a cost (0..255).

    The C++ reads the int8 as an unsigned char and compares it with `unknown_cost_value` stored the same way.
    """
    v = value & 0xFF
    unknown = params.unknown_cost_value & 0xFF
    lethal = max(min(params.lethal_cost_threshold, 100), 0)
    if v == unknown:
        return NO_INFORMATION if params.track_unknown_space else FREE_SPACE
    if v >= lethal:
        return LETHAL_OBSTACLE
    if params.trinary_costmap:
        return FREE_SPACE
    return int(v / lethal * LETHAL_OBSTACLE)  # C++: double to unsigned char truncates


def decode_table(params: StaticLayerParams = ZONE_GRID_PARAMS) -> NDArray[np.uint8]:
    """interpret_value for every byte value, indexed by the value read as uint8."""
    return np.array([interpret_value(v, params) for v in range(256)], dtype=np.uint8)


def _encode_table(params: StaticLayerParams) -> NDArray[np.int16]:
    """For each cost, the OccupancyGrid value that decodes to it (0 and 100 first), or UNREPRESENTABLE."""
    table = np.full(256, UNREPRESENTABLE, dtype=np.int16)
    for v in [0, 100, *range(1, 100), -1]:
        cost = interpret_value(v, params)
        if table[cost] == UNREPRESENTABLE:
            table[cost] = v
    return table


class UnrepresentableCost(ValueError):
    """A zone cost no OccupancyGrid value turns into under the StaticLayer's parameters."""


class ZoneGridCodec:
    """Zone layer costs <-> OccupancyGrid values, exact under `params` for every cost the layer may produce."""

    def __init__(self, params: StaticLayerParams = ZONE_GRID_PARAMS) -> None:
        self.params = params
        self._encode = _encode_table(params)
        self._decode = decode_table(params)

    def check(self, costs: set[int]) -> None:
        """Raise UnrepresentableCost (one line, with the nearest costs that work) for a cost with no value."""
        bad = sorted(c for c in costs if self._encode[c] == UNREPRESENTABLE)
        if not bad:
            return
        ok = np.flatnonzero(self._encode != UNREPRESENTABLE)
        hints = []
        for c in bad:
            below, above = ok[ok < c], ok[ok > c]
            near = [str(int(x)) for part in (below[-1:], above[:1]) for x in part]
            hints.append(f"{c} (nearest that work: {' or '.join(near)})")
        raise UnrepresentableCost(
            "zone cost " + ", ".join(hints) + " cannot travel through an OccupancyGrid to costmap_2d's "
            "StaticLayer (it maps value v to floor(v/100*254)): choose a representable policy.caution_cost"
        )

    def encode(self, costs: NDArray[np.uint8]) -> NDArray[np.int8]:
        """OccupancyGrid values for a window of zone costs (row 0 at the map's origin, as the message wants)."""
        values = self._encode[costs]
        if (values == UNREPRESENTABLE).any():
            self.check({int(c) for c in np.unique(costs[values == UNREPRESENTABLE])})
        return values.astype(np.int8)

    def decode(self, values: NDArray[np.int8]) -> NDArray[np.uint8]:
        """What the StaticLayer makes of OccupancyGrid values (its interpretValue for each)."""
        return self._decode[values.view(np.uint8)]


class UpdateWindow:
    """The window each OccupancyGridUpdate carries: every cell changed within the last `hold_s` seconds.

    costmap_2d's StaticLayer remembers only the LAST update's window until its next update cycle: when two
    updates arrive between two cycles, the first one's cells are written into the layer but never repainted into
    the master costmap. Each update therefore also covers the windows sent within `hold_s` before it: set it at
    least as long as the costmap's update period (1 / update_frequency).
    """

    def __init__(self, hold_s: float = 1.0) -> None:
        self.hold_s = hold_s
        self._recent: list[tuple[float, Bounds]] = []

    def add(self, changed: list[Bounds], now: float) -> Bounds | None:
        """The window to send for these changes, or None when nothing changed."""
        changed = [b for b in changed if not b.empty]
        if not changed:
            return None
        self._recent = [(t, b) for t, b in self._recent if now - t <= self.hold_s]
        window = changed[0]
        for b in changed[1:]:
            window = window.union(b)
        self._recent.append((now, window))
        for _t, b in self._recent:
            window = window.union(b)
        return window
