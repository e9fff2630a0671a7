"""The planner's building blocks on small hand-made grids: costmap_2d's inflation numbers, zone masks that
respect origin and resolution exactly, and A* plans that are short, smooth and keep off walls."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from tests.conftest import SITES
from wsnav.navigation.costmap.inflation import InflationParams, inflate, static_layer
from wsnav.navigation.planning.astar import (
    PlannerParams,
    _astar,
    densify,
    dyadic,
    plan_path,
    simplify,
    steps_to,
    weight_lut,
)
from wsnav.schemas.site import load_site
from wsnav.zones.cost_values import INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import GridFrame, Polygon, polygon_window

RES = 0.05
INFL = InflationParams(inscribed_radius=0.105, inflation_radius=1.0, cost_scaling_factor=3.0)


def test_inflation_follows_costmap_2d_formula() -> None:
    grid = np.zeros((61, 61), dtype=np.uint8)
    grid[30, 30] = LETHAL_OBSTACLE
    out = inflate(grid, RES, INFL)
    assert out[30, 30] == LETHAL_OBSTACLE
    assert out[30, 32] == INSCRIBED_INFLATED_OBSTACLE  # 0.10 m <= inscribed radius
    for cells in (3, 5, 10, 20):
        d = cells * RES
        assert out[30, 30 + cells] == int(252 * math.exp(-3.0 * (d - 0.105)))
    diagonal = math.hypot(7, 7) * RES
    assert out[37, 37] == int(252 * math.exp(-3.0 * (diagonal - 0.105)))
    assert out[30, 30 + 21] == 0  # 1.05 m: beyond the inflation radius
    assert out[0, 0] == 0


def test_inflation_leaves_unknown_unknown_unless_inscribed() -> None:
    grid = np.full((20, 20), NO_INFORMATION, dtype=np.uint8)
    grid[10, :] = LETHAL_OBSTACLE
    grid[:5, :] = 0
    out = inflate(grid, RES, INFL)
    assert out[11, 0] == INSCRIBED_INFLATED_OBSTACLE and out[12, 0] == INSCRIBED_INFLATED_OBSTACLE
    assert out[13, 0] == NO_INFORMATION
    assert 0 < out[4, 0] < INSCRIBED_INFLATED_OBSTACLE  # known free cell 0.3 m away gets inflated
    assert np.all(inflate(np.zeros((5, 5), dtype=np.uint8), RES, INFL) == 0)


def reference_inflation(master: np.ndarray, params: InflationParams) -> np.ndarray:
    """costmap_2d's rule the plain way: scipy's exact EDT, the formula per cell, unknown kept unless inscribed."""
    lethal = master == LETHAL_OBSTACLE
    if not lethal.any():
        inflated = np.zeros(master.shape)
    else:
        d = np.asarray(distance_transform_edt(~lethal), dtype=np.float64) * RES
        inflated = np.floor(252 * np.exp(-params.cost_scaling_factor * (d - params.inscribed_radius)))
        inflated = inflated.clip(0, 252)
        inflated[d <= params.inscribed_radius] = INSCRIBED_INFLATED_OBSTACLE
        inflated[d > params.inflation_radius] = 0
        inflated[lethal] = LETHAL_OBSTACLE
    out = np.maximum(master, inflated)
    unknown = master == NO_INFORMATION
    out[unknown] = np.where(
        inflated[unknown] >= INSCRIBED_INFLATED_OBSTACLE, inflated[unknown], NO_INFORMATION
    )
    return out.astype(np.uint8)


def test_inflation_of_a_real_map_and_of_windows_equals_the_exact_distance_transform() -> None:
    master = static_layer(load_site(SITES / "school").grid)
    rng = np.random.default_rng(5)
    master[rng.random(master.shape) < 0.002] = LETHAL_OBSTACLE  # scattered lidar marks
    master[rng.random(master.shape) < 0.002] = 120  # zone costs between free and inscribed
    params = InflationParams(inscribed_radius=0.105, inflation_radius=0.5, cost_scaling_factor=3.0)
    expected = reference_inflation(master, params)
    assert np.array_equal(inflate(master, RES, params), expected)
    height, width = master.shape
    for _ in range(50):
        r0, r1 = sorted(rng.integers(0, height + 1, size=2).tolist())
        c0, c1 = sorted(rng.integers(0, width + 1, size=2).tolist())
        window = inflate(master, RES, params, (slice(r0, r1), slice(c0, c1)))
        assert np.array_equal(window, expected[r0:r1, c0:c1]), "a window is cut from the whole map"


def test_static_layer_of_a_real_map() -> None:
    site = load_site(SITES / "school")
    costs = static_layer(site.grid)
    assert set(np.unique(costs).tolist()) == {0, LETHAL_OBSTACLE, NO_INFORMATION}
    assert np.array_equal(costs == LETHAL_OBSTACLE, site.grid.data == 100)
    assert np.array_equal(costs == NO_INFORMATION, site.grid.data == -1)


def polygon_mask(polygon: Polygon, frame: GridFrame) -> np.ndarray:
    """The polygon's cells on the whole grid (row 0 = map bottom)."""
    mask = np.zeros((frame.height, frame.width), dtype=bool)
    window = polygon_window(polygon, frame)
    mask[window.rows, window.cols] = window.mask
    return mask


