"""A* over a weighted grid, the search under the global planner (global_planner.py::GlobalPlanner): cost-aware A*
(compiled, pyastar2d) over a costmap_2d-style grid.

Input is a uint8 costmap with costmap_2d's values (0 free .. 252, 253 inscribed, 254 lethal, 255 unknown;
row 0 = map bottom) plus its resolution and origin; output is a path in world metres. Cell weights follow
NavFn (`COST_NEUTRAL + COST_FACTOR * cost`, normalised so a free step costs 1), so paths keep clear of walls
the way ROS users expect. The grid path is then shortened by line-of-sight shortcuts that never cross cells
costlier than the stretch they replace (or than `smooth_cost`), so it is not a staircase yet no nearer walls.
"""

from __future__ import annotations

import importlib
import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numba
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from wsnav.zones.cost_values import INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import Bounds, GridFrame

_PYASTAR: Any = importlib.import_module("pyastar2d.astar")
"""The compiled module behind pyastar2d.astar_path."""

Reason = Literal["ok", "start_outside", "goal_outside", "start_blocked", "goal_blocked", "no_path"]
XY = tuple[float, float]


@dataclass(frozen=True)
class PlannerParams:
    """Tuning of the planner; the defaults are NavFn's cost model with diagonal moves."""

    neutral_cost: float = 50.0
    """NavFn's COST_NEUTRAL: the price of a step through free space."""
    cost_factor: float = 0.8
    """NavFn's COST_FACTOR: how much a unit of costmap cost adds to a step."""
    impassable_from: int = INSCRIBED_INFLATED_OBSTACLE
    """Costs at or above this (inscribed, lethal) cannot be entered; NavFn uses the inscribed value."""
    allow_unknown: bool = False
    """When true, unknown cells are passable at the highest price (NavFn's allow_unknown)."""
    allow_diagonal: bool = True
    coarse_above_cells: int = 250_000
    """Grids this big are searched coarse to fine: A* on blocks of `coarse_factor`^2 cells (mean weight,
    impassable if any cell is), then A* on the full grid restricted to a band around the coarse route. On
    corridor grids the straight-line heuristic leaves A* a plateau the size of the map; this keeps a 2000 x 2000
    plan under 100 ms, and a detour on the school floor (665k cells) at 8-10 ms instead of 12-47 ms with paths
    as long. Falls back to a whole-grid search when the band holds no path. 0 disables it."""
    coarse_factor: int = 4
    coarse_margin: int = 2
    """Coarse cells of band on each side of the coarse route."""
    smooth: bool = True
    smooth_cost: int = 64
    """A shortcut may cross cells up to this cost, or up to the highest cost of the stretch it replaces."""
    start_step_off_m: float = 0.3
    """If the start lies in inscribed space (robot brushing a wall), inscribed cells this near it may be
    crossed to get out; lethal cells never."""


@dataclass(frozen=True)
class Plan:
    reachable: bool
    reason: Reason
    path: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    """(n, 2) world x, y in metres from start to goal: the smoothed polyline's vertices."""
    cells: NDArray[np.intp] = field(default_factory=lambda: np.zeros((0, 2), dtype=np.intp))
    """(m, 2) row, col of the raw A* path."""
    length_m: float = float("nan")
    plan_ms: float = 0.0


WEIGHT_QUANTUM = 1.0 / 64.0
"""Step weights are multiples of this, so float32 sums of them are exact (see `dyadic`)."""


def dyadic(weights: NDArray[np.float64]) -> NDArray[np.float64]:
    """Weights rounded to multiples of WEIGHT_QUANTUM (1/64): every partial path cost A* adds up is then exact.

    pyastar2d rebuilds a path by following predecessors for as many steps as the goal's entry recorded when it
    was pushed; that holds only if no cell's cost improves after it was expanded, which a consistent heuristic
    guarantees in exact arithmetic but float32 rounding of NavFn's 1 + 0.016 * cost weights does not: the walk
    then reads an unset predecessor and crashes the process (seen in the experiment, 1 plan in ~100k).
    """
    return np.round(weights / WEIGHT_QUANTUM) * WEIGHT_QUANTUM


