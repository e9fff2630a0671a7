"""`wsnav plan` on the school and on every site over a third-party Nav2 map; bad input gives one line."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import REPO, SITES
from wsnav.cli import main
from wsnav.schemas.site import load_site

REAL_MAP_SITES = ["depot", "depot_keepout", "warehouse", "warehouse_keepout", "tb3_sandbox"]


def run_plan(capsys: pytest.CaptureFixture[str], *args: str) -> dict[str, Any]:
    assert main(["plan", *args]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1, "plan prints exactly one JSON object"
    return json.loads(out[0])


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "wsnav.cli", *args], capture_output=True, text=True, check=False, cwd=REPO
    )


def test_school_plan_json(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    png = tmp_path / "ab.png"
    out = run_plan(capsys, "--site", str(SITES / "school"), "--from", "A", "--to", "B", "--png", str(png))
    assert out["reachable"] is True
    assert out["blocked_zones"] == []
    assert {"length_m", "path", "plan_ms"} <= out.keys()
    path = out["path"]
    assert path[0] == [12.0, 7.2] and path[-1] == [29.0, 22.8]
    assert 2 <= len(path) <= 200, "the path is downsampled to its corners"
    polyline = sum(((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2) ** 0.5 for a, b in itertools.pairwise(path))
    assert out["length_m"] == pytest.approx(polyline, rel=0.01)
    assert png.read_bytes().startswith(b"\x89PNG")


def test_school_plan_blocked_is_longer_and_named(capsys: pytest.CaptureFixture[str]) -> None:
    site = str(SITES / "school")
    free = run_plan(capsys, "--site", site, "--from", "A", "--to", "B")
    blocked = run_plan(capsys, "--site", site, "--from", "A", "--to", "B", "--block", "z1", "--block", "z1")
    assert blocked["blocked_zones"] == ["z1"]
    assert blocked["reachable"] is True
    assert blocked["length_m"] > free["length_m"] + 5.0
    both = run_plan(capsys, "--site", site, "--from", "A", "--to", "B", "--block", "z1", "--block", "z4")
    assert both["length_m"] >= blocked["length_m"]


def test_school_plan_accepts_coordinates(capsys: pytest.CaptureFixture[str]) -> None:
    out = run_plan(capsys, "--site", str(SITES / "school"), "--from", "12,7.2", "--to", "29,22.8,1.57")
    assert out["reachable"] is True
    assert out["path"][0] == [12.0, 7.2]
    assert out["goal"] == [29.0, 22.8, 1.57]


def test_goal_inside_a_blocked_zone_is_unreachable_not_an_error(capsys: pytest.CaptureFixture[str]) -> None:
    out = run_plan(capsys, "--site", str(SITES / "school"), "--from", "A", "--to", "18,7.2", "--block", "z1")
    assert out["reachable"] is False
    assert out["reason"] == "goal_blocked"
    assert out["length_m"] is None and out["path"] == []


def test_cut_off_goal_is_unreachable(capsys: pytest.CaptureFixture[str]) -> None:
    # D sits in the west corridor between z2 and z3: block both and no way leads there.
    args = ["--site", str(SITES / "school"), "--from", "A", "--to", "D", "--block", "z2", "--block", "z3"]
    out = run_plan(capsys, *args)
    assert out["reachable"] is False
    assert out["reason"] == "no_path"


@pytest.mark.parametrize("name", REAL_MAP_SITES)
def test_real_map_sites_check_and_plan(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    site_dir = SITES / name
    assert main(["site", "check", str(site_dir)]) == 0
    capsys.readouterr()
    site = load_site(site_dir)
    assert site.spec.map == f"../nav2_maps/{name}.yaml"
    assert 2 <= len(site.spec.zones) <= 4 and site.spec.nodes and site.spec.routes
    for route in site.spec.routes:
        base = run_plan(capsys, "--site", str(site_dir), "--from", route.from_, "--to", route.to)
        assert base["reachable"] is True, base
        for zone_set in route.raffle:
            blocked_args = [a for z in zone_set for a in ("--block", z)]
            out = run_plan(
                capsys, "--site", str(site_dir), "--from", route.from_, "--to", route.to, *blocked_args
            )
            assert out["blocked_zones"] == zone_set
            assert out["reachable"] is True, out
            assert out["length_m"] >= base["length_m"] - 0.05
            for x, y in out["path"]:
                row, col = site.grid.world_to_cell(x, y)
                assert site.grid.data[row, col] == 0, f"path vertex ({x}, {y}) is not in free space"


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--from", "Q", "--to", "B"], "--from 'Q': not a point of site 'school'"),
        (["--from", "A", "--to", "B", "--block", "z9"], "--block 'z9': no such zone"),
        (["--from", "0,0", "--to", "B"], "--from [0, 0] lies inside a wall"),
        (["--from", "A", "--to", "-0.5,-0.5"], "--to [-0.5, -0.5] lies inside unknown space"),
        (["--from", "A", "--to", "100,5"], "--to [100, 5] lies outside the map"),
        (["--from", "A", "--to", "1,2,3,4"], "not a point of site"),
        (["--from", "A", "--to", "nan,1"], "not a point of site"),
        (["--from", "A", "--to", "B", "--robot", "r9"], "--robot 'r9': no such robot"),
        (["--from", "A", "--to", "B", "--inflation-radius", "nan"], "--inflation-radius nan: expected"),
    ],
)
def test_bad_input_is_one_line_on_stderr(args: list[str], expected: str) -> None:
    result = run_cli("plan", "--site", str(SITES / "school"), *args)
    assert result.returncode != 0
    assert result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert expected in lines[0]
    assert "Traceback" not in result.stderr


def test_bad_site_and_unwritable_png_are_one_line(tmp_path: Path) -> None:
    missing = run_cli("plan", "--site", str(tmp_path / "nowhere"), "--from", "A", "--to", "B")
    assert missing.returncode != 0 and len(missing.stderr.strip().splitlines()) == 1
    assert "no such site file" in missing.stderr
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    png = blocker / "plan.png"
    bad_png = run_cli("plan", "--site", str(SITES / "school"), "--from", "A", "--to", "B", "--png", str(png))
    assert bad_png.returncode != 0 and len(bad_png.stderr.strip().splitlines()) == 1
    assert "cannot write picture" in bad_png.stderr
