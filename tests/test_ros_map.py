"""Maps load exactly as ROS map_server loads them, including maps drawn by others."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.conftest import SITES
from tests.site_fixtures import write_pgm
from wsnav.schemas.ros_map import FREE, OCCUPIED, UNKNOWN, MapError, load_map


def _yaml(path: Path, image: str, **keys: object) -> Path:
    fields = {
        "image": image,
        "resolution": 0.1,
        "origin": "[-1.0, 2.0, 0.0]",
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
        **keys,
    }
    path.write_text("".join(f"{k}: {v}\n" for k, v in fields.items()))
    return path


def test_pgm_with_comment_is_classified_and_flipped(tmp_path: Path) -> None:
    px = np.array([[0, 254, 205], [254, 254, 254]], dtype=np.uint8)  # top image row holds the wall
    write_pgm(tmp_path / "m.pgm", px, comment="# CREATOR: GIMP PNM Filter Version 1.1")
    grid = load_map(_yaml(tmp_path / "m.yaml", "m.pgm"))
    assert grid.data.shape == (2, 3)
    assert grid.data[1].tolist() == [OCCUPIED, FREE, UNKNOWN]  # row 1 = top of the image = highest y
    assert grid.data[0].tolist() == [FREE, FREE, FREE]
    assert grid.bounds == pytest.approx((-1.0, 2.0, -0.7, 2.2))
    assert grid.occupied(-0.95, 2.15) and not grid.occupied(-0.95, 2.05)


def test_negate_swaps_free_and_occupied(tmp_path: Path) -> None:
    write_pgm(tmp_path / "m.pgm", np.array([[0, 255]], dtype=np.uint8))
    grid = load_map(_yaml(tmp_path / "m.yaml", "m.pgm", negate=1))
    assert grid.data.tolist() == [[FREE, OCCUPIED]]


def test_scale_mode_keeps_intermediate_costs(tmp_path: Path) -> None:
    write_pgm(tmp_path / "m.pgm", np.array([[0, 128, 254]], dtype=np.uint8))
    grid = load_map(_yaml(tmp_path / "m.yaml", "m.pgm", mode="scale"))
    wall, middle, free = grid.data[0].tolist()
    assert (wall, free) == (OCCUPIED, FREE)
    assert 1 <= middle <= 99


def test_raw_mode_reads_values_directly(tmp_path: Path) -> None:
    write_pgm(tmp_path / "m.pgm", np.array([[0, 42, 100, 255]], dtype=np.uint8))
    grid = load_map(_yaml(tmp_path / "m.yaml", "m.pgm", mode="raw"))
    assert grid.data[0].tolist() == [0, 42, 100, UNKNOWN]


def test_rgba_png_averages_colour_and_uses_alpha_in_scale_mode(tmp_path: Path) -> None:
    rgba = np.array([[[0, 0, 0, 255], [255, 255, 255, 255], [120, 120, 120, 100]]], dtype=np.uint8)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "m.png")
    grid = load_map(_yaml(tmp_path / "m.yaml", "m.png", mode="scale"))
    assert grid.data[0].tolist() == [OCCUPIED, FREE, UNKNOWN]


def test_absolute_image_path(tmp_path: Path) -> None:
    write_pgm(tmp_path / "m.pgm", np.array([[254]], dtype=np.uint8))
    other = tmp_path / "elsewhere"
    other.mkdir()
    grid = load_map(_yaml(other / "m.yaml", str(tmp_path / "m.pgm")))
    assert grid.data.tolist() == [[FREE]]


@pytest.mark.parametrize(
    ("image_bytes", "keys", "expected"),
    [
        (None, {}, "map image not found"),
        (b"P5\nnot a pgm", {}, "cannot read map image"),
        (b"", {"resolution": -1}, "resolution"),
        (b"", {"free_thresh": 0.9}, "free_thresh"),
        (b"", {"mode": "fancy"}, "mode"),
    ],
)
def test_bad_maps_give_one_line(
    tmp_path: Path, image_bytes: bytes | None, keys: dict[str, object], expected: str
) -> None:
    if image_bytes is not None:
        (tmp_path / "m.pgm").write_bytes(image_bytes)
    with pytest.raises(MapError) as err:
        load_map(_yaml(tmp_path / "m.yaml", "m.pgm", **keys))
    assert expected in str(err.value)
    assert "\n" not in str(err.value)


NAV2_MAPS = {
    "depot": (307, 604, 0.05),
    "depot_keepout": (307, 604, 0.05),
    "warehouse": (1674, 1006, 0.03),
    "warehouse_keepout": (1674, 1006, 0.03),
    "tb3_sandbox": (384, 384, 0.05),
}


@pytest.mark.parametrize("name", sorted(NAV2_MAPS))
def test_maps_drawn_by_others_load(name: str) -> None:
    grid = load_map(SITES / "nav2_maps" / f"{name}.yaml")
    height, width, resolution = NAV2_MAPS[name]
    assert (grid.height, grid.width, grid.resolution) == (height, width, resolution)
    values = set(np.unique(grid.data).tolist())
    assert {FREE, OCCUPIED} <= values <= {FREE, OCCUPIED, UNKNOWN}
    assert (grid.data == FREE).mean() > 0.05


def test_warehouse_origin_is_honoured() -> None:
    grid = load_map(SITES / "nav2_maps" / "warehouse.yaml")
    assert grid.bounds[:2] == pytest.approx((-15.1, -25.0))
    assert grid.world_to_cell(-15.1 + 0.031, -25.0 + 0.061) == (2, 1)
