"""Generate the school floor's ROS map (map.pgm + map.yaml) from its vector description (layout.yaml).

The map is a build product of the layout so that walls, doors and corridor widths are reviewed as numbers,
not pixels. Output is deterministic: same layout, same bytes (a test regenerates and compares).

Usage: python sites/school/generate.py [--layout FILE] [--out DIR]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError

HERE = Path(__file__).resolve().parent
FREE_PIXEL, OCCUPIED_PIXEL, UNKNOWN_PIXEL = 254, 0, 205
"""map_server's conventions for a trinary map saved by map_saver."""

Rect = tuple[float, float, float, float]
XY = tuple[float, float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MapSpec(_Strict):
    resolution: Annotated[float, Field(gt=0)]
    origin: tuple[float, float, float]
    size: tuple[Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)]]


class Building(_Strict):
    rect: Rect
    thickness: Annotated[float, Field(gt=0)]


class Door(_Strict):
    side: Literal["south", "north", "west", "east"]
    at: float
    width: Annotated[float, Field(gt=0)] | None = None


class Room(_Strict):
    name: str
    rect: Rect
    thickness: Annotated[float, Field(gt=0)] | None = None
    doors: list[Door] = Field(default_factory=list)


class Wall(_Strict):
    from_: XY = Field(alias="from")
    to: XY
    thickness: Annotated[float, Field(gt=0)] | None = None


class Layout(_Strict):
    map: MapSpec
    building: Building
    wall_thickness: Annotated[float, Field(gt=0)]
    door_width: Annotated[float, Field(gt=0)]
    rooms: list[Room] = Field(default_factory=list)
    walls: list[Wall] = Field(default_factory=list)
    blocks: list[Rect] = Field(default_factory=list)


class Raster:
    """Cell-centre geometry of the output grid (row 0 = bottom, as nav_msgs/OccupancyGrid)."""

    def __init__(self, spec: MapSpec) -> None:
        self.resolution = spec.resolution
        self.width = round(spec.size[0] / spec.resolution)
        self.height = round(spec.size[1] / spec.resolution)
        self.x = spec.origin[0] + (np.arange(self.width) + 0.5) * spec.resolution
        self.y = spec.origin[1] + (np.arange(self.height) + 0.5) * spec.resolution

    def rect_mask(self, x0: float, y0: float, x1: float, y1: float) -> NDArray[np.bool_]:
        xs = (self.x >= min(x0, x1)) & (self.x <= max(x0, x1))
        ys = (self.y >= min(y0, y1)) & (self.y <= max(y0, y1))
        return ys[:, None] & xs[None, :]

    def segment_mask(self, a: XY, b: XY, thickness: float) -> NDArray[np.bool_]:
        """Cells whose centre lies in the segment's stroke: `thickness` wide, square caps of half that."""
        half = thickness / 2
        (ax, ay), (bx, by) = a, b
        length = float(np.hypot(bx - ax, by - ay))
        if length == 0:
            return self.rect_mask(ax - half, ay - half, ax + half, ay + half)
        ux, uy = (bx - ax) / length, (by - ay) / length
        dx = self.x[None, :] - ax
        dy = self.y[:, None] - ay
        along = dx * ux + dy * uy
        across = -dx * uy + dy * ux
        return (along >= -half) & (along <= length + half) & (np.abs(across) <= half)


