"""The whole experiment: every planned run over a pool of worker processes (or as tasks on a Dask cluster:
experiments/cluster.py), each run on its own embedded broker (runs cannot see each other's topics or clash on
client ids: amqtt in the worker's process, or Mosquitto beside it), a progress line on stderr, the runs table, the path figures of run 0 and the report.
"""

from __future__ import annotations

import multiprocessing
import os
import platform
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from wsnav.experiments.report import BACKEND_LINE, paths_figure, write_report
from wsnav.experiments.run_plan import RunSpec
from wsnav.experiments.run_record import record_name
from wsnav.experiments.single_run import COLUMNS, DT, BrokerAt, RunResult
from wsnav.experiments.worker import init_worker, work
from wsnav.schemas.site import Site, load_site

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class Outcome:
    table: pd.DataFrame
    trajectories: dict[tuple[str, str], NDArray[np.float64]]
    """(route, config) -> run 0's driven path."""
    wall_s: float
    every_path: dict[tuple[str, str, int], NDArray[np.float64]] = field(default_factory=dict)
    """(config, route, run) -> that run's driven path, for a picture per run."""

    @property
    def simulated_s(self) -> float:
        return float(self.table["time_s"].to_numpy(dtype=np.float64).sum())


def run_experiment(
    site_dir: Path,
    specs: list[RunSpec],
    *,
    workers: int,
    broker: BrokerAt | None = None,
    progress: Progress | None = None,
    scheduler: str | None = None,
    run_broker: str = "amqtt",
    record: Path | None = None,
) -> Outcome:
    """Run `specs` (with an external `broker`: in this process, one after the other; with a `scheduler`
    address: as tasks on that Dask cluster, `workers` unused); otherwise each run on its own `run_broker`.
    `record`: a folder for one MCAP record per run (not on a cluster: its workers' disks are not this one)."""
    if record is not None and scheduler is not None:
        raise ValueError("runs on a cluster are not recorded")
    start = time.monotonic()
    done: list[tuple[RunSpec, RunResult]] = []
    if scheduler is not None:
        from wsnav.experiments.cluster import run_on_cluster  # dask loads only when a cluster is used

        def arrived(n: int) -> None:
            if progress is not None:
                progress(n, len(specs))

        done = list(run_on_cluster(scheduler, load_site(site_dir), specs, arrived, run_broker).values())
    elif broker is not None or workers <= 1:
        init_worker(site_dir, broker, run_broker, record)
        for spec in specs:
            done.append(work(spec))
            if progress is not None:
                progress(len(done), len(specs))
    else:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(
            workers, ctx, initializer=init_worker, initargs=(site_dir, None, run_broker, record)
        ) as pool:
            futures = [pool.submit(work, spec) for spec in specs]
            for future in as_completed(futures):
                done.append(future.result())
                if progress is not None:
                    progress(len(done), len(specs))
    return collect(done, time.monotonic() - start)


def collect(done: list[tuple[RunSpec, RunResult]], wall_s: float) -> Outcome:
    """The table and paths of finished runs, whatever ran them (this pool, a cluster, the ROS backend)."""
    done = sorted(done, key=lambda d: (d[0].config, d[0].route, d[0].run))
    table = pd.DataFrame([r.row for _, r in done], columns=list(COLUMNS))
    paths = {(s.route, s.config): r.trajectory for s, r in done if s.run == 0}
    every = {(s.config, s.route, s.run): r.trajectory for s, r in done}
    return Outcome(table, paths, wall_s, every)


def progress_line(started: float | None = None) -> Progress:
    """`[#####.....] 37/300 runs, 1m12s` on stderr, rewritten in place."""
    t0 = time.monotonic() if started is None else started

    def show(done: int, total: int) -> None:
        width = 30
        filled = width * done // max(total, 1)
        secs = int(time.monotonic() - t0)
        end = "\n" if done >= total else ""
        print(
            f"\r[{'#' * filled}{'.' * (width - filled)}] {done}/{total} runs, {secs // 60}m{secs % 60:02d}s",
            end=end,
            file=sys.stderr,
            flush=True,
        )

    return show