def weight_lut(params: PlannerParams) -> NDArray[np.float32]:
    """A* step weight for each cost value 0..255 (dyadic, see `dyadic`); inf = impassable."""
    cost = np.arange(256, dtype=np.float64)
    weight = 1.0 + params.cost_factor * np.minimum(cost, 252.0) / params.neutral_cost
    weight[cost >= params.impassable_from] = np.inf
    if params.allow_unknown:
        # NavFn maps unknown to COST_OBS - 1 (253) on its own scale.
        weight[NO_INFORMATION] = (LETHAL_OBSTACLE - 1) / params.neutral_cost
    else:
        weight[NO_INFORMATION] = np.inf
    return dyadic(weight).astype(np.float32)


def weights_for(costs: NDArray[np.uint8], params: PlannerParams) -> NDArray[np.float32]:
    """A* weights of a whole costmap (one table lookup, so cheap even on big maps)."""
    return weight_lut(params)[costs]


def plan_path(
    costs: NDArray[np.uint8],
    resolution: float,
    origin: Sequence[float],
    start: XY,
    goal: XY,
    params: PlannerParams | None = None,
    weights: NDArray[np.float32] | None = None,
    coarse: NDArray[np.float32] | None = None,
) -> Plan:
    """Plan from `start` to `goal` (world metres) over `costs`; never raises for unreachable goals.

    `origin` is the world position of cell (0, 0)'s corner (x, y[, yaw]; yaw must be 0, as map_server's).
    Pass `weights` (from weights_for) to reuse them across several plans on the same costmap, and with them
    `coarse` (their `coarse_weights`) when the grid is searched coarse to fine (`searched_coarse`).
    """
    p = params or PlannerParams()
    t0 = time.perf_counter()
    height, width = costs.shape
    ox, oy = float(origin[0]), float(origin[1])
    frame = GridFrame(width, height, resolution, ox, oy)
    s = frame.world_to_cell(*start)
    g = frame.world_to_cell(*goal)
    if not frame.contains_cell(*s):
        return Plan(False, "start_outside", plan_ms=_ms(t0))
    if not frame.contains_cell(*g):
        return Plan(False, "goal_outside", plan_ms=_ms(t0))
    w = weights if weights is not None else weights_for(costs, p)
    if not np.isfinite(w[g]):
        return Plan(False, "goal_blocked", plan_ms=_ms(t0))
    if not np.isfinite(w[s]):
        w = _step_off_inscribed_start(costs, w, s, resolution, p)
        if w is None:
            return Plan(False, "start_blocked", plan_ms=_ms(t0))
        coarse = None  # the weights changed around the start: their block grid is made anew
    if s == g:
        path = np.array([start, goal], dtype=np.float64)
        return Plan(True, "ok", path, np.array([s], dtype=np.intp), _length(path), _ms(t0))
    raw = _search(w, s, g, p, coarse)
    if raw is None or len(raw) == 0:
        return Plan(False, "no_path", plan_ms=_ms(t0))
    cells = np.asarray(raw, dtype=np.intp)
    keep = _shortcut(cells, costs, w, p) if p.smooth else np.arange(len(cells))
    centres = np.empty((len(keep), 2), dtype=np.float64)
    centres[:, 0] = ox + (cells[keep, 1] + 0.5) * resolution
    centres[:, 1] = oy + (cells[keep, 0] + 0.5) * resolution
    centres[0] = start
    centres[-1] = goal
    return Plan(True, "ok", centres, cells, _length(centres), _ms(t0))


