"""Simulated robot benchmark on the school map: lidar scans/s, controller steps/s, and the real-time factor of the
simulated TurtleBot3 + path follower driving A -> B.

    ./.venv/bin/python -m bench.sim_robot [--scans 3000] [--runs 3] [--no-write]

Scans: 360-beam, 3.5 m sweeps from random free poses of the school map (1040 x 640 cells), cast against the
world grid, after one untimed scan that compiles the numba kernel (its time is reported on its own). Controller: `PathFollower.compute` on a 3 x 3 m local costmap window, timed inside the A -> B drive.
Real-time factor: simulated seconds / wall seconds of the whole loop (controller 20 Hz, physics 0.05 s, lidar
at 5 Hz, local window cut each step) from A until `arrived`; the costmap is the static map's, prepared once.
Writes its section of BENCHMARKS.md unless --no-write. `--quick`: 300 scans and one drive, each cost (a scan, a
controller step, a simulated second of the drive) over a fixed reference workload timed in the same run
(`bench.quick.reference_work_s`), against bounds 3x the ratios measured at load 5 (0.008, 0.0067, 0.23).
"""

from __future__ import annotations

import math
import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.benchmarks_md import write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser, reference_work_s
from wsnav.navigation.control.controller import PathFollower
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.planning.astar import plan_path
from wsnav.robot_agent.sim.lidar import LidarParams, cast_scan
from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.schemas.site import load_site

REPO = Path(__file__).resolve().parent.parent
SECTION = "## Simulated robot: lidar, controller, real-time factor"
COMMAND = "./.venv/bin/python -m bench.sim_robot"
CONTROL_DT = 0.05
LOCAL_M = 3.0
SCAN_BOUND, STEP_BOUND, DRIVE_BOUND = 0.025, 0.02, 0.7
"""Quick mode's bounds on each cost over the reference workload."""


def bench_scans(world: SimWorldGrid, count: int) -> float:
    rng = np.random.default_rng(0)
    free = np.argwhere(~world.occupied)
    cells = free[rng.integers(0, len(free), count)]
    poses = [
        (*world.frame.cell_to_world(int(r), int(c)), float(rng.uniform(-math.pi, math.pi))) for r, c in cells
    ]
    params = LidarParams()
    t0 = time.perf_counter()
    for i, pose in enumerate(poses):
        cast_scan(world.occupied, world.frame, pose, params, float(i))
    return count / (time.perf_counter() - t0)


@dataclass
class Drive:
    sim_s: float
    wall_s: float
    controller_s: float
    controller_steps: int
    collisions: int
    distance_m: float

    @property
    def real_time_factor(self) -> float:
        return self.sim_s / self.wall_s

    @property
    def controller_rate(self) -> float:
        return self.controller_steps / self.controller_s


def bench_follow(costmap: LayeredCostmap, site_dir: Path) -> Drive:
    """One A -> B drive: the whole loop timed, and the controller's share of it timed on its own."""
    site = load_site(site_dir)
    world = SimWorldGrid(site.grid)
    a, b = site.point("A"), site.point("B")
    plan = plan_path(costmap.master, site.grid.resolution, site.grid.origin, a[:2], b[:2])
    bot = SimTurtleBot3("robot1", world, a)
    follower = PathFollower()
    follower.set_path(plan.path, goal_yaw=b[2])
    t, steps, controller_s = 0.0, 0, 0.0
    status, reason = "following", ""
    t0 = time.perf_counter()
    while t < 600.0 and status == "following":
        local, frame = costmap.local_window(bot.pose(), LOCAL_M)
        c0 = time.perf_counter()
        result = follower.compute(bot.pose(), bot.velocity(), local, frame)
        controller_s += time.perf_counter() - c0
        steps += 1
        status, reason = result.status, result.reason
        bot.command(result.velocity)
        t += CONTROL_DT
        bot.step(CONTROL_DT, t)
    wall = time.perf_counter() - t0
    if status != "arrived":
        raise SystemExit(f"bench: A -> B ended {status} ({reason}) at t={t:.1f}s")
    return Drive(t, wall, controller_s, steps, bot.collisions, bot.distance_m)