def test_polygon_mask_respects_origin_and_resolution() -> None:
    frame = GridFrame(width=100, height=80, resolution=RES, origin_x=-1.0, origin_y=-1.0)
    mask = polygon_mask([(0.0, 0.0), (1.0, 0.0), (1.0, 0.5), (0.0, 0.5)], frame)
    rows, cols = np.nonzero(mask)
    # x 0..1 m is columns 20..39 by centre, plus column 40 that the east edge x = 1.0 touches; same for rows.
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (20, 30, 20, 40)
    assert mask[20:31, 20:41].all() and mask.sum() == 11 * 21
    assert frame.cell_to_world(20, 20) == pytest.approx((0.025, 0.025))
    assert frame.world_to_cell(0.026, 0.049) == (20, 20)


def test_polygon_window_clips_and_handles_slanted_edges() -> None:
    frame = GridFrame(width=50, height=50, resolution=0.1, origin_x=2.0, origin_y=3.0)
    assert polygon_window([(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)], frame).empty  # entirely outside
    half = polygon_window([(6.5, 5.0), (9.0, 5.0), (9.0, 6.0), (6.5, 6.0)], frame)
    assert half.col0 + half.mask.shape[1] == 50 and half.mask.all()
    tri = polygon_mask([(3.0, 4.0), (5.0, 4.0), (3.0, 6.0)], frame)
    # A thin diagonal line of cells would leak; the outline keeps the hypotenuse closed.
    for k in range(20):
        r, c = frame.world_to_cell(5.0 - k * 0.1 - 0.05, 4.0 + k * 0.1 + 0.05)
        assert tri[r, c]
    assert not tri[frame.world_to_cell(4.8, 5.8)]


def test_weights_follow_navfn() -> None:
    lut = weight_lut(PlannerParams())
    assert lut[0] == 1.0
    assert lut[100] == pytest.approx(1.0 + 0.8 * 100 / 50, abs=1 / 128)  # rounded to a 64th (dyadic)
    assert np.isinf(lut[INSCRIBED_INFLATED_OBSTACLE]) and np.isinf(lut[LETHAL_OBSTACLE])
    assert np.isinf(lut[NO_INFORMATION])
    assert np.isfinite(weight_lut(PlannerParams(allow_unknown=True))[NO_INFORMATION])


def walled_room() -> np.ndarray:
    """10 x 6 m room at 0.05 m: a wall across the middle with a 1.5 m gap near the top."""
    grid = np.zeros((120, 200), dtype=np.uint8)
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = LETHAL_OBSTACLE
    grid[:80, 100] = LETHAL_OBSTACLE
    grid[110:, 100] = LETHAL_OBSTACLE
    return inflate(grid, RES, InflationParams(0.105, 0.6, 3.0))


def test_plan_goes_through_the_gap_smoothly() -> None:
    costs = walled_room()
    plan = plan_path(costs, RES, (0.0, 0.0), (2.0, 1.0), (8.0, 1.0))
    assert plan.reachable and plan.reason == "ok"
    assert tuple(plan.path[0]) == (2.0, 1.0) and tuple(plan.path[-1]) == (8.0, 1.0)
    assert len(plan.path) <= 8, "line-of-sight smoothing leaves only corners"
    gap_y = 0.5 * (80 + 110) * RES
    assert plan.length_m == pytest.approx(2 * math.hypot(3.0, gap_y - 1.0), rel=0.08)
    dense = densify(plan.path, RES / 2)
    rows = np.floor(dense[:, 1] / RES).astype(int)
    cols = np.floor(dense[:, 0] / RES).astype(int)
    raw_max = int(costs[plan.cells[:, 0], plan.cells[:, 1]].max())
    assert (
        int(costs[rows, cols].max())
        <= max(PlannerParams().smooth_cost, raw_max)
        < INSCRIBED_INFLATED_OBSTACLE
    )


