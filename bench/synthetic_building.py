"""A synthetic building floor of any size for the costmap and planner benchmarks: rooms off a grid of corridors.

Big real maps are rare; this one has what makes costmaps and A* work hard: long walls to inflate, doors, corridors
with alternatives. Seeded, so every run measures the same map.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wsnav.schemas.ros_map import FREE, OCCUPIED, OccupancyGrid
from wsnav.schemas.site_file import SiteFile

RESOLUTION = 0.05
BLOCK = 250
"""Cells between corridor centre lines (12.5 m)."""
CORRIDOR = 50
"""Corridor width in cells (2.5 m)."""


def building_grid(cells: int, seed: int = 1) -> OccupancyGrid:
    """A `cells` x `cells` floor at 0.05 m: corridors every 12.5 m, rooms between them, a door per room wall."""
    rng = np.random.default_rng(seed)
    data = np.full((cells, cells), FREE, dtype=np.int8)
    data[0, :] = data[-1, :] = data[:, 0] = data[:, -1] = OCCUPIED
    half = CORRIDOR // 2
    for k in range(BLOCK // 2, cells, BLOCK):
        # Walls on both sides of the horizontal and vertical corridors centred on k.
        for wall in (k - half, k + half):
            if 0 < wall < cells - 1:
                data[wall, :] = OCCUPIED
                data[:, wall] = OCCUPIED
    # Reopen the corridors where they cross, then a 1 m door into every room on every side, and a pillar.
    for k in range(BLOCK // 2, cells, BLOCK):
        lo, hi = max(k - half + 1, 1), min(k + half, cells - 1)
        data[lo:hi, 1:-1] = FREE
        data[1:-1, lo:hi] = FREE
    for r in range(BLOCK // 2, cells, BLOCK):
        for c in range(BLOCK // 2, cells, BLOCK):
            for wall in (r - half, r + half):
                if 0 < wall < cells - 1:
                    door = c + half + int(rng.integers(10, BLOCK - CORRIDOR - 30))
                    data[wall, door : min(door + 20, cells - 1)] = FREE
            for wall in (c - half, c + half):
                if 0 < wall < cells - 1:
                    door = r + half + int(rng.integers(10, BLOCK - CORRIDOR - 30))
                    data[door : min(door + 20, cells - 1), wall] = FREE
            pr, pc = r + BLOCK // 2, c + BLOCK // 2
            data[pr - 5 : pr + 5, pc - 5 : pc + 5] = OCCUPIED
    data[0, :] = data[-1, :] = data[:, 0] = data[:, -1] = OCCUPIED
    return OccupancyGrid(data, RESOLUTION, (0.0, 0.0, 0.0), Path(f"synthetic-{cells}"))


def corridor_zones(cells: int, count: int, seed: int = 2) -> SiteFile:
    """A site over the building with `count` corridor-sized zones (2.6 x 2 m, across a corridor), one node each."""
    rng = np.random.default_rng(seed)
    centres = list(range(BLOCK // 2, cells - BLOCK // 2, BLOCK)) or [cells // 2]
    zones, nodes = [], []
    for i in range(count):
        k = float(centres[int(rng.integers(len(centres)))]) * RESOLUTION
        along = float(rng.uniform(5.0, cells * RESOLUTION - 5.0))
        half_w = (CORRIDOR / 2 + 1) * RESOLUTION
        polygon = [
            (along, k - half_w),
            (along + 2.0, k - half_w),
            (along + 2.0, k + half_w),
            (along, k + half_w),
        ]
        zones.append({"id": f"z{i}", "polygon": polygon})
        nodes.append({"id": f"n{i}", "zone": f"z{i}", "sensor": {"type": "pir", "pin": 5}})
    return SiteFile.model_validate({"name": "bench", "map": "synthetic", "zones": zones, "nodes": nodes})
