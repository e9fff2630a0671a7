"""Load a site (site.yaml plus its ROS map) and check it whole: every error names file, key and problem.

This is the one loader every component uses, so a site that passes `wsnav site check` works everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import ValidationError

from wsnav.schemas.site_file import SiteFile
from wsnav.schemas.yaml_file import read_yaml_mapping

if TYPE_CHECKING:  # the map (numpy, Pillow) loads with `load_site` only: a broker needs the site file alone
    from wsnav.schemas.ros_map import OccupancyGrid

SITE_FILE_NAME = "site.yaml"


class SiteError(ValueError):
    """A site that cannot be used; str() is one line: `<file>: <key>: <problem>`."""


@dataclass(frozen=True)
class Site:
    path: Path
    """The site.yaml file."""
    spec: SiteFile
    grid: OccupancyGrid

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def directory(self) -> Path:
        return self.path.parent

    def point(self, name: str) -> tuple[float, float, float]:
        x, y, yaw = self.spec.points[name]
        return x, y, yaw


def site_file_path(location: str | Path) -> Path:
    """Accept either a site directory or the site.yaml inside it."""
    path = Path(location)
    return path / SITE_FILE_NAME if path.is_dir() else path


def load_site_file(location: str | Path) -> SiteFile:
    """The site file alone, validated but not against its map (what the broker needs: no numpy, no image);
    raises SiteError (one line) on any problem."""
    return _parse(site_file_path(location))


def load_site(location: str | Path) -> Site:
    """Parse, validate against the map, and return the site; raises SiteError (one line) on any problem."""
    from wsnav.schemas.ros_map import MapError, load_map

    path = site_file_path(location)
    spec = _parse(path)
    map_path = Path(spec.map) if Path(spec.map).is_absolute() else path.parent / spec.map
    try:
        grid = load_map(map_path)
    except MapError as exc:
        raise SiteError(f"{path}: map: {exc}") from None
    _check_against_map(path, spec, grid)
    return Site(path=path, spec=spec, grid=grid)


def _parse(path: Path) -> SiteFile:
    raw = read_yaml_mapping(path, SiteError, "a site file")
    try:
        return SiteFile.model_validate(raw)
    except ValidationError as exc:
        raise SiteError(f"{path}: {_describe(exc, raw)}") from None


def _describe(exc: ValidationError, raw: dict[str, object]) -> str:
    """The first error as `key[i] (id).sub: message`: the id names the list item a reader should look at."""
    err = exc.errors()[0]
    loc = [p for p in err["loc"] if not (isinstance(p, str) and p in ("pir", "ir_beam", "hcsr04"))]
    msg = str(err["msg"]).removeprefix("Value error, ")
    key = ""
    node: object = raw
    for part in loc:
        key += f"[{part}]" if isinstance(part, int) else (f".{part}" if key else str(part))
        if isinstance(node, dict):
            node = node.get(str(part))
        elif isinstance(node, list) and isinstance(part, int) and part < len(node):
            node = node[part]
            if isinstance(node, dict) and "id" in node:
                key += f" ({node['id']})"
        else:
            node = None
    return f"{key}: {msg}" if key else msg


def _check_against_map(path: Path, spec: SiteFile, grid: OccupancyGrid) -> None:
    from wsnav.schemas.ros_map import FREE

    x0, y0, x1, y1 = grid.bounds
    extent = f"the map spans x {x0:g}..{x1:g}, y {y0:g}..{y1:g}"
    for i, zone in enumerate(spec.zones):
        for x, y in zone.polygon:
            if not (x0 <= x <= x1 and y0 <= y <= y1):
                raise SiteError(
                    f"{path}: zones[{i}] ({zone.id}): vertex [{x:g}, {y:g}] lies outside the map ({extent})"
                )
    for i, node in enumerate(spec.nodes):
        if node.position is not None and not grid.contains(*node.position):
            x, y = node.position
            raise SiteError(
                f"{path}: nodes[{i}] ({node.id}).position: [{x:g}, {y:g}] lies outside the map ({extent})"
            )
    for name, (x, y, _yaw) in spec.points.items():
        if not grid.contains(x, y):
            raise SiteError(f"{path}: points.{name}: [{x:g}, {y:g}] lies outside the map ({extent})")
        row, col = grid.world_to_cell(x, y)
        value = int(grid.data[row, col])
        if value != FREE:
            what = "unknown space" if value < 0 else "a wall"
            raise SiteError(f"{path}: points.{name}: [{x:g}, {y:g}] lies inside {what}")
