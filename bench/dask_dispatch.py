"""What Dask dispatch costs: the same runs through the local process pool and through a Dask cluster on this
machine (a real `dask scheduler` and as many single-threaded `dask worker` processes as pool workers), wall
time ratio Dask / pool, alternated so both see the same load.

    ./.venv/bin/python -m bench.dask_dispatch [--runs N] [--configs full] [--rounds R] [--no-write]

Each side is timed as `wsnav experiment` meets it: the pool's worker processes start inside its time (a new
pool per experiment), the cluster's workers are already running (a cluster outlives experiments; its start-up
is left out); connecting, shipping the site and every task are in. The tables must agree (apart from the
columns that measure the machine). `--quick`: one run of A -> B under `full`, one worker each side, one round; Dask's wall time over the
pool's at most 3 (measured 0.42 at load 8: the pool's time holds its workers' start).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from bench.benchmarks_md import machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser
from tests.dask_fixtures import DaskCluster
from wsnav.experiments.run_plan import plan_runs
from wsnav.experiments.runner import Outcome, run_experiment
from wsnav.experiments.single_run import COLUMNS, NONDETERMINISTIC
from wsnav.schemas.site import load_site

REPO = Path(__file__).resolve().parent.parent
SECTION = "## Experiment dispatch: Dask cluster vs local process pool (bench/dask_dispatch.py)"
WORKERS = 2


def _rows(outcome: Outcome) -> list[list[object]]:
    keep = [c for c in COLUMNS if c not in NONDETERMINISTIC]
    return [[r[c] for c in keep] for r in outcome.table.to_dict("records")]


def main() -> None:
    parser = quick_parser(__doc__)
    parser.add_argument("--runs", type=int, default=2, help="runs per route and configuration (2)")
    parser.add_argument("--configs", default="full", help="configurations, comma-separated (full)")
    parser.add_argument("--rounds", type=int, default=2, help="pool/Dask pairs, alternated (2)")
    args = parse_quick_args(parser)
    if args.quick:
        args.runs, args.configs, args.rounds = 1, "full", 1
    configs: list[str] = str(args.configs).split(",")
    site = load_site(REPO / "sites" / "school")
    specs = plan_runs(site.spec, configs, args.runs, 1)
    workers = WORKERS
    if args.quick:
        specs, workers = specs[:1], 1
    lines: list[str] = []
    loads = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory(prefix="wsnav-dask-bench-") as tmp:
        cluster = DaskCluster(Path(tmp))
        try:
            cluster.start(workers=workers)
            ratios: list[float] = []
            for i in range(args.rounds):
                pool = run_experiment(site.path, specs, workers=workers)
                loads.append(os.getloadavg()[0])
                dask = run_experiment(site.path, specs, workers=workers, scheduler=cluster.address)
                loads.append(os.getloadavg()[0])
                if _rows(pool) != _rows(dask):
                    raise SystemExit("the Dask table differs from the pool's: not a fair comparison")
                ratios.append(dask.wall_s / pool.wall_s)
                lines.append(
                    f"round {i + 1}: pool {pool.wall_s:6.1f} s, Dask {dask.wall_s:6.1f} s, "
                    f"Dask / pool {ratios[-1]:.2f}x (load {loads[-2]:.1f} / {loads[-1]:.1f})"
                )
                print(lines[-1], flush=True)
        finally:
            cluster.stop()
    head = (
        f"school site, {len(specs)} runs ({args.runs} per route, {args.configs}), {workers} pool workers vs "
        f"{workers} single-threaded Dask workers on 127.0.0.1 (already running); same tables; "
        f"load {min(loads):.1f}-{max(loads):.1f}"
    )
    summary = f"Dask / pool wall time: {min(ratios):.2f}x-{max(ratios):.2f}x over {args.rounds} rounds"
    print(head)
    print(summary)
    if args.quick:
        check_ratio("Dask wall time / process pool wall time", max(ratios), 3.0)
        finish_quick()
    if args.no_write:
        return
    cmd = "./.venv/bin/python -m bench.dask_dispatch" + (f" --runs {args.runs}" if args.runs != 2 else "")
    if args.configs != "full":
        cmd += f" --configs {args.configs}"
    if args.rounds != 2:
        cmd += f" --rounds {args.rounds}"
    write_section(
        SECTION,
        f"`{cmd}` ({machine_note()}). The machine is shared with other work: read the ratio, measured in the "
        "same run with pool and Dask alternated, not the absolute times.\n\n"
        "```\n" + "\n".join([head, *lines, summary]) + "\n```",
    )


if __name__ == "__main__":
    main()
