"""The simulated lidar on real maps: ranges to walls whose positions the school's layout gives, agreement with a
brute-force ray tracer on a Nav2 map, REP 117 infinities, and obstacles from the zone simulator's SimWorld."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.conftest import SITES
from wsnav.robot_agent.sim.lidar import LidarParams, cast_scan
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.schemas.messages import SimObstacle, SimWorld
from wsnav.schemas.site import load_site
from wsnav.zones.geometry import GridFrame

CELL = 0.05
# South corridor of the school (sites/school/layout.yaml): wall centre lines y 5.9 and 8.5, 0.2 m thick, so
# the free corridor is y 6.0 .. 8.4; at x 10.5 no door interrupts either wall.
CORRIDOR = (10.5, 7.2)


@pytest.fixture(scope="module")
def school() -> SimWorldGrid:
    return SimWorldGrid(load_site(SITES / "school").grid)


def beam_towards(params: LidarParams, yaw: float, direction: float) -> int:
    return round(((direction - yaw) % (2 * math.pi)) / params.angle_increment) % params.beams


def test_ranges_to_corridor_walls_match_the_layout(school: SimWorldGrid) -> None:
    params = LidarParams()
    for yaw in (0.0, 0.7, math.pi / 2, -2.0):
        scan = cast_scan(school.occupied, school.frame, (*CORRIDOR, yaw), params, stamp=3.0)
        north = scan.ranges[beam_towards(params, yaw, math.pi / 2)]
        south = scan.ranges[beam_towards(params, yaw, -math.pi / 2)]
        assert north == pytest.approx(8.4 - 7.2, abs=CELL)
        assert south == pytest.approx(7.2 - 6.0, abs=CELL)
        # 45 degrees to the north-east the same wall is 1.2 / sin(45 deg) away.
        assert scan.ranges[beam_towards(params, yaw, math.pi / 4)] == pytest.approx(
            1.2 * math.sqrt(2), abs=CELL
        )
    assert scan.stamp == 3.0 and scan.pose == (*CORRIDOR, -2.0)
    assert len(scan.ranges) == 360 and scan.ranges.dtype == np.float32


def test_nothing_within_range_reads_inf_and_no_range_exceeds_range_max(school: SimWorldGrid) -> None:
    params = LidarParams()
    scan = cast_scan(school.occupied, school.frame, (*CORRIDOR, 0.0), params, stamp=0.0)
    assert scan.ranges[0] == np.inf  # straight along the corridor: the next wall is metres beyond 3.5 m
    assert scan.ranges[180] == np.inf
    finite = scan.ranges[np.isfinite(scan.ranges)]
    assert len(finite) > 100 and finite.max() <= params.range_max and finite.min() >= params.range_min
    short = LidarParams(range_max=1.0)
    scan = cast_scan(school.occupied, school.frame, (*CORRIDOR, 0.0), short, stamp=0.0)
    assert scan.ranges[90] == np.inf  # the wall at 1.2 m is beyond a 1 m sensor


def test_walls_closer_than_range_min_read_minus_inf(school: SimWorldGrid) -> None:
    params = LidarParams()
    scan = cast_scan(school.occupied, school.frame, (10.5, 6.11, 0.0), params, stamp=0.0)
    assert scan.ranges[270] == -np.inf  # 0.11 m from the south wall, under the LDS-01's 0.12 m
    assert scan.ranges[90] == pytest.approx(8.4 - 6.11, abs=CELL)


def brute_force_range(occupied: np.ndarray, frame: GridFrame, x: float, y: float, angle: float) -> float:
    """The reference: walk the ray in 0.1 mm steps and stop in the first occupied cell."""
    t = np.arange(1, 35001) * 1e-4
    cols = np.floor((x + t * math.cos(angle) - frame.origin_x) / frame.resolution).astype(int)
    rows = np.floor((y + t * math.sin(angle) - frame.origin_y) / frame.resolution).astype(int)
    hit = np.flatnonzero(occupied[rows, cols])  # the sandbox's arena lies well inside its map
    return float(t[hit[0]]) if len(hit) else math.inf


def test_agrees_with_a_brute_force_tracer_on_a_nav2_map() -> None:
    world = SimWorldGrid(load_site(SITES / "tb3_sandbox").grid)
    params = LidarParams(beams=90)
    rng = np.random.default_rng(7)
    checked = 0
    while checked < 8:
        x, y = rng.uniform(-2.5, 2.5, size=2)
        if world.is_occupied(x, y):
            continue
        yaw = float(rng.uniform(-math.pi, math.pi))
        scan = cast_scan(world.occupied, world.frame, (x, y, yaw), params, stamp=0.0)
        for i, got in enumerate(scan.ranges):
            angle = yaw + i * params.angle_increment
            want = brute_force_range(world.occupied, world.frame, x, y, angle)
            if want > params.range_max:
                assert got == np.inf, (x, y, yaw, i)
            elif want < params.range_min:
                assert got == -np.inf, (x, y, yaw, i)
            else:
                assert got == pytest.approx(want, abs=2e-4), (x, y, yaw, i)
                t = float(got) + 1e-5
                assert world.is_occupied(x + t * math.cos(angle), y + t * math.sin(angle))
        checked += 1


def test_an_obstacle_from_the_zone_simulator_appears_and_disappears() -> None:
    world = SimWorldGrid(load_site(SITES / "school").grid)
    params = LidarParams()
    pose = (*CORRIDOR, 0.0)
    assert cast_scan(world.occupied, world.frame, pose, params, 0.0).ranges[0] == np.inf
    box = [(11.5, 6.8), (12.0, 6.8), (12.0, 7.6), (11.5, 7.6)]
    world.apply(SimWorld(t=1.0, obstacles=[SimObstacle(id="cart", polygon=box)]))
    assert world.obstacle_ids == ["cart"]
    ahead = cast_scan(world.occupied, world.frame, pose, params, 1.0).ranges[0]
    assert ahead == pytest.approx(1.0, abs=CELL)
    world.apply(SimWorld(t=2.0, obstacles=[]))
    assert cast_scan(world.occupied, world.frame, pose, params, 2.0).ranges[0] == np.inf
    # Removing the obstacle gives back exactly the map: the walls it did not cover are untouched.
    assert np.array_equal(world.occupied, SimWorldGrid(load_site(SITES / "school").grid).occupied)


def test_an_obstacle_across_a_zone_closes_the_corridor_to_the_lidar() -> None:
    site = load_site(SITES / "school")
    world = SimWorldGrid(site.grid)
    z1 = site.spec.zone("z1").polygon  # x 17..19, wall to wall across the south corridor
    world.apply(SimWorld(t=0.0, obstacles=[SimObstacle(id="people", zone="z1", polygon=z1)]))
    params = LidarParams()
    for y in (6.2, 7.2, 8.2):
        assert cast_scan(world.occupied, world.frame, (15.5, y, 0.0), params, 0.0).ranges[0] == pytest.approx(
            1.5, abs=CELL
        )


def test_noise_is_seeded_and_small(school: SimWorldGrid) -> None:
    exact = cast_scan(school.occupied, school.frame, (*CORRIDOR, 0.0), LidarParams(), 0.0).ranges
    noisy_params = LidarParams(noise_std=0.01)
    a = cast_scan(
        school.occupied, school.frame, (*CORRIDOR, 0.0), noisy_params, 0.0, np.random.default_rng(1)
    )
    b = cast_scan(
        school.occupied, school.frame, (*CORRIDOR, 0.0), noisy_params, 0.0, np.random.default_rng(1)
    )
    assert np.array_equal(a.ranges, b.ranges)
    finite = np.isfinite(exact)
    assert np.array_equal(finite, np.isfinite(a.ranges))
    diff = a.ranges[finite] - exact[finite]
    assert 0.005 < float(diff.std()) < 0.02 and float(np.abs(diff).max()) < 0.06


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="range_min"):
        LidarParams(range_min=4.0)
    with pytest.raises(ValueError, match="beam"):
        LidarParams(beams=0)


def test_range_proportional_noise_grows_with_distance_like_the_lds01(school: SimWorldGrid) -> None:
    """Beams to the near corridor wall scatter less than beams along the corridor to far walls."""
    pose = (*CORRIDOR, 0.0)
    exact = cast_scan(school.occupied, school.frame, pose, LidarParams(), 0.0).ranges
    params = LidarParams(noise_fraction=0.0175)
    rng = np.random.default_rng(5)
    scans = np.stack(
        [cast_scan(school.occupied, school.frame, pose, params, 0.0, rng).ranges for _ in range(40)]
    )
    near = np.isfinite(exact) & (exact < 1.5)
    far = np.isfinite(exact) & (exact > 2.5)
    assert near.any() and far.any()
    spread_near = float((scans[:, near] - exact[near]).std())
    spread_far = float((scans[:, far] - exact[far]).std())
    assert spread_far > 1.8 * spread_near
    assert 0.01 < spread_far / float(exact[far].mean()) < 0.025


def test_rays_that_leave_the_map_read_nothing_beyond_its_edge() -> None:
    # A 2 x 2 m grid walled only along its west edge (column 0); the sensor stands 0.1 m from the east edge.
    occupied = np.zeros((40, 40), dtype=bool)
    occupied[:, 0] = True
    frame = GridFrame(40, 40, CELL, 0.0, 0.0)
    params = LidarParams()
    scan = cast_scan(occupied, frame, (1.9, 1.0, 0.0), params, stamp=0.0)
    angles = np.arange(params.beams) * params.angle_increment
    east = np.cos(angles) > 0.5  # beams that leave through the east edge
    assert np.all(scan.ranges[east] == np.inf), "nothing lies east of the map (no wrap into the next row)"
    assert scan.ranges[180] == pytest.approx(1.9 - CELL, abs=1e-4), "the west wall, 1.85 m away"
