"""The whole experiment's wall time and real-time factor (target: 50 runs per route and configuration in
<= 10 min, >= 100x real time), by configuration, on this machine's cores with one embedded broker per worker.

    ./.venv/bin/python -m bench.experiment_wall [--runs N] [--workers K] [--run-broker amqtt|mosquitto]
                                                [--configs default,full] [--no-write] [--out DIR]

With a smaller `--runs` the full experiment's wall time is extrapolated (runs scale linearly) and says so.
With `--out` it also writes the experiment's table, report and figures there (what `wsnav experiment` writes),
so one run of the whole experiment gives both its results and its speed (`--configs default,zones,full` for the
published report's three configurations; the timing is `default` and `full` by default). Each run starts its own broker:
Mosquitto by default here (the rows are the same as with amqtt, the wall time lower), `--run-broker amqtt` for
the embedded amqtt broker that `wsnav experiment` uses by default. `--quick`: one run of A -> B per configuration;
`full`'s agent CPU per simulated second over `default`'s at most 1 (measured 0.24-0.28), and `default`'s over a
fixed reference workload timed in the same run (`bench.quick.reference_work_s`, in s) at most 4 (measured 1.4 at
load 5).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from bench.benchmarks_md import write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser, reference_work_s
from wsnav.experiments.run_plan import plan_runs
from wsnav.experiments.runner import progress_line, report_header, run_experiment, write_outputs
from wsnav.experiments.worker import RUN_BROKERS
from wsnav.robot_agent.agent_config import BUILTIN
from wsnav.schemas.site import load_site

REPO = Path(__file__).resolve().parent.parent
SECTION = "## Experiment wall time (bench/experiment_wall.py)"
FULL_RUNS = 50
CONFIGS = ["default", "full"]
DEFAULT_CPU_BOUND = 4.0
"""Quick mode's bound on `default`'s agent CPU per simulated second over the reference workload."""


def main() -> None:
    parser = quick_parser(__doc__)
    parser.add_argument("--runs", type=int, default=FULL_RUNS, help="runs per route and configuration")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--run-broker", choices=RUN_BROKERS, default="mosquitto")
    parser.add_argument("--out", type=Path, default=None, help="also write the experiment's report here")
    parser.add_argument(
        "--configs",
        default=",".join(CONFIGS),
        help=f"built-in configurations, comma-separated ({','.join(BUILTIN)})",
    )
    args = parse_quick_args(parser)
    configs = [c for c in args.configs.split(",") if c]
    if not {"default", "full"} <= set(configs) or not set(configs) <= set(BUILTIN):
        parser.error(f"--configs: built-in configurations including default and full ({','.join(BUILTIN)})")
    if args.quick:
        args.runs = 1
        configs = CONFIGS
    site = load_site(REPO / "sites" / "school")
    specs = plan_runs(site.spec, configs, args.runs, args.seed)
    if args.quick:
        specs = [s for s in specs if s.route == specs[0].route]
    load = os.getloadavg()[0]
    outcome = run_experiment(
        site.path, specs, workers=args.workers, progress=progress_line(), run_broker=args.run_broker
    )
    t = outcome.table
    sim_s = outcome.simulated_s
    cpu_per_sim: dict[str, float] = {}
    lines = [
        f"school site, {len(specs)} runs ({args.runs} per route and configuration), {args.workers} workers, "
        f"{os.cpu_count()} CPUs, one {args.run_broker} broker per run, load {load:.1f} at the start",
        f"wall {outcome.wall_s:.0f} s for {sim_s:.0f} s simulated: real-time factor {sim_s / outcome.wall_s:.0f}x; "
        f"{int(t['collisions'].to_numpy(dtype=np.int64).sum())} collisions, "
        f"{int(t['success'].to_numpy(dtype=bool).sum())}/{len(t)} arrived",
    ]
    for config in configs:
        part = t.loc[t["config"] == config]
        cpu = float(part["agent_cpu_s"].to_numpy(dtype=np.float64).sum())
        sim = float(part["time_s"].to_numpy(dtype=np.float64).sum())
        cpu_per_sim[config] = cpu / sim
        lines.append(f"  {config:8s} agent CPU {cpu:7.0f} s for {sim:6.0f} s simulated ({cpu / sim:.4f} s/s)")
        process = float(part["process_cpu_s"].to_numpy(dtype=np.float64).sum())
        mem = part["peak_mem_mb"].to_numpy(dtype=np.float64)
        lines.append(
            f"  {config:8s} run-process CPU {process:7.0f} s ({process / sim:.4f} s/s); "
            f"peak memory {mem.min():.0f}-{mem.max():.0f} MB a run"
        )
    cmd = "./.venv/bin/python -m bench.experiment_wall" + (
        f" --runs {args.runs}" if args.runs != FULL_RUNS else ""
    )
    if args.seed != 1:
        cmd += f" --seed {args.seed}"
    if args.run_broker != "mosquitto":
        cmd += f" --run-broker {args.run_broker}"
    if configs != CONFIGS:
        cmd += f" --configs {','.join(configs)}"
    if args.out is not None:
        cmd += f" --out {args.out}"
        where = f"{'a Mosquitto process' if args.run_broker == 'mosquitto' else 'an embedded amqtt broker'} of each run's own"
        header = report_header(
            site.name, configs, args.runs, args.seed, args.workers, where, outcome, cmd, args.run_broker
        )
        lines.append(f"report: {write_outputs(site, outcome, args.out, header)}")
    if args.runs != FULL_RUNS:
        scale = FULL_RUNS / args.runs
        lines.append(
            f"extrapolated to {FULL_RUNS} runs: ~{outcome.wall_s * scale / 60:.0f} min wall (measured with {args.runs})"
        )
    print("\n".join(lines))
    if args.quick:
        ref = reference_work_s(clock=time.thread_time)  # the figure is CPU time
        print(f"reference workload: {ref * 1000:.1f} ms of CPU")
        check_ratio(
            "`full` agent CPU / `default` agent CPU, per simulated second",
            cpu_per_sim["full"] / cpu_per_sim["default"],
            1.0,
        )
        check_ratio(
            "`default` agent CPU per simulated second / reference workload",
            cpu_per_sim["default"] / ref,
            DEFAULT_CPU_BOUND,
        )
        finish_quick()
    if args.no_write:
        return
    write_section(
        SECTION,
        f"`{cmd}` ({time.strftime('%Y-%m-%d')}); target: {FULL_RUNS} runs in <= 10 min, >= 100x real time.\n\n"
        "```\n" + "\n".join(lines) + "\n```",
    )


if __name__ == "__main__":
    main()
