"""The offline plan behind `wsnav plan`: the costmap the agent would hold with some zones `blocked` (the agent's
own LayeredCostmap: static layer, zones lethal, inflation for the robot's footprint), A* over it, and the JSON
of the result (the command and its picture live in wsnav.plan_command: components do not import wsnav).

Kept apart from robot_agent.cli so that every other wsnav command starts without loading scipy and pyastar2d.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.planning.astar import Plan, PlannerParams, plan_path, simplify
from wsnav.runtime.cli_support import CliError
from wsnav.schemas.messages import OperatorBlock
from wsnav.schemas.ros_map import FREE
from wsnav.schemas.site import Site, SiteError, load_site
from wsnav.zones.geometry import GridFrame, polygon_window
from wsnav.zones.zone_rule import ZoneRule


def zone_lethal(site: Site, blocked: Sequence[str]) -> NDArray[np.bool_]:
    """Cells of the blocked zones (what the zone layer marks lethal)."""
    frame = GridFrame.of_grid(site.grid)
    mask = np.zeros((frame.height, frame.width), dtype=bool)
    for zone_id in blocked:
        window = polygon_window(site.spec.zone(zone_id).polygon, frame)
        if window.mask.size:
            mask[window.rows, window.cols] |= window.mask
    return mask


def site_costmap(site: Site, blocked: Sequence[str], inflation: InflationParams) -> NDArray[np.uint8]:
    """The agent's global costmap for these zone states: the robot's own LayeredCostmap, each blocked zone set
    as an operator block (so a zone no node watches can be blocked too), no lidar."""
    layer = ZoneRule(site.spec, GridFrame.of_grid(site.grid))
    for zone_id in blocked:
        layer.on_operator_block(f"plan-{zone_id}", OperatorBlock(zone=zone_id), 0.0)
    return LayeredCostmap(site.grid, inflation, zone_layer=layer, obstacle_layer=False).master


def parse_point(site: Site, text: str, what: str) -> tuple[float, float, float]:
    """A named point of the site, or `x,y` / `x,y,yaw` in metres; must lie in the map's free space."""
    if text in site.spec.points:
        return site.point(text)
    parts = text.split(",")
    try:
        values = [float(v) for v in parts]
    except ValueError:
        values = []
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        known = ", ".join(sorted(site.spec.points)) or "none"
        raise CliError(f"{what} {text!r}: not a point of site {site.name!r} (points: {known}) nor x,y[,yaw]")
    x, y = values[0], values[1]
    yaw = values[2] if len(values) == 3 else 0.0
    grid = site.grid
    if not grid.contains(x, y):
        x0, y0, x1, y1 = grid.bounds
        raise CliError(f"{what} [{x:g}, {y:g}] lies outside the map (x {x0:g}..{x1:g}, y {y0:g}..{y1:g})")
    row, col = grid.world_to_cell(x, y)
    value = int(grid.data[row, col])
    if value != FREE:
        raise CliError(f"{what} [{x:g}, {y:g}] lies inside {'unknown space' if value < 0 else 'a wall'}")
    return x, y, yaw


@dataclass(frozen=True)
class OfflinePlan:
    """One offline plan: what `wsnav plan` prints (`json`) and what its picture draws."""

    site: Site
    plan: Plan
    blocked: list[str]
    json: dict[str, object]


def offline_plan(
    site_path: Path,
    start_text: str,
    goal_text: str,
    block: Sequence[str] = (),
    robot: str | None = None,
    inflation_radius: float = 1.0,
    cost_scaling: float = 3.0,
) -> OfflinePlan:
    """Plan from `start_text` to `goal_text` (named points or x,y[,yaw]) with the zones in `block` lethal.

    Bad input (site, points, zones, robot, flags) raises CliError with one line naming the flag.
    """
    try:
        site = load_site(site_path)
    except SiteError as exc:
        raise CliError(str(exc)) from None
    start = parse_point(site, start_text, "--from")
    goal = parse_point(site, goal_text, "--to")
    zone_ids = [z.id for z in site.spec.zones]
    blocked: list[str] = []
    for zone in block:
        if zone not in zone_ids:
            raise CliError(
                f"--block {zone!r}: no such zone in site {site.name!r} (zones: {', '.join(zone_ids)})"
            )
        if zone not in blocked:
            blocked.append(zone)
    radius = robot_radius(site, robot)
    for flag, value in (("--inflation-radius", inflation_radius), ("--cost-scaling", cost_scaling)):
        if not (math.isfinite(value) and value >= 0):
            raise CliError(f"{flag} {value:g}: expected a finite number >= 0")
    try:
        inflation = InflationParams(radius, max(inflation_radius, radius), cost_scaling)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    t0 = time.perf_counter()
    costs = site_costmap(site, blocked, inflation)
    costmap_ms = (time.perf_counter() - t0) * 1000.0
    plan = plan_path(costs, site.grid.resolution, site.grid.origin, start[:2], goal[:2], PlannerParams())
    return OfflinePlan(
        site, plan, blocked, plan_json(site, start_text, goal_text, start, goal, blocked, plan, costmap_ms)
    )


def robot_radius(site: Site, robot_id: str | None) -> float:
    robots = site.spec.robots
    if robot_id is None:
        return robots[0].footprint_radius if robots else 0.105
    for robot in robots:
        if robot.id == robot_id:
            return robot.footprint_radius
    raise CliError(f"--robot {robot_id!r}: no such robot in site {site.name!r}")


def plan_json(
    site: Site,
    start_name: str,
    goal_name: str,
    start: tuple[float, float, float],
    goal: tuple[float, float, float],
    blocked: list[str],
    plan: Plan,
    costmap_ms: float,
) -> dict[str, object]:
    """The command's output: path vertices within half a cell of the planned polyline, in metres."""
    path = simplify(plan.path, site.grid.resolution / 2) if plan.reachable else plan.path
    return {
        "site": site.name,
        "from": start_name,
        "to": goal_name,
        "start": [round(v, 4) for v in start],
        "goal": [round(v, 4) for v in goal],
        "blocked_zones": blocked,
        "reachable": plan.reachable,
        "reason": plan.reason,
        "length_m": round(plan.length_m, 3) if plan.reachable else None,
        "path": [[round(float(x), 3), round(float(y), 3)] for x, y in path],
        "plan_ms": round(plan.plan_ms, 2),
        "costmap_ms": round(costmap_ms, 2),
    }
