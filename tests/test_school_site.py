"""The school site (the paper's Figures 5-7): its map is reproducible, and every raffled zone matters.

For each route, the unblocked shortest path must cross each raffled zone (so the raffle changes something),
and with that zone blocked the goal must stay reachable by a clearly longer way that avoids the zone.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from tests.conftest import SCHOOL
from wsnav.cli import main
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.planning.astar import Plan, PlannerParams, densify, plan_path
from wsnav.navigation.planning.offline_plan import site_costmap, zone_lethal
from wsnav.robot_agent.sim.lidar import LidarParams
from wsnav.schemas.site import Site

ROUTES = [("A", "B", ["z1", "z4"]), ("B", "C", ["z4", "z5"]), ("C", "D", ["z1", "z5", "z3"])]


def plan(site: Site, start: str, goal: str, blocked: list[str]) -> Plan:
    costs = site_costmap(
        site, blocked, InflationParams(inscribed_radius=site.spec.robots[0].footprint_radius)
    )
    grid = site.grid
    return plan_path(
        costs, grid.resolution, grid.origin, site.point(start)[:2], site.point(goal)[:2], PlannerParams()
    )


def test_site_check_passes(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["site", "check", str(SCHOOL)]) == 0
    assert "ok: site 'school'" in capsys.readouterr().out


def test_school_matches_the_brief(school: Site) -> None:
    spec = school.spec
    assert [z.id for z in spec.zones] == [f"z{i}" for i in range(1, 8)]
    assert [(r.from_, r.to, r.raffle) for r in spec.routes] == [
        (a, b, [[z] for z in zs]) for a, b, zs in ROUTES
    ]
    assert [r.id for r in spec.robots] == [f"robot{i}" for i in range(1, 11)]
    assert {n.sensor.type for n in spec.nodes} == {"pir", "ir_beam", "hcsr04"}
    watchers = [n.zone for n in spec.nodes]
    assert any(watchers.count(z) >= 2 for z in set(watchers))
    x0, y0, x1, y1 = school.grid.bounds
    assert 45 <= x1 - x0 <= 55 and 28 <= y1 - y0 <= 35
    assert school.grid.resolution == 0.05


def test_points_stand_well_clear_of_walls(school: Site) -> None:
    grid = school.grid
    clearance = np.asarray(distance_transform_edt(grid.data == 0), dtype=np.float64) * grid.resolution
    for name in school.spec.points:
        row, col = grid.world_to_cell(*school.point(name)[:2])
        assert clearance[row, col] >= 0.8, f"point {name} is {clearance[row, col]:.2f} m from a wall"


def test_generator_is_reproducible(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, str(SCHOOL / "generate.py"), "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    for name in ("map.pgm", "map.yaml"):
        assert (tmp_path / name).read_bytes() == (SCHOOL / name).read_bytes(), f"{name} differs: regenerate"


def test_generated_map_follows_map_server_conventions(school: Site) -> None:
    raw = (SCHOOL / "map.pgm").read_bytes()
    assert raw.startswith(b"P5\n")
    values = set(
        np.unique(np.frombuffer(raw[-school.grid.width * school.grid.height :], dtype=np.uint8)).tolist()
    )
    assert values == {0, 205, 254}
    # The outer wall is occupied and the middle of the south corridor is free (row 0 = map bottom).
    assert school.grid.occupied(0.0, 15.0)
    assert not school.grid.occupied(20.0, 7.2)


@pytest.mark.parametrize(("start", "goal", "zones"), ROUTES, ids=[f"{a}->{b}" for a, b, _ in ROUTES])
def test_every_raffled_zone_matters_and_leaves_a_longer_way(
    school: Site, start: str, goal: str, zones: list[str]
) -> None:
    free = plan(school, start, goal, [])
    assert free.reachable, free.reason
    for zone in zones:
        mask = zone_lethal(school, [zone])
        rows, cols = free.cells[:, 0], free.cells[:, 1]
        assert mask[rows, cols].any(), f"{start}->{goal}: the shortest path does not cross {zone}"
        blocked = plan(school, start, goal, [zone])
        assert blocked.reachable, f"{start}->{goal} with {zone} blocked: {blocked.reason}"
        assert not mask[blocked.cells[:, 0], blocked.cells[:, 1]].any()
        dense = densify(blocked.path, school.grid.resolution / 4)
        for x, y in dense:
            row, col = school.grid.world_to_cell(x, y)
            assert not mask[row, col], f"smoothed path enters {zone} at ({x:.2f}, {y:.2f})"
        assert blocked.length_m >= 1.15 * free.length_m, (zone, free.length_m, blocked.length_m)
        assert blocked.length_m >= free.length_m + 5.0, (zone, free.length_m, blocked.length_m)


@pytest.mark.parametrize(("start", "goal", "zones"), ROUTES, ids=[f"{a}->{b}" for a, b, _ in ROUTES])
def test_no_raffled_zone_is_in_lidar_range_of_its_route_start(
    school: Site, start: str, goal: str, zones: list[str]
) -> None:
    """Otherwise the stock robot sees the obstacle before it moves and the run shows nothing the nodes add."""
    grid = school.grid
    x, y = school.point(start)[:2]
    for zone in zones:
        rows, cols = np.nonzero(zone_lethal(school, [zone]))
        cx = grid.origin[0] + (cols + 0.5) * grid.resolution
        cy = grid.origin[1] + (rows + 0.5) * grid.resolution
        nearest = float(np.hypot(cx - x, cy - y).min())
        assert nearest > LidarParams().range_max + 1.0, f"{zone} is {nearest:.1f} m from {start}"


def test_unraffled_zones_sit_in_corridors_too(school: Site) -> None:
    """Blocking any single zone never cuts the building in two: every point still reaches every other."""
    names = list(school.spec.points)
    for zone in school.spec.zones:
        for a, b in itertools.pairwise(names):
            assert plan(school, a, b, [zone.id]).reachable, f"{a}->{b} with {zone.id} blocked"