def plan_exit(
    costs: NDArray[np.uint8],
    exits: NDArray[np.bool_],
    start: tuple[int, int],
    resolution: float,
    params: PlannerParams | None = None,
) -> NDArray[np.intp] | None:
    """Cells (row, col) of the cheapest way from cell `start` to the nearest cell of `exits`, over a small grid.

    A robot in a zone that became blocked leaves by the shortest way out, wherever its goal lies: a way out
    toward the goal may cross the blocked area. Dijkstra from the start (A* needs a single goal); inscribed
    cells near the start may be crossed as in `plan_path`, lethal ones never; smoothed the same way. None when
    no exit can be reached.
    """
    p = params or PlannerParams()
    w = weight_lut(p)[costs]
    if not np.isfinite(w[start]):
        stepped = _step_off_inscribed_start(costs, w, start, resolution, p)
        if stepped is None:
            return None
        w = stepped
    if exits[start]:
        return np.array([start], dtype=np.intp)
    height, width = costs.shape
    index = np.arange(height * width).reshape(height, width)
    src: list[NDArray[np.intp]] = []
    dst: list[NDArray[np.intp]] = []
    step: list[NDArray[np.float64]] = []
    moves = ((0, 1), (1, 0), (1, 1), (1, -1)) if p.allow_diagonal else ((0, 1), (1, 0))
    for dr, dc in moves:
        a = (slice(0, height - dr), slice(max(-dc, 0), width - max(dc, 0)))
        b = (slice(dr, height), slice(max(dc, 0), width - max(-dc, 0)))
        cost = (w[a].astype(np.float64) + w[b]) * (0.5 * float(np.hypot(dr, dc)))
        ok = np.isfinite(cost)
        src.append(index[a][ok])
        dst.append(index[b][ok])
        step.append(cost[ok])
    n = height * width
    graph = csr_matrix((np.concatenate(step), (np.concatenate(src), np.concatenate(dst))), shape=(n, n))
    origin = start[0] * width + start[1]
    dist, pred = dijkstra(graph, directed=False, indices=origin, return_predecessors=True)
    reach = np.where(exits.ravel(), dist, np.inf)
    target = int(np.argmin(reach))
    if not np.isfinite(reach[target]):
        return None
    chain = [target]
    while chain[-1] != origin:
        chain.append(int(pred[chain[-1]]))
    flat = np.asarray(chain[::-1], dtype=np.intp)
    cells = np.column_stack([flat // width, flat % width]).astype(np.intp)
    keep = _shortcut(cells, costs, w, p) if p.smooth else np.arange(len(cells))
    return cells[keep]


def steps_to(stop: float, n: int) -> NDArray[np.float64]:
    """`np.linspace(0, stop, n + 1)[1:]` bit for bit (k * (stop / n), the last exactly `stop`), at a fifth of
    its cost: the controller samples with it 20 times a second."""
    t = np.arange(1, n + 1) * (np.float64(stop) / n)
    t[-1] = stop
    return t


def densify(path: NDArray[np.float64], step_m: float) -> NDArray[np.float64]:
    if len(path) < 2:
        return path.copy()
    out = [path[:1]]
    for a, b in itertools.pairwise(path):
        n = max(1, int(np.ceil(float(np.hypot(*(b - a))) / step_m)))
        out.append(a + (b - a) * steps_to(1.0, n)[:, None])
    return np.vstack(out)


def simplify(path: NDArray[np.float64], tolerance_m: float) -> NDArray[np.float64]:
    """Ramer-Douglas-Peucker: drop vertices within `tolerance_m` of the line through their neighbours."""
    if len(path) < 3:
        return path.copy()
    keep = np.zeros(len(path), dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, len(path) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        a, b = path[i], path[j]
        seg = b - a
        norm = float(np.hypot(*seg))
        mid = path[i + 1 : j]
        if norm == 0:
            dist = np.hypot(*(mid - a).T)
        else:
            dist = np.abs(seg[0] * (mid[:, 1] - a[1]) - seg[1] * (mid[:, 0] - a[0])) / norm
        k = int(np.argmax(dist))
        if dist[k] > tolerance_m:
            keep[i + 1 + k] = True
            stack += [(i, i + 1 + k), (i + 1 + k, j)]
    return path[keep]


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0


def _length(path: NDArray[np.float64]) -> float:
    return float(np.hypot(*np.diff(path, axis=0).T).sum()) if len(path) > 1 else 0.0


def _step_off_inscribed_start(
    costs: NDArray[np.uint8], w: NDArray[np.float32], s: tuple[int, int], resolution: float, p: PlannerParams
) -> NDArray[np.float32] | None:
    """Weights that let the robot leave inscribed space around its start; None if the start is lethal."""
    if costs[s] != INSCRIBED_INFLATED_OBSTACLE or p.start_step_off_m <= 0:
        return None
    r = int(np.ceil(p.start_step_off_m / resolution))
    r0, r1 = max(s[0] - r, 0), min(s[0] + r + 1, costs.shape[0])
    c0, c1 = max(s[1] - r, 0), min(s[1] + r + 1, costs.shape[1])
    rows, cols = np.ogrid[r0:r1, c0:c1]
    near = (rows - s[0]) ** 2 + (cols - s[1]) ** 2 <= r * r
    window = costs[r0:r1, c0:c1]
    out = w.copy()
    patch = out[r0:r1, c0:c1]
    patch[near & (window == INSCRIBED_INFLATED_OBSTACLE)] = np.float32(
        dyadic(np.array(1.0 + p.cost_factor * 252.0 / p.neutral_cost))
    )
    return out


def _astar(
    w: NDArray[np.float32], s: tuple[int, int], g: tuple[int, int], diagonal: bool
) -> NDArray[np.int32] | None:
    """pyastar2d's compiled A* without its wrapper's per-call copy and scan of the grid (our weights are >= 1)."""
    height, width = w.shape
    flat = np.ascontiguousarray(w, dtype=np.float32).ravel()
    return _PYASTAR.astar(flat, height, width, s[0] * width + s[1], g[0] * width + g[1], diagonal, 0)


def searched_coarse(shape: tuple[int, int], p: PlannerParams) -> bool:
    """Whether a grid of this shape is searched coarse to fine (PlannerParams.coarse_above_cells)."""
    return bool(p.coarse_above_cells) and shape[0] * shape[1] > p.coarse_above_cells and p.coarse_factor > 1


def coarse_weights(
    w: NDArray[np.float32],
    f: int,
    out: NDArray[np.float32] | None = None,
    changed: Bounds | None = None,
) -> NDArray[np.float32]:
    """The block grid the coarse search runs on: each f x f block's mean weight, dyadic (inf if any cell is;
    blocks past the grid's edge are padded with impassable cells).

    Given the grid `out` made earlier and the fine cells that `changed` since, only the blocks holding them
    are computed again, in place: each block depends on its own cells alone, so the result is the same as
    made anew, and a planner at 5 Hz does not average the whole map for every plan.
    """
    height, width = w.shape
    hc, wc = -(-height // f), -(-width // f)
    if out is None or changed is None:
        out = np.empty((hc, wc), dtype=np.float32)
        blocks = Bounds(0, 0, hc, wc)
    else:
        blocks = Bounds(changed.row0 // f, changed.col0 // f, -(-changed.row1 // f), -(-changed.col1 // f))
    if blocks.empty:
        return out
    r0, c0, r1, c1 = blocks.row0 * f, blocks.col0 * f, blocks.row1 * f, blocks.col1 * f
    if r1 <= height and c1 <= width:
        cells = w[r0:r1, c0:c1]
    else:
        cells = np.full((r1 - r0, c1 - c0), np.inf, dtype=np.float32)
        cells[: min(r1, height) - r0, : min(c1, width) - c0] = w[r0:r1, c0:c1]
    out[blocks.rows, blocks.cols] = dyadic(_block_means(cells, f).astype(np.float64))
    return out


def _search(
    w: NDArray[np.float32],
    s: tuple[int, int],
    g: tuple[int, int],
    p: PlannerParams,
    coarse: NDArray[np.float32] | None = None,
) -> NDArray[np.int32] | None:
    """A* over `w`, coarse to fine on big grids (PlannerParams.coarse_above_cells), recursively; `coarse` is
    `w`'s block grid when the caller keeps one."""
    if searched_coarse(w.shape, p):
        band = _coarse_band(w, coarse if coarse is not None else coarse_weights(w, p.coarse_factor), s, g, p)
        if band is not None:
            area, restricted = _band_weights(w, *band, p.coarse_factor)
            offset = np.array([area.row0, area.col0], dtype=np.int32)
            raw = _astar(
                restricted,
                (s[0] - area.row0, s[1] - area.col0),
                (g[0] - area.row0, g[1] - area.col0),
                p.allow_diagonal,
            )
            if raw is not None and len(raw) > 0:
                return raw + offset
    return _astar(w, s, g, p.allow_diagonal)


def _coarse_band(
    w: NDArray[np.float32],
    coarse: NDArray[np.float32],
    s: tuple[int, int],
    g: tuple[int, int],
    p: PlannerParams,
) -> tuple[Bounds, NDArray[np.bool_]] | None:
    """The blocks within `coarse_margin` of the route found on the block grid `coarse`, as a mask over the
    smallest window of blocks holding them; None if the block grid has no route."""
    f = p.coarse_factor
    hc, wc = coarse.shape
    sc, gc = (s[0] // f, s[1] // f), (g[0] // f, g[1] // f)
    own = False
    for cell in (sc, gc):
        if not np.isfinite(coarse[cell]):
            # The robot or goal in a block with an impassable cell: that block alone gets its passable mean
            # (on a copy: the caller's grid stays the weights' own).
            if not own:
                coarse, own = coarse.copy(), True
            block = w[cell[0] * f : (cell[0] + 1) * f, cell[1] * f : (cell[1] + 1) * f]
            coarse[cell] = np.float32(dyadic(np.array(block[np.isfinite(block)].mean())))
    route = _search(np.ascontiguousarray(coarse), sc, gc, p)
    if route is None or len(route) == 0:
        return None
    m = p.coarse_margin
    r0, c0 = max(int(route[:, 0].min()) - m, 0), max(int(route[:, 1].min()) - m, 0)
    r1, c1 = min(int(route[:, 0].max()) + m + 1, hc), min(int(route[:, 1].max()) + m + 1, wc)
    # The route's blocks grown by m on every side (a square dilation, row-wise then column-wise), on a window
    # with m spare blocks on each side, then cut to the blocks of the grid.
    on = np.zeros((r1 - r0 + 2 * m, c1 - c0 + 2 * m), dtype=bool)
    on[route[:, 0] - r0 + m, route[:, 1] - c0 + m] = True
    tall = on.copy()
    for d in range(1, m + 1):
        tall[d:] |= on[:-d]
        tall[:-d] |= on[d:]
    mask = tall.copy()
    for d in range(1, m + 1):
        mask[:, d:] |= tall[:, :-d]
        mask[:, :-d] |= tall[:, d:]
    return Bounds(r0, c0, r1, c1), mask[m : m + r1 - r0, m : m + c1 - c0]


def _band_weights(
    w: NDArray[np.float32], blocks: Bounds, mask: NDArray[np.bool_], f: int
) -> tuple[Bounds, NDArray[np.float32]]:
    """The fine cells under `blocks` (block coordinates) and their weights where `mask` marks the block, inf
    elsewhere: what the fine search runs on."""
    height, width = w.shape
    nr, nc = mask.shape
    area = Bounds(blocks.row0 * f, blocks.col0 * f, min(blocks.row1 * f, height), min(blocks.col1 * f, width))
    cells = w[area.rows, area.cols]
    if cells.shape != (nr * f, nc * f):  # blocks past the grid's edge: padded as impassable
        cells = np.full((nr * f, nc * f), np.inf, dtype=np.float32)
        cells[: area.row1 - area.row0, : area.col1 - area.col0] = w[area.rows, area.cols]
    restricted = np.full((nr * f, nc * f), np.inf, dtype=np.float32)
    # Rows of blocks as (block row, row within it, column): the mask repeated along columns only, broadcast
    # over the f rows of each block, copies about twice as fast as a mask repeated along both axes.
    np.copyto(
        restricted.reshape(nr, f, nc * f),
        cells.reshape(nr, f, nc * f),
        where=np.repeat(mask, f, axis=1)[:, None, :],
    )
    return area, restricted[: area.row1 - area.row0, : area.col1 - area.col0]


def _block_means(w: NDArray[np.float32], f: int) -> NDArray[np.float32]:
    """Mean of each f x f block (inf if any cell is), by strided adds: ten times faster than a reshaped
    `mean` over two axes, which on the school floor cost 3 ms of every plan."""
    rows = w[:, 0::f].copy()
    for dc in range(1, f):
        rows += w[:, dc::f]
    out = rows[0::f].copy()
    for dr in range(1, f):
        out += rows[dr::f]
    out /= np.float32(f * f)
    return out


def _shortcut(
    cells: NDArray[np.intp], costs: NDArray[np.uint8], w: NDArray[np.float32], p: PlannerParams
) -> NDArray[np.intp]:
    """Indices of the raw path kept after greedy line-of-sight shortcutting (exponential then binary search)."""
    return _shortcut_kernel(cells, costs, w, p.smooth_cost)


@numba.njit("boolean(intp[:, :], uint8[:, :], float32[:, :], int64, intp, intp)", nogil=True)
def _visible(
    cells: NDArray[np.intp], costs: NDArray[np.uint8], w: NDArray[np.float32], limit: int, i: int, j: int
) -> bool:
    """Whether the straight line between the centres of path cells i and j, sampled at a quarter cell, crosses
    only passable cells of cost <= `limit`."""
    a0, a1 = cells[i, 0], cells[i, 1]
    d0, d1 = cells[j, 0] - a0, cells[j, 1] - a1
    n = 4 * max(abs(d0), abs(d1)) + 1
    for k in range(n + 1):
        t = k / n
        row = math.floor(a0 + 0.5 + d0 * t)
        col = math.floor(a1 + 0.5 + d1 * t)
        if not math.isfinite(w[row, col]) or costs[row, col] > limit:
            return False
    return True


@numba.njit("intp[:](intp[:, :], uint8[:, :], float32[:, :], int64)", nogil=True)
def _shortcut_kernel(
    cells: NDArray[np.intp], costs: NDArray[np.uint8], w: NDArray[np.float32], smooth_cost: int
) -> NDArray[np.intp]:
    """`_shortcut` compiled: its ~20 line-of-sight tests per plan cost 20 us each as numpy calls. A shortcut may
    cross cells up to `smooth_cost` or up to the highest cost of the stretch it replaces.

    Compiled when the module is imported (its signature given: ~0.9 s CPU once per process), so that no run's
    measured agent CPU includes the compilation."""
    n = len(cells)
    path_cost = np.empty(n, dtype=np.int64)
    for k in range(n):
        path_cost[k] = costs[cells[k, 0], cells[k, 1]]
    keep = np.empty(n, dtype=np.intp)
    keep[0] = 0
    kept = 1
    i = 0
    while i < n - 1:
        good, step = i + 1, 1
        bad = n
        while good < n - 1:
            j = min(i + 2 * step, n - 1)
            if _visible(cells, costs, w, max(smooth_cost, path_cost[i : j + 1].max()), i, j):
                good, step = j, 2 * step
                if j == n - 1:
                    break
            else:
                bad = j
                break
        while bad - good > 1:
            mid = (good + bad) // 2
            if _visible(cells, costs, w, max(smooth_cost, path_cost[i : mid + 1].max()), i, mid):
                good = mid
            else:
                bad = mid
        keep[kept] = good
        kept += 1
        i = good
    return keep[:kept].copy()