def room_walls(room: Room, layout: Layout) -> list[tuple[XY, XY, float]]:
    """The room's four sides as segments, each side split around its doors."""
    x0, y0, x1, y1 = room.rect
    t = room.thickness or layout.wall_thickness
    sides: dict[str, tuple[XY, XY]] = {
        "south": ((x0, y0), (x1, y0)),
        "north": ((x0, y1), (x1, y1)),
        "west": ((x0, y0), (x0, y1)),
        "east": ((x1, y0), (x1, y1)),
    }
    out: list[tuple[XY, XY, float]] = []
    for side, (a, b) in sides.items():
        horizontal = side in ("south", "north")
        lo, hi = (a[0], b[0]) if horizontal else (a[1], b[1])
        gaps = sorted(
            (d.at - (d.width or layout.door_width) / 2, d.at + (d.width or layout.door_width) / 2)
            for d in room.doors
            if d.side == side
        )
        for g0, g1 in gaps:
            if not lo < g0 < g1 < hi:
                raise ValueError(f"room {room.name}: door at {(g0 + g1) / 2:g} does not fit its {side} side")
        pieces: list[tuple[float, float]] = []
        start = lo
        for g0, g1 in gaps:
            pieces.append((start, g0))
            start = g1
        pieces.append((start, hi))
        for p0, p1 in pieces:
            # Square caps would reach half a thickness into the door; pull the ends back by that much.
            c0 = p0 if p0 == lo else p0 + t / 2
            c1 = p1 if p1 == hi else p1 - t / 2
            if c1 < c0:
                continue
            if horizontal:
                out.append(((c0, a[1]), (c1, a[1]), t))
            else:
                out.append(((a[0], c0), (a[0], c1), t))
    return out


def rasterise(layout: Layout) -> NDArray[np.uint8]:
    """Pixels of the map image, top row first (as a PGM stores them)."""
    raster = Raster(layout.map)
    pixels = np.full((raster.height, raster.width), UNKNOWN_PIXEL, dtype=np.uint8)
    bx0, by0, bx1, by1 = layout.building.rect
    pixels[raster.rect_mask(bx0, by0, bx1, by1)] = FREE_PIXEL
    occupied = np.zeros_like(pixels, dtype=bool)
    corners = [(bx0, by0), (bx1, by0), (bx1, by1), (bx0, by1)]
    for a, b in zip(corners, corners[1:] + corners[:1], strict=True):
        occupied |= raster.segment_mask(a, b, layout.building.thickness)
    for room in layout.rooms:
        for a, b, t in room_walls(room, layout):
            occupied |= raster.segment_mask(a, b, t)
    for wall in layout.walls:
        occupied |= raster.segment_mask(wall.from_, wall.to, wall.thickness or layout.wall_thickness)
    for x0, y0, x1, y1 in layout.blocks:
        occupied |= raster.rect_mask(x0, y0, x1, y1)
    pixels[occupied] = OCCUPIED_PIXEL
    return np.ascontiguousarray(np.flipud(pixels))


def pgm_bytes(pixels: NDArray[np.uint8]) -> bytes:
    height, width = pixels.shape
    return f"P5\n{width} {height}\n255\n".encode("ascii") + pixels.tobytes()


def map_yaml_text(layout: Layout, image_name: str) -> str:
    ox, oy, oyaw = layout.map.origin
    return (
        "# Generated by sites/school/generate.py from layout.yaml: edit the layout, not this file.\n"
        f"image: {image_name}\n"
        "mode: trinary\n"
        f"resolution: {layout.map.resolution}\n"
        f"origin: [{ox}, {oy}, {oyaw}]\n"
        "negate: 0\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
    )


def load_layout(path: Path) -> Layout:
    return Layout.model_validate(yaml.safe_load(path.read_text()))


def generate(layout_path: Path, out_dir: Path) -> tuple[Path, Path]:
    """Write map.pgm and map.yaml into out_dir; returns their paths."""
    layout = load_layout(layout_path)
    out_dir.mkdir(parents=True, exist_ok=True)
    pgm, meta = out_dir / "map.pgm", out_dir / "map.yaml"
    pgm.write_bytes(pgm_bytes(rasterise(layout)))
    meta.write_text(map_yaml_text(layout, pgm.name))
    return pgm, meta


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--layout", type=Path, default=HERE / "layout.yaml")
    parser.add_argument("--out", type=Path, default=HERE)
    args = parser.parse_args(argv)
    try:
        pgm, meta = generate(args.layout, args.out)
    except (OSError, yaml.YAMLError, ValidationError, ValueError) as exc:
        print(f"generate.py: error: {args.layout}: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    print(f"wrote {pgm} and {meta}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
