"""Small hand-made sites for tests: a PGM map written byte by byte, and a site.yaml over it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

FREE_PX, WALL_PX, UNKNOWN_PX = 254, 0, 205


def write_pgm(path: Path, pixels: NDArray[np.uint8], comment: str | None = "# made by a wsnav test") -> None:
    """A binary P5 PGM as map_saver writes it, with an optional comment line in the header."""
    height, width = pixels.shape
    header = "P5\n" + (f"{comment}\n" if comment else "") + f"{width} {height}\n255\n"
    path.write_bytes(header.encode() + pixels.astype(np.uint8).tobytes())


def room_pixels(width: int = 200, height: int = 100) -> NDArray[np.uint8]:
    """A walled rectangle (1-cell border) with a wall stub in the middle of the top half."""
    px = np.full((height, width), FREE_PX, dtype=np.uint8)
    px[0, :] = px[-1, :] = px[:, 0] = px[:, -1] = WALL_PX
    px[: height // 2, width // 2] = WALL_PX  # image rows from the top: the upper half of the room
    return px


def tiny_site(directory: Path, **overrides: Any) -> Path:
    """A valid 10 x 5 m site at 0.05 m with two zones, two nodes, a robot, points and a route."""
    directory.mkdir(parents=True, exist_ok=True)
    write_pgm(directory / "room.pgm", room_pixels())
    (directory / "room.yaml").write_text(
        "image: room.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    site: dict[str, Any] = {
        "name": "tiny",
        "map": "room.yaml",
        "zones": [
            {"id": "z1", "polygon": [[1, 1], [3, 1], [3, 2], [1, 2]]},
            {"id": "z2", "polygon": [[6, 1], [8, 1], [8, 2], [6, 2]]},
        ],
        "nodes": [
            {"id": "n1", "zone": "z1", "sensor": {"type": "pir", "pin": 5}},
            {"id": "n2", "zone": "z2", "sensor": {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 14}},
        ],
        "robots": [{"id": "robot1"}],
        "points": {"A": [1.0, 4.0, 0.0], "B": [9.0, 4.0]},
        "routes": [{"from": "A", "to": "B", "raffle": [["z1"], ["z2"]]}],
    }
    site.update(overrides)
    (directory / "site.yaml").write_text(yaml.safe_dump(site, sort_keys=False))
    return directory
