"""The controller's local costmap: CPU per update and per second of `default`'s and `full`'s (the paper's lever).

On the school site, each configuration's own rolling window (`default` 3 x 3 m at 10 Hz, `full` 2 x 2 m at 5 Hz,
robot_agent/configs) is updated from poses along the site's points, each with the simulated LDS-01's scan cast
there beforehand; one sample is one `LocalCostmap.update` (re-home, mark and clear the scan, merge, inflate), in
thread CPU time. Baselines timed in the same run: the window of the global costmap the controller read before
the local costmap existed (`LayeredCostmap.local_window`, same size), and the fixed reference workload
(`bench.quick.reference_work_s`). Samples come in a shuffled order with random pauses of 0-2 ms between them.
Writes its section of BENCHMARKS.md unless --no-write.
`--quick`: 300 updates a configuration; `full`'s CPU per second over `default`'s at most 1.0 (the reduced set
must cost less), and `default`'s update over the reference workload at most 0.1 (measured 0.012 at load 2).
"""

from __future__ import annotations

import random
import statistics
import time
from pathlib import Path

import numpy as np

from bench.benchmarks_md import commit, machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser, reference_work_s
from wsnav.navigation.backend import LaserScan, Pose
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.costmap.local_costmap import LocalCostmap
from wsnav.robot_agent.agent_config import load_agent_config
from wsnav.robot_agent.sim.lidar import LidarParams, cast_scan
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.schemas.site import Site, load_site
from wsnav.zones.geometry import GridFrame

REPO = Path(__file__).resolve().parent.parent
SECTION = "## Local costmap: CPU per update (bench/local_costmap.py)"
COMMAND = "./.venv/bin/python -m bench.local_costmap"
CONFIGS = ("default", "full")
UPDATE_BOUND = 0.1
"""Quick mode's bound on `default`'s update over the reference workload (both thread CPU)."""


def poses_and_scans(site: Site, count: int, seed: int) -> list[tuple[Pose, LaserScan]]:
    """`count` poses on free cells within 2 m of the site's points, each with the scan the simulated lidar sees
    there (cast before the timing starts: the lidar is the robot's, not the costmap's, work)."""
    rng = np.random.default_rng(seed)
    frame = GridFrame.of_grid(site.grid)
    occupied = SimWorldGrid(site.grid).occupied
    points = list(site.spec.points.values())
    out: list[tuple[Pose, LaserScan]] = []
    while len(out) < count:
        x0, y0, _ = points[len(out) % len(points)]
        x, y = x0 + rng.uniform(-2.0, 2.0), y0 + rng.uniform(-2.0, 2.0)
        row, col = frame.world_to_cell(x, y)
        if not (0 <= row < frame.height and 0 <= col < frame.width) or occupied[row, col]:
            continue
        pose: Pose = (x, y, float(rng.uniform(-np.pi, np.pi)))
        out.append((pose, cast_scan(occupied, frame, pose, LidarParams(), 0.0)))
    return out


def measure(site: Site, config_name: str, samples: list[tuple[Pose, LaserScan]]) -> dict[str, float]:
    """Median thread-CPU ms of one local costmap update and of one global-costmap window of the same size."""
    config = load_agent_config(config_name)
    radius = max(r.footprint_radius for r in site.spec.robots)
    inflation = config.inflation.params(radius)
    plugins = config.local_plugins
    assert plugins is not None, f"{config_name} names no local costmap"
    global_costmap = LayeredCostmap(
        site.grid, inflation
    )  # its map and inflation; the zones are not the local one's
    local = LocalCostmap(global_costmap, config.local_costmap_size_m, inflation, plugins)
    order = list(range(len(samples)))
    random.Random(config_name).shuffle(order)
    update_s: list[float] = []
    window_s: list[float] = []
    for i in order:
        pose, scan = samples[i]
        time.sleep(random.uniform(0.0, 0.002))
        t0 = time.thread_time()
        local.update(pose, scan)
        t1 = time.thread_time()
        global_costmap.local_window(pose, config.local_costmap_size_m)
        t2 = time.thread_time()
        update_s.append(t1 - t0)
        window_s.append(t2 - t1)
    update_ms = statistics.median(update_s) * 1000.0
    return {
        "size_m": config.local_costmap_size_m,
        "rate_hz": config.local_costmap_rate_hz,
        "update_ms": update_ms,
        "update_p99_ms": float(np.percentile(update_s, 99)) * 1000.0,
        "window_ms": statistics.median(window_s) * 1000.0,
        "ms_per_s": update_ms * config.local_costmap_rate_hz,
    }


def main() -> None:
    parser = quick_parser(__doc__)
    parser.add_argument("--updates", type=int, default=3000, help="updates per configuration")
    args = parse_quick_args(parser)
    if args.updates < 10:
        parser.error("--updates: at least 10")
    updates = 300 if args.quick else args.updates
    site = load_site(REPO / "sites" / "school")
    samples = poses_and_scans(site, updates, seed=1)
    ref_ms = reference_work_s(clock=time.thread_time) * 1000.0
    rows = {name: measure(site, name, samples) for name in CONFIGS}
    lines = [
        f"school site, {updates} updates a configuration from poses near its points (LDS-01 scans), thread CPU; "
        f"reference workload {ref_ms:.1f} ms",
        "| config | window | rate | update p50 | update p99 | global window (before) | CPU per second |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, r in rows.items():
        lines.append(
            f"| {name} | {r['size_m']:g} x {r['size_m']:g} m | {r['rate_hz']:g} Hz | {r['update_ms']:.3f} ms | "
            f"{r['update_p99_ms']:.3f} ms | {r['window_ms']:.4f} ms ({r['update_ms'] / r['window_ms']:.0f}x) | "
            f"{r['ms_per_s']:.2f} ms/s |"
        )
    lever = rows["full"]["ms_per_s"] / rows["default"]["ms_per_s"]
    lines.append(f"`full`'s local costmap CPU per second over `default`'s: {lever:.2f}x")
    print("\n".join(lines))
    if args.quick:
        check_ratio("`full` local costmap CPU per second / `default`'s", lever, 1.0)
        check_ratio(
            "`default` local costmap update / reference workload",
            rows["default"]["update_ms"] / ref_ms,
            UPDATE_BOUND,
        )
        finish_quick()
    if args.no_write:
        return
    cmd = COMMAND + (f" --updates {args.updates}" if args.updates != 3000 else "")
    write_section(SECTION, f"`{cmd}` (commit {commit()}, {machine_note()})\n\n" + "\n".join(lines))


if __name__ == "__main__":
    main()
