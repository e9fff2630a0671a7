"""ROS map_server maps (YAML + image), read exactly as map_server reads them.

The grid follows nav_msgs/OccupancyGrid: values -1 (unknown), 0 (free) ... 100 (occupied), row 0 at the map's
origin (the image's bottom row), so cell (row, col) covers world x = origin_x + col * resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from numpy.typing import NDArray
from PIL import Image, UnidentifiedImageError
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

UNKNOWN, FREE, OCCUPIED = -1, 0, 100


class MapError(ValueError):
    """A map that cannot be used; the message names the file and the problem in one line."""


class MapYaml(BaseModel):
    """The keys of a map_server YAML file; unknown keys are tolerated as map_server tolerates them."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    image: str
    resolution: Annotated[float, Field(gt=0)]
    origin: Annotated[list[float], Field(min_length=3, max_length=3)]
    negate: Literal[0, 1] | bool = 0
    occupied_thresh: Annotated[float, Field(ge=0, le=1)] = 0.65
    free_thresh: Annotated[float, Field(ge=0, le=1)] = 0.196
    mode: Literal["trinary", "scale", "raw"] = "trinary"

    @model_validator(mode="after")
    def _thresholds(self) -> MapYaml:
        if self.free_thresh >= self.occupied_thresh:
            raise ValueError(
                f"free_thresh {self.free_thresh} must be below occupied_thresh {self.occupied_thresh}"
            )
        return self


@dataclass(frozen=True)
class OccupancyGrid:
    data: NDArray[np.int8]
    """(height, width), row 0 at origin y; values -1, 0..100 (raw mode: 0..255 stored as int16 would not fit)."""
    resolution: float
    origin: tuple[float, float, float]
    source: Path

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the map in metres."""
        x0, y0 = self.origin[0], self.origin[1]
        return x0, y0, x0 + self.width * self.resolution, y0 + self.height * self.resolution

    def world_to_cell(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the cell containing a world point; may lie outside the grid."""
        col = int(np.floor((x - self.origin[0]) / self.resolution))
        row = int(np.floor((y - self.origin[1]) / self.resolution))
        return row, col

    def cell_to_world(self, row: int, col: int) -> tuple[float, float]:
        """Centre of a cell in world coordinates."""
        return (
            self.origin[0] + (col + 0.5) * self.resolution,
            self.origin[1] + (row + 0.5) * self.resolution,
        )

    def contains(self, x: float, y: float) -> bool:
        """Whether a world point lies on the map; compared in metres, so any float (1e308, NaN) is an answer."""
        if not (math.isfinite(x) and math.isfinite(y)):
            return False
        x0, y0, x1, y1 = self.bounds
        if not (x0 <= x < x1 + self.resolution and y0 <= y < y1 + self.resolution):
            return False
        row, col = self.world_to_cell(x, y)
        return 0 <= row < self.height and 0 <= col < self.width

    def occupied(self, x: float, y: float) -> bool:
        row, col = self.world_to_cell(x, y)
        return bool(self.data[row, col] == OCCUPIED)


def load_map(yaml_path: str | Path) -> OccupancyGrid:
    """Read a map_server YAML and its image; raises MapError with one line naming the file."""
    path = Path(yaml_path)
    try:
        raw = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise MapError(f"{path}: cannot read map file: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise MapError(f"{path}: not valid YAML: {_one_line(exc)}") from None
    if not isinstance(raw, dict):
        raise MapError(f"{path}: a map file must be a YAML mapping")
    try:
        meta = MapYaml.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "map"
        raise MapError(f"{path}: {where}: {err['msg']}") from None
    image_path = Path(meta.image) if Path(meta.image).is_absolute() else path.parent / meta.image
    pixels, alpha = _read_image(image_path)
    data = _classify(pixels, alpha, meta)
    ox, oy, oyaw = meta.origin
    return OccupancyGrid(data=data, resolution=meta.resolution, origin=(ox, oy, oyaw), source=path)


def _read_image(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Grey level 0..255 per pixel (colour averaged as map_server does) and alpha in 0..1 if the image has one."""
    try:
        with Image.open(path) as img:
            img.load()
            mode = img.mode
            arr = np.asarray(img)
    except FileNotFoundError:
        raise MapError(f"{path}: map image not found") from None
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as exc:
        raise MapError(f"{path}: cannot read map image: {_one_line(exc)}") from None
    if mode in ("I;16", "I;16B", "I;16L", "I", "F"):
        top = 65535.0 if mode.startswith("I;16") or arr.max(initial=0) > 255 else 255.0
        return arr.astype(np.float64) * (255.0 / top), None
    if mode in ("1", "L", "P"):
        if mode == "P":
            with Image.open(path) as img:
                return np.asarray(img.convert("L")).astype(np.float64), None
        return arr.astype(np.float64) * (255.0 if mode == "1" else 1.0), None
    if mode == "LA":
        return arr[..., 0].astype(np.float64), arr[..., 1] / 255.0
    if mode == "RGB":
        return arr.astype(np.float64).mean(axis=2), None
    if mode == "RGBA":
        return arr[..., :3].astype(np.float64).mean(axis=2), arr[..., 3] / 255.0
    raise MapError(f"{path}: unsupported image mode {mode}")


def _classify(
    grey: NDArray[np.float64], alpha: NDArray[np.float64] | None, meta: MapYaml
) -> NDArray[np.int8]:
    """map_server's per-pixel rule, vectorised; flips rows so row 0 is the bottom of the image."""
    p = 255.0 - grey if meta.negate else grey
    if meta.mode == "raw":
        out = np.clip(np.rint(p), 0, 100).astype(np.int8)
        out[p > 100] = UNKNOWN
        return np.ascontiguousarray(np.flipud(out))
    occ = (255.0 - p) / 255.0
    out = np.full(occ.shape, UNKNOWN, dtype=np.int8)
    if meta.mode == "scale":
        ratio = (occ - meta.free_thresh) / (meta.occupied_thresh - meta.free_thresh)
        out = np.rint(1 + 98 * ratio).clip(1, 99).astype(np.int8)
        if alpha is not None:
            out[alpha < 1.0] = UNKNOWN
    out[occ > meta.occupied_thresh] = OCCUPIED
    out[occ < meta.free_thresh] = FREE
    return np.ascontiguousarray(np.flipud(out))


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__
