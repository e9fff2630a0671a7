"""Zone polygons (metres, map frame) as cell masks of a grid, the way costmap_2d fills a polygon.

A cell belongs to a zone when its centre lies inside the polygon or the polygon's outline crosses it
(costmap_2d's `setConvexPolygonCost` marks outline cells too), so a zone drawn from wall to wall closes the
passage with no gap of free cells. Kept separate and small: the planner's CLI and the zone layer share it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.path import Path as MplPath
from numpy.typing import NDArray

from wsnav.schemas.ros_map import OccupancyGrid

Polygon = Sequence[tuple[float, float]] | Sequence[Sequence[float]]


@dataclass(frozen=True)
class GridFrame:
    """Where a grid sits in the world: row 0 at origin y (map bottom), square cells of `resolution` metres."""

    width: int
    height: int
    resolution: float
    origin_x: float
    origin_y: float

    @staticmethod
    def of_grid(grid: OccupancyGrid) -> GridFrame:
        return GridFrame(grid.width, grid.height, grid.resolution, grid.origin[0], grid.origin[1])

    def world_to_cell(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the cell containing a world point; may lie outside the grid."""
        col = int(np.floor((x - self.origin_x) / self.resolution))
        row = int(np.floor((y - self.origin_y) / self.resolution))
        return row, col

    def world_to_cells(
        self, xs: NDArray[np.float64], ys: NDArray[np.float64]
    ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """`world_to_cell` for arrays of points: (rows, cols), which may lie outside the grid."""
        cols = np.floor((xs - self.origin_x) / self.resolution).astype(np.intp)
        rows = np.floor((ys - self.origin_y) / self.resolution).astype(np.intp)
        return rows, cols

    def cell_to_world(self, row: int, col: int) -> tuple[float, float]:
        """Centre of a cell in metres."""
        return self.origin_x + (col + 0.5) * self.resolution, self.origin_y + (row + 0.5) * self.resolution

    def contains_cell(self, row: int, col: int) -> bool:
        return 0 <= row < self.height and 0 <= col < self.width


@dataclass(frozen=True)
class CellWindow:
    """A polygon's cells inside its bounding window: mask[r, c] is grid cell (row0 + r, col0 + c)."""

    row0: int
    col0: int
    mask: NDArray[np.bool_]

    @property
    def rows(self) -> slice:
        return slice(self.row0, self.row0 + self.mask.shape[0])

    @property
    def cols(self) -> slice:
        return slice(self.col0, self.col0 + self.mask.shape[1])

    @property
    def empty(self) -> bool:
        return self.mask.size == 0 or not bool(self.mask.any())


@dataclass(frozen=True)
class Bounds:
    """A rectangle of cells, rows [row0, row1) x cols [col0, col1): what a costmap update touched."""

    row0: int
    col0: int
    row1: int
    col1: int

    @property
    def rows(self) -> slice:
        return slice(self.row0, self.row1)

    @property
    def cols(self) -> slice:
        return slice(self.col0, self.col1)

    @property
    def empty(self) -> bool:
        return self.row1 <= self.row0 or self.col1 <= self.col0

    @property
    def shape(self) -> tuple[int, int]:
        return max(self.row1 - self.row0, 0), max(self.col1 - self.col0, 0)

    def grow(self, cells: int, frame: GridFrame) -> Bounds:
        """These bounds widened by `cells` on every side, clipped to the grid."""
        return Bounds(
            max(self.row0 - cells, 0),
            max(self.col0 - cells, 0),
            min(self.row1 + cells, frame.height),
            min(self.col1 + cells, frame.width),
        )

    def union(self, other: Bounds | None) -> Bounds:
        if other is None or other.empty:
            return self
        if self.empty:
            return other
        return Bounds(
            min(self.row0, other.row0),
            min(self.col0, other.col0),
            max(self.row1, other.row1),
            max(self.col1, other.col1),
        )

    def intersection(self, other: Bounds) -> Bounds:
        """The common cells (empty bounds if none)."""
        return Bounds(
            max(self.row0, other.row0),
            max(self.col0, other.col0),
            min(self.row1, other.row1),
            min(self.col1, other.col1),
        )

    def within(self, outer: Bounds) -> tuple[slice, slice]:
        """Slices that pick these bounds out of an array covering `outer` (which must contain them)."""
        return (
            slice(self.row0 - outer.row0, self.row1 - outer.row0),
            slice(self.col0 - outer.col0, self.col1 - outer.col0),
        )

    @staticmethod
    def of_window(window: CellWindow) -> Bounds:
        return Bounds(
            window.row0, window.col0, window.row0 + window.mask.shape[0], window.col0 + window.mask.shape[1]
        )


def polygon_window(polygon: Polygon, frame: GridFrame) -> CellWindow:
    """The polygon's cells, clipped to the grid, in the smallest window that holds them.

    Returning a window rather than a full-size mask lets a zone layer update only the bounds that changed.
    """
    pts = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    res = frame.resolution
    # Continuous cell coordinates (col, row) of the vertices.
    cc = (pts[:, 0] - frame.origin_x) / res
    rr = (pts[:, 1] - frame.origin_y) / res
    c0 = max(int(np.floor(cc.min())), 0)
    c1 = min(int(np.floor(cc.max())), frame.width - 1)
    r0 = max(int(np.floor(rr.min())), 0)
    r1 = min(int(np.floor(rr.max())), frame.height - 1)
    if c1 < c0 or r1 < r0:
        return CellWindow(row0=0, col0=0, mask=np.zeros((0, 0), dtype=bool))
    shape = (r1 - r0 + 1, c1 - c0 + 1)
    cols, rows = np.meshgrid(np.arange(c0, c1 + 1) + 0.5, np.arange(r0, r1 + 1) + 0.5)
    centres = np.column_stack([cols.ravel(), rows.ravel()])
    inside = MplPath(np.column_stack([cc, rr])).contains_points(centres).reshape(shape)
    inside |= _outline(cc, rr, r0, c0, shape)
    return CellWindow(row0=r0, col0=c0, mask=inside)


def _outline(
    cc: NDArray[np.float64], rr: NDArray[np.float64], r0: int, c0: int, shape: tuple[int, int]
) -> NDArray[np.bool_]:
    """Cells the polygon's edges pass through, sampled at a quarter cell (enough for cells 1 wide).

    Each edge is clipped to the window first, so the work is bounded by the window, not by the edge's length
    (an operator block reaching 1e6 m used to be sampled in full: seconds of CPU and gigabytes)."""
    out = np.zeros(shape, dtype=bool)
    n = len(cc)
    box = (float(c0), float(c0 + shape[1]), float(r0), float(r0 + shape[0]))
    for i in range(n):
        clipped = _clip_segment(cc[i], rr[i], cc[(i + 1) % n], rr[(i + 1) % n], box)
        if clipped is None:
            continue
        xa, ya, xb, yb = clipped
        steps = int(np.ceil(max(abs(xb - xa), abs(yb - ya)) * 4)) + 1
        t = np.linspace(0.0, 1.0, steps + 1)
        cols = np.floor(xa + (xb - xa) * t).astype(np.int64) - c0
        rows = np.floor(ya + (yb - ya) * t).astype(np.int64) - r0
        keep = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
        out[rows[keep], cols[keep]] = True
    return out


def _clip_segment(
    xa: float, ya: float, xb: float, yb: float, box: tuple[float, float, float, float]
) -> tuple[float, float, float, float] | None:
    """The part of segment a-b inside box (xmin, xmax, ymin, ymax), or None (Liang-Barsky)."""
    xmin, xmax, ymin, ymax = box
    dx, dy = xb - xa, yb - ya
    t0, t1 = 0.0, 1.0
    for p, q in ((-dx, xa - xmin), (dx, xmax - xa), (-dy, ya - ymin), (dy, ymax - ya)):
        if p == 0:
            if q < 0:
                return None
            continue
        t = q / p
        if p < 0:
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
        if t0 > t1:
            return None
    return xa + t0 * dx, ya + t0 * dy, xa + t1 * dx, ya + t1 * dy
