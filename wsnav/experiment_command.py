"""What `wsnav experiment` and `wsnav demo` do once their arguments parse: check them, run, write, summarise."""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import numpy as np
import pandas as pd

from wsnav.broker.mosquitto.process import MosquittoError
from wsnav.experiments.cluster import ClusterError
from wsnav.experiments.report import ReportError, paths_figure, read_runs, rerender
from wsnav.experiments.run_plan import RunSpec, plan_runs
from wsnav.experiments.runner import (
    Outcome,
    collect,
    progress_line,
    provenance,
    report_header,
    run_experiment,
    write_outputs,
    write_run_pictures,
)
from wsnav.experiments.single_run import BrokerAt
from wsnav.robot_agent.agent_config import AgentConfigError, load_agent_config
from wsnav.runtime.cli_support import CliError
from wsnav.schemas.site import Site, SiteError, load_site


def _site(path: Path) -> Site:
    try:
        return load_site(path)
    except SiteError as exc:
        raise CliError(str(exc)) from None


def _writable(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"{out}: cannot create output directory: {exc.strerror}") from None


def _specs(site: Site, configs: list[str], runs: int, seed: int) -> list[RunSpec]:
    if not site.spec.routes:
        raise CliError(f"site {site.name} has no routes to run")
    if not site.spec.robots or site.spec.robots[0].id != "robot1":
        raise CliError(f"site {site.name}: the experiment drives robot1, which the site does not have")
    return plan_runs(site.spec, configs, runs, seed)


def _configs(args: argparse.Namespace) -> list[str]:
    configs = [c.strip() for c in args.configs.split(",") if c.strip()]
    if not configs:
        raise CliError("--configs names no configuration")
    for config in configs:
        try:
            load_agent_config(config)
        except AgentConfigError as exc:
            raise CliError(f"--configs: {exc}") from None
    return configs


def _cluster_size(address: str) -> int:
    """The cluster's worker threads; a scheduler that does not answer, or has no workers, is one line."""
    from wsnav.experiments.cluster import cluster_size

    try:
        return cluster_size(address)
    except ClusterError as exc:
        raise CliError(f"--scheduler {address}: {exc}") from None


def _compared(folder: Path | None) -> tuple[pd.DataFrame, str] | None:
    """The other backend's runs table and header (`--compare`), read before anything runs."""
    if folder is None:
        return None
    try:
        return read_runs(folder)
    except ReportError as exc:
        raise CliError(f"--compare: {exc}") from None


def experiment(args: argparse.Namespace) -> int:
    if args.report_only:
        try:
            report = rerender(args.out, args.compare)
        except ReportError as exc:
            raise CliError(f"--report-only: {exc}") from None
        print(f"wrote {report} from {args.out / 'runs.csv'} (nothing rerun)")
        return 0
    compare = _compared(args.compare)
    if args.backend == "ros":
        return experiment_on_ros(args, compare)
    if args.move_base_cmd is not None:
        raise CliError("--move-base-cmd goes with --backend ros")
    if args.runs < 1:
        raise CliError(f"--runs must be at least 1, got {args.runs}")
    if args.workers < 1:
        raise CliError(f"--workers must be at least 1, got {args.workers}")
    configs = _configs(args)
    if args.broker is not None and args.run_broker is not None:
        raise CliError("--run-broker is the broker each run starts for itself: it does not go with --broker")
    broker: BrokerAt | None = None
    if args.broker is not None:
        if args.credentials is None or not (args.credentials / "robot1.json").is_file():
            raise CliError(
                "--broker needs --credentials DIR holding the site's credentials (robot1.json, ...)"
            )
        broker = BrokerAt(args.broker[0], args.broker[1], args.credentials)
    elif args.credentials is not None:
        raise CliError("--credentials goes with --broker")
    if broker is not None and args.scheduler is not None:
        raise CliError("--scheduler runs each run on its own embedded broker: it does not go with --broker")
    run_broker: str = args.run_broker or "amqtt"
    if run_broker == "mosquitto" and shutil.which("mosquitto") is None:
        raise CliError(
            "--run-broker mosquitto: mosquitto is not installed (Debian: apt-get install mosquitto)"
        )
    if args.record is not None and args.scheduler is not None:
        raise CliError("--record writes on this machine's disk: it does not go with --scheduler")
    if args.record is not None:
        _recordable(args.record)
    site = _site(args.site)
    _writable(args.out)
    if args.pictures is not None:
        _writable(args.pictures)
    specs = _specs(site, configs, args.runs, args.seed)
    workers = 1 if broker is not None else min(args.workers, len(specs))
    own = "a Mosquitto process" if run_broker == "mosquitto" else "an embedded amqtt broker"
    where = f"{own} of each run's own" if broker is None else f"{broker.host}:{broker.port}"
    if args.scheduler is not None:
        workers = _cluster_size(args.scheduler)
        where = f"{own} of each run's own, on the Dask cluster at {args.scheduler}"
        print(
            f"{len(specs)} runs ({args.runs} per route and configuration) on the Dask cluster at {args.scheduler}"
        )
    else:
        print(f"{len(specs)} runs ({args.runs} per route and configuration) on {workers} worker(s)")
    code = provenance(run_broker)  # the code that runs, before anything can change it
    try:
        outcome = run_experiment(
            site.path,
            specs,
            workers=workers,
            broker=broker,
            progress=progress_line(),
            scheduler=args.scheduler,
            run_broker=run_broker,
            record=args.record,
        )
    except ClusterError as exc:
        raise CliError(f"--scheduler {args.scheduler}: {exc}") from None
    except MosquittoError as exc:
        raise CliError(f"--run-broker mosquitto: {exc}") from None
    reproduce = (
        f"wsnav experiment --site {args.site} --runs {args.runs} --seed {args.seed} "
        f"--configs {','.join(configs)} --out {args.out}"
        + (f" --run-broker {run_broker}" if run_broker != "amqtt" else "")
    )
    header = report_header(
        site.name, configs, args.runs, args.seed, workers, where, outcome, reproduce, run_broker, code
    )
    report = _report(site, outcome, args.out, header, compare)
    t = outcome.table
    print(
        f"{len(t)} runs, {int(t['success'].to_numpy(dtype=bool).sum())} successful, "
        f"{int(t['collisions'].to_numpy(dtype=np.int64).sum())} collisions; "
        f"{outcome.wall_s:.0f} s wall for {outcome.simulated_s:.0f} s simulated "
        f"({outcome.simulated_s / outcome.wall_s:.0f}x real time)"
    )
    print(f"wrote {report} and the table {args.out / 'runs.csv'}")
    if args.record is not None:
        print(f"wrote {len(specs)} run records (MCAP) to {args.record}")
    if args.pictures is not None:
        pictures = write_run_pictures(site, outcome, args.pictures)
        print(f"wrote {pictures} run pictures to {args.pictures}")
    return 0


