"""A real Dask cluster on loopback for tests: `dask scheduler` and `dask worker` processes from the venv,
each in its own session so teardown can end it and anything it started."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, cast

import pytest

from tests.conftest import REPO
from wsnav.broker.mosquitto.process import free_port

DASK = Path(sys.executable).parent / "dask"


class DaskCluster:
    """One scheduler and single-threaded workers without nannies (a killed worker stays dead, so its runs have
    to move to another)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.address = f"tcp://127.0.0.1:{free_port()}"
        self.scheduler: subprocess.Popen[bytes] | None = None
        self.workers: list[subprocess.Popen[bytes]] = []
        self._logs: list[IO[bytes]] = []

    def _spawn(self, name: str, args: list[str]) -> subprocess.Popen[bytes]:
        log = (self.tmp / f"{name}.log").open("wb")
        self._logs.append(log)
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        return subprocess.Popen(
            [str(DASK), *args],
            cwd=REPO,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def start(self, workers: int) -> DaskCluster:
        port = self.address.rsplit(":", 1)[1]
        self.scheduler = self._spawn(
            "scheduler",
            ["scheduler", "--host", "127.0.0.1", "--port", port, "--dashboard-address", "127.0.0.1:0"],
        )
        for _ in range(workers):
            self.add_worker(wait=False)
        self.wait_for_workers(workers)
        return self

    def add_worker(self, wait: bool = True) -> subprocess.Popen[bytes]:
        i = len(self.workers)
        worker = self._spawn(
            f"worker{i}",
            [
                "worker",
                self.address,
                "--nthreads",
                "1",
                "--no-nanny",
                "--no-dashboard",
                "--host",
                "127.0.0.1",
                "--name",
                f"w{i}",
                "--local-directory",
                str(self.tmp / f"w{i}"),
                "--death-timeout",
                "60",
            ],
        )
        self.workers.append(worker)
        if wait:
            self.wait_for_workers(sum(w.poll() is None for w in self.workers))
        return worker

    def worker_pids(self) -> dict[str, int]:
        """Worker address -> its process id, as each worker says."""
        from distributed import Client

        with Client(self.address, timeout=10, set_as_default=False) as client:
            return cast("dict[str, int]", client.run(os.getpid))

    def wait_for_workers(self, n: int, timeout_s: float = 90.0) -> None:
        from distributed import Client

        deadline = time.monotonic() + timeout_s
        while True:
            try:
                with Client(self.address, timeout=10, set_as_default=False) as client:
                    client.wait_for_workers(n, timeout=max(deadline - time.monotonic(), 1.0))
                    return
            except (OSError, TimeoutError):
                if time.monotonic() > deadline:
                    raise AssertionError(f"the cluster did not get {n} workers: {self.logs()}") from None
                time.sleep(0.5)

    def logs(self) -> str:
        return "\n".join(
            f"--- {p.name}\n{p.read_text(errors='replace')[-3000:]}" for p in sorted(self.tmp.glob("*.log"))
        )

    def stop(self) -> None:
        for proc in [*self.workers, self.scheduler]:
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in [*self.workers, self.scheduler]:
            if proc is None:
                continue
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(15)
        for log in self._logs:
            log.close()


@pytest.fixture
def dask_cluster(tmp_path: Path) -> Iterator[DaskCluster]:
    """A scheduler on 127.0.0.1 (workers as the test starts them), stopped with everything it started after
    the test."""
    cluster = DaskCluster(tmp_path / "dask")
    cluster.tmp.mkdir()
    try:
        yield cluster
    finally:
        cluster.stop()
