"""costmap_2d's StaticLayer, transcribed from its C++ (ROS 1 navigation, static_layer.cpp and costmap_layer.cpp) for
tests: what a stock move_base makes of the zone grid. Written from the C++, not from ros_bridge's code, so that a
test comparing the two can fail.

  interpretValue: v == unknown_cost_value -> NO_INFORMATION (track_unknown_space) or FREE_SPACE;
                  v >= lethal_threshold -> LETHAL; trinary -> FREE_SPACE; else (v / lethal_threshold) * 254
  incomingMap:    every cell interpreted; bounds = the whole map
  incomingUpdate: the window's cells interpreted; bounds = that window (x_, y_, width_, height_ overwritten)
  updateCosts with use_maximum (updateWithMax): within the bounds, skip NO_INFORMATION, else take the layer's
                  cost where the master's is NO_INFORMATION or lower
  LayeredCostmap (LayeredModel below): the first map sizes the master; a map whose size, resolution or origin
                  differs from the master's by anything (`!=`) resizes the master and every layer, which wipes
                  what the others held (the walls); first_map_only shuts the map subscriber after the first map
                  (updates still come); onInitialize blocks until the layer has its first map.
Left out: rolling windows, the obstacle and inflation layers, parameter reading (ros_bridge/costmap_params.py
carries the defaults), threads and timing.
"""

from __future__ import annotations

from dataclasses import dataclass

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
    def __init__(self, first_map_only: bool = False) -> None:
        self.first_map_only = first_map_only
        self.map_received = False
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
        self.map_received = True

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


@dataclass(frozen=True)
class MapMeta:
    width: int
    height: int
    resolution: float
    origin_x: float
    origin_y: float


class LayeredModel:
    """The master and its StaticLayers as LayeredCostmap ties them (static_layer.cpp incomingMap, onInitialize)."""

    def __init__(self) -> None:
        self.meta: MapMeta | None = None
        self.layers: dict[str, StaticLayerModel] = {}

    def add_layer(self, name: str, first_map_only: bool = False) -> StaticLayerModel:
        self.layers[name] = StaticLayerModel(first_map_only)
        return self.layers[name]

    @property
    def initialized(self) -> bool:
        """move_base's costmap starts only once every StaticLayer has had its first map."""
        return all(layer.map_received for layer in self.layers.values())

    def incoming_map(self, name: str, meta: MapMeta, data: list[int] | tuple[int, ...]) -> bool:
        """A full map on layer `name`'s topic; False if the layer no longer listens (first_map_only)."""
        layer = self.layers[name]
        if layer.first_map_only and layer.map_received:
            return False
        if self.meta != meta:  # resizeMap on the master and on every layer: each is reset to its default
            self.meta = meta
            for other in self.layers.values():
                if other.costmap is not None:
                    other.costmap = np.full((meta.height, meta.width), NO_INFORMATION, dtype=np.uint8)
                    other.bounds = (0, 0, meta.width, meta.height)
                    other.has_updated_data = True
        layer.incoming_map(meta.width, meta.height, data)
        return True