def _report(
    site: Site, outcome: Outcome, out: Path, header: str, compare: tuple[pd.DataFrame, str] | None
) -> Path:
    try:
        return write_outputs(site, outcome, out, header, compare)
    except ReportError as exc:
        raise CliError(str(exc)) from None


def experiment_on_ros(args: argparse.Namespace, compare: tuple[pd.DataFrame, str] | None) -> int:
    """`--backend ros`: the same plan, one run at a time, on move_base (wsnav.ros_experiment); refused in one
    line where move_base or ROS is not installed, or with an option only the default backend has."""
    from wsnav.ros_bridge.ros_env import require_rospy
    from wsnav.ros_experiment import BACKEND_LINE, MOVE_BASE_CMD, move_base_argv, run_on_ros

    for given, name in (
        (args.broker, "--broker"),
        (args.scheduler, "--scheduler"),
        (args.run_broker, "--run-broker"),
        (args.record, "--record"),
    ):
        if given is not None:
            raise CliError(f"{name} goes with the simulated backend, not --backend ros")
    cmd = args.move_base_cmd or MOVE_BASE_CMD
    move_base = move_base_argv(cmd)
    require_rospy()
    configs = _configs(args)
    site = _site(args.site)
    _writable(args.out)
    if args.pictures is not None:
        _writable(args.pictures)
    specs = _specs(site, configs, args.runs, args.seed)
    print(
        f"{len(specs)} runs ({args.runs} per route and configuration) on move_base (`{cmd}`), one at a time"
    )
    code = provenance("amqtt")
    start = time.monotonic()
    done = run_on_ros(site, specs, move_base, progress_line())
    outcome = collect(done, time.monotonic() - start)
    reproduce = (
        f"wsnav experiment --backend ros --move-base-cmd '{cmd}' --site {args.site} --runs {args.runs} "
        f"--seed {args.seed} --configs {','.join(configs)} --out {args.out}"
    )
    where = "an embedded amqtt broker of each run's own"
    backend = BACKEND_LINE.format(cmd=cmd)
    header = report_header(
        site.name, configs, args.runs, args.seed, 1, where, outcome, reproduce, "amqtt", code, backend
    )
    report = _report(site, outcome, args.out, header, compare)
    t = outcome.table
    print(
        f"{len(t)} runs on move_base, {int(t['success'].to_numpy(dtype=bool).sum())} arrived, "
        f"{int(t['collisions'].to_numpy(dtype=np.int64).sum())} collisions; {outcome.wall_s:.0f} s wall"
    )
    print(f"wrote {report} and the table {args.out / 'runs.csv'}")
    if args.pictures is not None:
        print(f"wrote {write_run_pictures(site, outcome, args.pictures)} run pictures to {args.pictures}")
    return 0


def _recordable(folder: Path) -> None:
    """The record folder exists and the mcap package is there, before any run starts."""
    from wsnav.experiments.run_record import RecordError, require_mcap

    _writable(folder)
    try:
        require_mcap()
    except RecordError as exc:
        raise CliError(f"--record: {exc}") from None


def demo(args: argparse.Namespace) -> int:
    site = _site(args.site)
    _writable(args.out)
    specs = _specs(site, ["full"], 1, args.seed)
    outcome = run_experiment(site.path, specs, workers=1, progress=progress_line())
    t = outcome.table
    t.to_csv(args.out / "runs.csv", index=False)
    print("| route | blocked zone | arrived | distance (m) | time (s) | replans | collisions |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in t.to_dict("records"):
        print(
            f"| {r['route']} | {r['blocked']} | {'yes' if r['success'] else 'no'} | {float(r['distance_m']):.1f} "
            f"| {float(r['time_s']):.1f} | {r['replans']} | {r['collisions']} |"
        )
    blocked = sorted({z for s in specs for z in s.blocked})
    paths = {
        f"{route} ({s.blocked_label} blocked)": outcome.trajectories[(route, "full")]
        for s in specs
        for route in [s.route]
    }
    png = args.out / "demo.png"
    paths_figure(site, paths, blocked, "wsnav demo: the `full` robot on each route", png)
    print(
        f"{outcome.simulated_s:.0f} s simulated in {outcome.wall_s:.0f} s; wrote {png} and {args.out / 'runs.csv'}"
    )
    return 0