def main() -> None:
    parser = quick_parser(__doc__)
    parser.add_argument("--scans", type=int, default=3000)
    parser.add_argument("--runs", type=int, default=3)
    args = parse_quick_args(parser)
    if args.quick:
        args.scans, args.runs = min(args.scans, 300), 1
    site_dir = REPO / "sites" / "school"
    site = load_site(site_dir)
    world = SimWorldGrid(site.grid)
    c0 = time.perf_counter()
    cast_scan(world.occupied, world.frame, site.point("A"), LidarParams(), 0.0)
    compile_s = time.perf_counter() - c0
    costmap = LayeredCostmap(site.grid, InflationParams(), obstacle_layer=False)
    a, b = site.point("A"), site.point("B")
    plan = plan_path(costmap.master, site.grid.resolution, site.grid.origin, a[:2], b[:2])

    scans = [bench_scans(world, args.scans) for _ in range(args.runs)]
    drives = [bench_follow(costmap, site_dir) for _ in range(args.runs)]
    steps = [d.controller_rate for d in drives]
    rtf = [d.real_time_factor for d in drives]
    last = drives[-1]
    sim_s, wall_s, collisions, distance = (
        last.sim_s,
        statistics.median(d.wall_s for d in drives),
        last.collisions,
        last.distance_m,
    )
    load = os.getloadavg()[0]
    lines = [
        f"school map {world.frame.width} x {world.frame.height} cells, {os.cpu_count()} CPUs, load {load:.1f}; "
        f"median (min-max) of {args.runs} runs",
        f"lidar (360 beams, 3.5 m):        {statistics.median(scans):8.0f} scans/s ({min(scans):.0f}-{max(scans):.0f})",
        f"lidar first scan (numba compile): {compile_s:8.2f} s",
        f"controller compute in the drive:   {statistics.median(steps):8.0f} steps/s ({min(steps):.0f}-{max(steps):.0f})",
        f"A -> B drive: {sim_s:.1f} s simulated in {wall_s:.2f} s wall, real-time factor {statistics.median(rtf):.0f}x "
        f"({min(rtf):.0f}-{max(rtf):.0f}); {distance:.2f} m driven (plan {plan.length_m:.2f} m), {collisions} collisions",
    ]
    print("\n".join(lines))
    if args.quick:
        ref = reference_work_s()
        print(f"reference workload: {ref * 1000:.1f} ms")
        check_ratio("one lidar scan / reference workload", 1.0 / statistics.median(scans) / ref, SCAN_BOUND)
        check_ratio(
            "one controller step / reference workload", 1.0 / statistics.median(steps) / ref, STEP_BOUND
        )
        check_ratio("one simulated second of A -> B / reference workload", wall_s / sim_s / ref, DRIVE_BOUND)
        finish_quick()
    if args.no_write:
        return
    when = time.strftime("%Y-%m-%d")
    write_section(
        SECTION,
        f"```\n{COMMAND}\n```\n\n"
        "The simulated TurtleBot3 Burger and its controller on the school map (`sites/school`, 0.05 m cells): "
        "the lidar cast from random free poses (exact grid traversal, a numba kernel compiled by one untimed "
        "scan first), the regulated pure pursuit "
        "controller's `compute` on a 3 x 3 m local costmap window, and the whole loop (controller 20 Hz, physics "
        "0.05 s, lidar 5 Hz, the layered costmap's rolling window, static layer only, prepared once) driving A -> B. "
        f"Measured {when} (machine shared with other jobs, load {load:.1f}):\n\n"
        "| what | median | range |\n| --- | --- | --- |\n"
        f"| lidar scans/s (target >= 2000) | {statistics.median(scans):.0f} | {min(scans):.0f}-{max(scans):.0f} |\n"
        f"| lidar's first scan of a process (numba compile), s | {compile_s:.2f} | |\n"
        f"| controller steps/s | {statistics.median(steps):.0f} | {min(steps):.0f}-{max(steps):.0f} |\n"
        f"| A -> B real-time factor (sim + controller) | {statistics.median(rtf):.0f}x | {min(rtf):.0f}-{max(rtf):.0f}x |\n\n"
        f"The drive: {sim_s:.1f} s simulated, {distance:.2f} m (plan {plan.length_m:.2f} m), {collisions} collisions. "
        "The loop's cost is mostly the lidar (5 scans per simulated second) and the controller (20 per second); "
        "the agent's costmap and planner come on top in the experiment.",
    )


if __name__ == "__main__":
    main()
