"""`wsnav site check` and `render`: good sites pass; bad ones fail with one line naming file, key and problem."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.site_fixtures import tiny_site
from wsnav.schemas.site import SiteError, load_site


def wsnav(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "wsnav.cli", *map(str, args)], capture_output=True, text=True, timeout=120
    )


def test_valid_site_passes(tmp_path: Path) -> None:
    result = wsnav("site", "check", tiny_site(tmp_path / "s"))
    assert result.returncode == 0, result.stderr
    assert "ok" in result.stdout and "2 zones" in result.stdout


def test_point_yaw_defaults_to_zero(tmp_path: Path) -> None:
    site = load_site(tiny_site(tmp_path / "s"))
    assert site.point("B") == (9.0, 4.0, 0.0)


BAD_SITES: list[tuple[str, dict[str, object], str]] = [
    (
        "zone outside the map",
        {
            "zones": [
                {"id": "z1", "polygon": [[1, 1], [3, 1], [3, 2], [1, 2]]},
                {"id": "z2", "polygon": [[9, 1], [12, 1], [12, 2], [9, 2]]},
            ]
        },
        "zones[1] (z2): vertex [12, 1] lies outside the map",
    ),
    (
        "unknown zone in a route",
        {"routes": [{"from": "A", "to": "B", "raffle": [["z1"], ["z9"]]}]},
        "routes[0].raffle: unknown zone 'z9'",
    ),
    (
        "unknown zone in a node",
        {"nodes": [{"id": "n1", "zone": "z7", "sensor": {"type": "pir", "pin": 5}}]},
        "nodes[0] (n1): unknown zone 'z7'",
    ),
    (
        "unknown point in a route",
        {"routes": [{"from": "A", "to": "Q", "raffle": [["z1"]]}]},
        "routes[0]: unknown point 'Q'",
    ),
    (
        "point inside a wall",
        {"points": {"A": [5.0, 4.0, 0.0], "B": [9.0, 4.0, 0.0]}},
        "points.A: [5, 4] lies inside a wall",
    ),
    (
        "point outside the map",
        {"points": {"A": [50.0, 4.0, 0.0], "B": [9.0, 4.0, 0.0]}},
        "points.A: [50, 4] lies outside the map",
    ),
    (
        "duplicate zone id",
        {
            "zones": [
                {"id": "z1", "polygon": [[1, 1], [3, 1], [3, 2]]},
                {"id": "z1", "polygon": [[6, 1], [8, 1], [8, 2]]},
            ]
        },
        "zones[1]: duplicate id 'z1'",
    ),
    (
        "id that cannot be a topic level",
        {"robots": [{"id": "robot/1"}]},
        "robots[0] (robot/1).id: String should match pattern",
    ),
    (
        "unknown sensor type",
        {"nodes": [{"id": "n1", "zone": "z1", "sensor": {"type": "laser", "pin": 5}}]},
        "nodes[0] (n1).sensor",
    ),
    (
        "a pin wired to the SPI flash",
        {"nodes": [{"id": "n1", "zone": "z1", "sensor": {"type": "pir", "pin": 6}}]},
        "nodes[0] (n1).sensor.pin: GPIO6 is wired to the SPI flash (use 4, 5, 12, 13 or 14)",
    ),
    (
        "the serial console's pin",
        {"nodes": [{"id": "n1", "zone": "z1", "sensor": {"type": "ir_beam", "pin": 3}}]},
        "nodes[0] (n1).sensor.pin: GPIO3 is the serial console (RX)",
    ),
    (
        "a boot-mode pin as the echo input",
        {
            "nodes": [
                {"id": "n1", "zone": "z1", "sensor": {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 15}}
            ]
        },
        "nodes[0] (n1).sensor.echo_pin: GPIO15 selects the boot mode",
    ),
    ("missing map", {"map": "nowhere.yaml"}, "nowhere.yaml"),
    ("misspelt key", {"zonez": []}, "zonez: Extra inputs are not permitted"),
]


@pytest.mark.parametrize(("what", "overrides", "message"), BAD_SITES, ids=[b[0] for b in BAD_SITES])
def test_bad_site_fails_with_one_line(
    tmp_path: Path, what: str, overrides: dict[str, object], message: str
) -> None:
    site_dir = tiny_site(tmp_path / "s", **overrides)
    result = wsnav("site", "check", site_dir)
    assert result.returncode != 0, what
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert str(site_dir / "site.yaml") in lines[0]
    assert message in lines[0]
    with pytest.raises(SiteError):
        load_site(site_dir)


def test_not_yaml_and_missing_site(tmp_path: Path) -> None:
    (tmp_path / "site.yaml").write_text("name: [unclosed\n")
    for target in (tmp_path, tmp_path / "absent"):
        result = wsnav("site", "check", target)
        assert result.returncode != 0
        assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr


def test_bad_arguments_give_one_line() -> None:
    result = wsnav("site", "render", "sites/school")
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "wsnav site render: error: the following arguments are required: --png (see --help)"
    ]


def test_render_draws_the_site(tmp_path: Path) -> None:
    png = tmp_path / "out" / "site.png"
    result = wsnav("site", "render", tiny_site(tmp_path / "s"), "--png", png)
    assert result.returncode == 0, result.stderr
    with Image.open(png) as img:
        assert img.width > 600
        colours = len(np.unique(np.asarray(img.convert("RGB")).reshape(-1, 3), axis=0))
    assert colours > 20  # map, zones, labels: not a blank canvas
