"""The experiment's runs as tasks on an existing Dask distributed cluster (`wsnav experiment --scheduler`).

Each task is self-contained: it gets the parsed site (shipped with the tasks, so no worker needs the site
directory) and one RunSpec, starts its own embedded broker on the worker's loopback, runs, and returns the row. Runs on one worker therefore never see each other's topics, and a run retried on another worker after
its first worker died starts from the same state. Results are keyed by the run's identity, so a run Dask
retried is counted once.
"""

from __future__ import annotations

import logging
import threading
import uuid
from collections.abc import Callable
from typing import TYPE_CHECKING

from wsnav.experiments.run_plan import RunSpec
from wsnav.experiments.single_run import RunResult
from wsnav.experiments.worker import quiet_worker_logs, run_with_own_broker
from wsnav.schemas.site import Site

if TYPE_CHECKING:
    from distributed import Client

CONNECT_TIMEOUT_S = 10.0
WORKERS_TIMEOUT_S = 10.0

RunKey = tuple[str, str, int]
"""(config, route, run): a run's identity in the table."""

_one_run_at_a_time = threading.Lock()
"""A worker started with several threads would otherwise run several runs in one process, mixing their
peak-memory measurements (the process's resident-set peak): runs in one worker process take turns."""


class ClusterError(Exception):
    """The cluster cannot be used or a run failed on it; one line for the user."""


def run_key(spec: RunSpec) -> RunKey:
    return (spec.config, spec.route, spec.run)


def _connect(address: str) -> Client:
    from distributed import Client  # imported here: dask takes a second to load, only a cluster needs it

    logging.getLogger("distributed").setLevel(logging.ERROR)
    try:
        return Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ClusterError(
            f"cannot reach the Dask scheduler at {address} within {CONNECT_TIMEOUT_S:g} s "
            f"(is `dask scheduler` running there and its port open?): {type(exc).__name__}"
        ) from None


def worker_threads(client: Client, address: str) -> int:
    """How many runs the cluster can hold at once; waits a little for a first worker."""
    try:
        client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
    except TimeoutError:
        raise ClusterError(
            f"the Dask scheduler at {address} has no workers "
            f"(start `dask worker {address} --nthreads 1` on each host)"
        ) from None
    workers = client.scheduler_info(n_workers=-1)["workers"].values()
    return sum(int(w["nthreads"]) for w in workers)


def cluster_size(address: str) -> int:
    """Check that the scheduler answers and has workers, before anything runs; their threads in all."""
    with _connect(address) as client:
        return worker_threads(client, address)


def _task(site: Site, spec: RunSpec, run_broker: str) -> tuple[RunSpec, RunResult]:
    """One run on a Dask worker, on its own broker (started on the worker's host)."""
    with _one_run_at_a_time:
        quiet_worker_logs()
        return run_with_own_broker(site, spec, run_broker)


def _the_site(site: Site) -> Site:
    """The site as a task of its own rather than scattered data: the scheduler keeps its input, so when every
    worker holding it has died it is computed again (scattered data lost with its holders is gone, and the runs
    waiting on it fail)."""
    return site


def _name(spec: RunSpec) -> str:
    return f"{spec.config} {spec.route} run {spec.run}"


def run_on_cluster(
    address: str,
    site: Site,
    specs: list[RunSpec],
    on_result: Callable[[int], None] | None = None,
    run_broker: str = "amqtt",
) -> dict[RunKey, tuple[RunSpec, RunResult]]:
    """Every spec as one task, each on its own `run_broker`; results as they arrive (`on_result(done)` after
    each), keyed by run identity."""
    if len({run_key(s) for s in specs}) != len(specs):
        raise ValueError("two specs share a run identity (config, route, run)")
    from distributed import as_completed
    from distributed.scheduler import KilledWorker

    done: dict[RunKey, tuple[RunSpec, RunResult]] = {}
    batch = uuid.uuid4().hex[:12]
    with _connect(address) as client:
        worker_threads(client, address)
        shipped = client.submit(_the_site, site, key=f"wsnav-site-{batch}", pure=False)
        futures = {
            client.submit(
                _task,
                shipped,
                spec,
                run_broker,
                key=f"wsnav-run-{batch}-{spec.config}-{spec.route}-{spec.run}",
                pure=False,
            ): spec
            for spec in specs
        }
        for future in as_completed(futures, loop=client.loop):
            spec = futures[future]
            try:
                got_spec, result = future.result()
            except KilledWorker:
                raise ClusterError(
                    f"{_name(spec)}: Dask gave up after the workers running it died repeatedly "
                    "(out of memory? see the workers' logs)"
                ) from None
            except Exception as exc:
                raise ClusterError(
                    f"{_name(spec)} failed on the cluster: {type(exc).__name__}: {exc}"
                ) from None
            done.setdefault(run_key(got_spec), (got_spec, result))
            if on_result is not None:
                on_result(len(done))
    return done
