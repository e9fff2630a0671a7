"""The experiment on a real Dask cluster (a `dask scheduler` and two `dask worker` processes on loopback): the
same table as the local pool for the same seed, a worker killed mid-run costs nothing, and a scheduler that
cannot be used is one line."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, cast

import pandas as pd
import pytest

from tests.conftest import SCHOOL
from tests.dask_fixtures import DaskCluster, dask_cluster, free_port
from wsnav.cli import main
from wsnav.experiments.run_plan import plan_runs
from wsnav.experiments.runner import Outcome, run_experiment
from wsnav.experiments.single_run import COLUMNS, NONDETERMINISTIC
from wsnav.schemas.site import load_site

if TYPE_CHECKING:
    from distributed import Worker

__all__ = ["dask_cluster"]

DETERMINISTIC = [c for c in COLUMNS if c not in NONDETERMINISTIC]


def _rows(table: pd.DataFrame) -> list[list[object]]:
    """The deterministic columns; an empty cell (a run without recoveries has no log) reads as "" (NaN != NaN)."""
    cells = table[DETERMINISTIC].astype(object)
    return cells.where(cells.notna(), "").to_numpy().tolist()


def test_the_cluster_gives_the_local_pools_table_for_the_same_seed(
    dask_cluster: DaskCluster, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dask_cluster.start(workers=2)
    out = tmp_path / "out"
    argv = ["experiment", "--site", str(SCHOOL), "--runs", "2", "--seed", "3", "--configs", "full"]
    assert main([*argv, "--scheduler", dask_cluster.address, "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert f"on the Dask cluster at {dask_cluster.address}" in printed.out
    assert "6/6 runs" in printed.err  # the same progress line as the local pool
    on_cluster = pd.read_csv(out / "runs.csv")
    site = load_site(SCHOOL)
    local = run_experiment(site.path, plan_runs(site.spec, ["full"], 2, 3), workers=2).table
    local.to_csv(tmp_path / "local.csv", index=False)
    assert _rows(on_cluster) == _rows(pd.read_csv(tmp_path / "local.csv"))
    assert len(on_cluster) == 6 and bool(on_cluster["success"].all())


def _executing(dask_worker: Worker) -> list[str]:
    """The keys a worker is running now (Client.run passes the worker to an argument of this name)."""
    return [str(key) for key, task in dask_worker.state.tasks.items() if task.state == "executing"]


def test_a_worker_killed_mid_run_has_its_run_retried_elsewhere_and_counted_once(
    dask_cluster: DaskCluster,
) -> None:
    """The hardest case: the only worker dies in the middle of a run, with everything it held (the shipped site
    too), and a new worker joins later."""
    from distributed import Client

    (first,) = dask_cluster.start(workers=1).workers
    site = load_site(SCHOOL)
    specs = plan_runs(site.spec, ["default"], 1, 3)  # default: 10 s or more a run
    arrived: list[int] = []
    outcome: list[Outcome] = []
    failed: list[BaseException] = []

    def experiment() -> None:
        try:
            outcome.append(
                run_experiment(
                    site.path,
                    specs,
                    workers=2,
                    scheduler=dask_cluster.address,
                    progress=lambda done, total: arrived.append(done),
                )
            )
        except BaseException as exc:
            failed.append(exc)

    runner = threading.Thread(target=experiment, daemon=True)
    runner.start()
    with Client(dask_cluster.address, timeout=10, set_as_default=False) as client:
        deadline = time.monotonic() + 60
        running: list[str] = []
        while not running and time.monotonic() < deadline:
            running = [
                k for keys in cast("dict[str, list[str]]", client.run(_executing)).values() for k in keys
            ]
            time.sleep(0.2)
        assert running, "no run started on the cluster"
        time.sleep(1)  # well into the run: mid-run, not before it starts
        assert not arrived, "a run finished before the worker could be killed mid-run"
        first.send_signal(signal.SIGKILL)
    assert first.wait(10) == -signal.SIGKILL
    dask_cluster.add_worker()
    runner.join(300)
    assert not runner.is_alive() and not failed, failed
    table = outcome[0].table
    identities = [(r["config"], r["route"], r["run"]) for r in table.to_dict("records")]
    assert sorted(identities) == sorted((s.config, s.route, s.run) for s in specs)  # each run exactly once
    assert arrived == [1, 2, 3]
    # The run the dead worker was in the middle of ran again from scratch on the new worker: its row is the
    # one the run gives on its own.
    interrupted = next(s for s in specs if running[0].endswith(f"-{s.config}-{s.route}-{s.run}"))
    alone = run_experiment(site.path, [interrupted], workers=1).table
    assert [r for r in _rows(table) if r[DETERMINISTIC.index("route")] == interrupted.route] == _rows(alone)


@pytest.mark.parametrize(
    ("address", "message"),
    [
        ("127.0.0.1:8786", "expected tcp://HOST:PORT, got '127.0.0.1:8786'"),
        ("tcp://127.0.0.1", "expected tcp://HOST:PORT"),
        ("http://127.0.0.1:8786", "expected tcp://HOST:PORT"),
        ("tcp://127.0.0.1:99999", "expected tcp://HOST:PORT"),
    ],
)
def test_a_malformed_scheduler_address_is_one_line(
    address: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["experiment", "--runs", "1", "--scheduler", address, "--out", str(tmp_path / "out")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_a_scheduler_that_does_not_answer_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    address = f"tcp://127.0.0.1:{free_port()}"  # nothing listens there
    argv = ["experiment", "--runs", "1", "--scheduler", address, "--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert f"cannot reach the Dask scheduler at {address}" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out" / "runs.csv").exists()


def test_scheduler_and_broker_together_are_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["experiment", "--runs", "1", "--scheduler", "tcp://127.0.0.1:8786", "--broker", "127.0.0.1:1883"]
    (tmp_path / "robot1.json").write_text("{}")
    assert main([*argv, "--credentials", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--scheduler" in err and "--broker" in err and len(err.splitlines()) == 1