def report_header(
    site: str,
    configs: list[str],
    runs: int,
    seed: int,
    workers: int,
    where: str,
    outcome: Outcome,
    reproduce: str,
    run_broker: str | None = None,
    code: str | None = None,
    backend: str | None = None,
) -> str:
    """The report's opening: what ran, how, on what machine, how fast, the code (`code`: `provenance()` taken
    as the runs started; now if not given) and the command that reproduces it. `backend`: the ROS backend's
    line (None: wsnav's navigator in lock step, the default backend)."""
    o = outcome
    how = (
        [
            f"{BACKEND_LINE}{backend}.",
            f"- Messages through {where}; emulated nodes with their own credentials.",
        ]
        if backend is not None
        else [
            f"{BACKEND_LINE}simulated (wsnav's navigator on the simulated TurtleBot3, in lock step).",
            f"- Messages through {where}; emulated nodes with their own credentials (zone simulator), the agent "
            f"on robot1's connection, a simulated TurtleBot3; lock-step simulated time, {DT:g} s steps.",
        ]
    )
    return "\n".join(
        [
            f"# Experiment: {', '.join(configs)} on site {site}",
            "",
            f"- {runs} runs per route and configuration, base seed {seed}; run i of a route blocks the "
            "same raffled zones under every configuration (paired).",
            *how,
            "- The obstacle is placed when the route starts and cleared when the robot stops.",
            "- Configurations take turns run by run (run i of a route under each, then run i+1), so a change in "
            "the machine's load falls on every configuration alike.",
            f"- Wall time {o.wall_s:.0f} s on {workers} worker(s) ({os.cpu_count()} cores, "
            f"{platform.processor() or platform.machine()}, load {os.getloadavg()[0]:.1f} at the end) for "
            f"{o.simulated_s:.0f} s simulated: {o.simulated_s / max(o.wall_s, 1e-9):.0f}x real time.",
            f"- Code: {code or provenance(run_broker)}.",
            f"- Reproduce: `{reproduce}`",
        ]
    )


REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("numpy", "scipy", "pandas", "numba", "pyastar2d", "amqtt", "paho-mqtt", "pydantic", "matplotlib")
"""The libraries whose versions can change a run's result or its speed, named in the report."""


def _git(*args: str) -> str | None:
    git = shutil.which("git")
    if git is None:
        return None
    try:
        done = subprocess.run([git, "-C", str(REPO), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def provenance(run_broker: str | None) -> str:
    """The code's commit (with `+ local changes` when the work tree differs from it), Python and the
    dependencies' versions, and Mosquitto's when the runs used it: what a reader needs to rerun the same."""
    commit = _git("rev-parse", "--short=12", "HEAD")
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    code = "an unknown commit (not a git checkout)" if commit is None else f"commit {commit}"
    if commit is not None and dirty:
        code += " + local changes"
    versions = []
    for name in PACKAGES:
        try:
            versions.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            continue
    if run_broker == "mosquitto" and (mosquitto := shutil.which("mosquitto")) is not None:
        try:
            first = subprocess.run(
                [mosquitto, "-h"], capture_output=True, text=True, timeout=10
            ).stdout.splitlines()
            versions.append(first[0].strip() if first else "mosquitto (version unknown)")
        except (OSError, subprocess.SubprocessError):
            versions.append("mosquitto (version unknown)")
    return f"{code}; Python {platform.python_version()}, {', '.join(versions)}"


def write_run_pictures(site: Site, outcome: Outcome, folder: Path) -> int:
    """One PNG per run in `folder` (named as its MCAP record): its driven path over the map, its blocked zones
    hatched; returns how many."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = {(str(r["config"]), str(r["route"]), int(r["run"])): r for r in outcome.table.to_dict("records")}
    for (config, route, run), xy in sorted(outcome.every_path.items()):
        row = rows[(config, route, run)]
        blocked = str(row["blocked"])
        name = record_name(config, route, run)
        title = f"{config}, {route} run {run}, {blocked} blocked: {row['outcome']} after {float(row['time_s']):.0f} s"
        paths_figure(
            site, {config: xy}, [] if blocked == "none" else blocked.split("+"), title, folder / f"{name}.png"
        )
    return len(outcome.every_path)


def path_png(out: Path, route: str) -> Path:
    return out / f"paths_{route.replace('->', '-')}.png"


def write_outputs(
    site: Site,
    outcome: Outcome,
    out: Path,
    header: str,
    compare: tuple[pd.DataFrame, str] | None = None,
) -> Path:
    """runs.csv, trajectories.npz, one paths_<route>.png per route, and the report (report.md, PNGs)."""
    out.mkdir(parents=True, exist_ok=True)
    outcome.table.to_csv(out / "runs.csv", index=False)
    arrays: dict[str, NDArray[np.float64]] = {f"{r}|{c}": xy for (r, c), xy in outcome.trajectories.items()}
    np.savez_compressed(out / "trajectories.npz", allow_pickle=False, **arrays)
    figures: list[Path] = []
    table = outcome.table
    for route in sorted({r for r, _ in outcome.trajectories}):
        first = table[(table["route"] == route) & (table["run"] == 0)]
        blocked = str(next(iter(first["blocked"]), "none"))
        zones = [] if blocked == "none" else blocked.split("+")
        paths = {c: xy for (r, c), xy in sorted(outcome.trajectories.items()) if r == route}
        png = path_png(out, route)
        paths_figure(site, paths, zones, f"{route}, {blocked} blocked: run 0's paths", png)
        figures.append(png)
    return write_report(table, out, header, figures, compare)