def test_plan_failures_have_reasons() -> None:
    costs = walled_room()
    closed = costs.copy()
    closed[:, 100] = LETHAL_OBSTACLE
    assert plan_path(closed, RES, (0.0, 0.0), (2.0, 1.0), (8.0, 1.0)).reason == "no_path"
    assert plan_path(costs, RES, (0.0, 0.0), (2.0, 1.0), (5.0, 1.0)).reason == "goal_blocked"
    assert plan_path(costs, RES, (0.0, 0.0), (5.0, 1.0), (2.0, 1.0)).reason == "start_blocked"
    assert plan_path(costs, RES, (0.0, 0.0), (-1.0, 1.0), (2.0, 1.0)).reason == "start_outside"
    assert plan_path(costs, RES, (0.0, 0.0), (2.0, 1.0), (2.0, 99.0)).reason == "goal_outside"


def test_start_brushing_a_wall_can_step_off() -> None:
    costs = walled_room()
    start = (100 * RES + 0.5 * RES + 0.1, 1.0)  # 0.1 m east of the wall: inscribed space
    assert costs[int(1.0 / RES), int(start[0] / RES)] == INSCRIBED_INFLATED_OBSTACLE
    plan = plan_path(costs, RES, (0.0, 0.0, 0.0), start, (8.0, 1.0))
    assert plan.reachable
    assert plan_path(costs, RES, (0.0, 0.0), start, (8.0, 1.0), PlannerParams(start_step_off_m=0)).reason == (
        "start_blocked"
    )


def test_simplify_keeps_corners_only() -> None:
    line = np.array([[0.0, 0.0], [1.0, 0.001], [2.0, 0.0], [2.0, 1.0], [2.0, 2.0]])
    assert simplify(line, 0.01).tolist() == [[0.0, 0.0], [2.0, 0.0], [2.0, 2.0]]


def test_step_weights_are_dyadic_so_path_costs_add_up_exactly() -> None:
    for params in (PlannerParams(), PlannerParams(allow_unknown=True), PlannerParams(cost_factor=0.37)):
        lut = weight_lut(params).astype(np.float64)
        finite = lut[np.isfinite(lut)]
        assert np.array_equal(finite * 64, np.round(finite * 64))
        assert finite.min() >= 1.0


def test_a_band_search_that_crashed_pyastar2d_now_returns_a_connected_path() -> None:
    """Weights (a coarse-to-fine band) recorded when an experiment worker died in pyastar2d's path walk: with
    NavFn's raw float weights its predecessor chain outran the recorded length and read unset memory."""
    data = np.load(Path(__file__).parent / "data" / "astar_band_crash.npz")
    weights = dyadic(data["weights"].astype(np.float64)).astype(np.float32)
    s, g = tuple(int(v) for v in data["start"]), tuple(int(v) for v in data["goal"])
    for _ in range(30):
        path = _astar(weights, (s[0], s[1]), (g[0], g[1]), True)
        assert path is not None
        assert tuple(path[0]) == s and tuple(path[-1]) == g
        assert int(np.abs(np.diff(path, axis=0)).max()) == 1


def test_densified_paths_and_arc_samples_are_the_points_np_linspace_gives_bit_for_bit() -> None:
    # The experiment's rows must not change when sampling is made cheaper: same floats, not just close ones.
    for stop in (1.0, 0.5, 1.5, 2.0 / 3.0, 1e-3, 7.123):
        for n in range(1, 400):
            assert np.array_equal(steps_to(stop, n), np.linspace(0.0, stop, n + 1)[1:])
    path = np.array([[0.013, 0.7], [1.31, 2.9], [1.31, 2.9], [-0.4, 0.05]])
    dense = densify(path, 0.025)
    want = [path[:1]] + [
        a
        + (b - a) * np.linspace(0.0, 1.0, max(1, math.ceil(float(np.hypot(*(b - a))) / 0.025)) + 1)[1:, None]
        for a, b in itertools.pairwise(path)
    ]
    assert np.array_equal(dense, np.vstack(want))
