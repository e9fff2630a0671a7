"""costmap_2d's StaticLayer, transcribed from its C++ (ROS 1 navigation, static_layer.cpp and costmap_layer.cpp) for
tests: what a stock move_base makes of the zone grid. Written from the C++, not from ros_bridge's code, so that a
test comparing the two can fail.

  interpretValue: v == unknown_cost_value -> NO_INFORMATION (track_unknown_space) or FREE_SPACE;
                  v >= lethal_threshold -> LETHAL; trinary -> FREE_SPACE; else (v / lethal_threshold) * 254
  incomingMap:    every cell interpreted; bounds = the whole map
  incomingUpdate: the window's cells interpreted; bounds = that window (x_, y_, width_, height_ overwritten)
  updateCosts with use_maximum (updateWithMax): within the bounds, skip NO_INFORMATION, else take the layer's
                  cost where the master's is NO_INFORMATION or lower
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

NO_INFORMATION, LETHAL, FREE = 255, 254, 0


def interpret_value(value: int, lethal_threshold: int = 100, track_unknown: bool = True) -> int:
    v = value & 0xFF  # the C++ reads the int8 as unsigned char
    if v == 255:  # unknown_cost_value -1, stored as unsigned char
        return NO_INFORMATION if track_unknown else FREE
    if v >= lethal_threshold:
        return LETHAL
    return int(float(v) / lethal_threshold * LETHAL)


class StaticLayerModel:
    def __init__(self) -> None:
        self.costmap: NDArray[np.uint8] | None = None
        self.bounds: tuple[int, int, int, int] | None = None
        """x_, y_, width_, height_: what the next updateBounds reports."""
        self.has_updated_data = False

    def incoming_map(self, width: int, height: int, data: list[int] | tuple[int, ...]) -> None:
        table = np.array([interpret_value(v) for v in range(256)], dtype=np.uint8)
        values = np.asarray(data, dtype=np.int16).astype(np.uint8)
        self.costmap = table[values].reshape(height, width)
        self.bounds = (0, 0, width, height)
        self.has_updated_data = True

    def incoming_update(
        self, x: int, y: int, width: int, height: int, data: list[int] | tuple[int, ...]
    ) -> None:
        assert self.costmap is not None, "update before map"
        values = np.asarray(data, dtype=np.int16).reshape(height, width)
        for r in range(height):
            for c in range(width):
                self.costmap[y + r, x + c] = interpret_value(int(values[r, c]))
        self.bounds = (x, y, width, height)
        self.has_updated_data = True

    def update_master_with_max(self, master: NDArray[np.uint8], walls: NDArray[np.uint8]) -> None:
        """One costmap cycle: updateBounds (only if data came), the master reset to the layers below (`walls`,
        the map's StaticLayer) within those bounds, then updateWithMax within them."""
        if not self.has_updated_data or self.bounds is None or self.costmap is None:
            return
        x, y, w, h = self.bounds
        self.has_updated_data = False
        master[y : y + h, x : x + w] = walls[y : y + h, x : x + w]
        window = master[y : y + h, x : x + w]
        layer = self.costmap[y : y + h, x : x + w]
        take = (layer != NO_INFORMATION) & ((window == NO_INFORMATION) | (window < layer))
        window[take] = layer[take]
