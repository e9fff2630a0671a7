"""Mosquitto as a child process on a free loopback port, configured from the site (`write_mosquitto_config`).

For callers that need a fresh broker per job (the experiment's runs, the benchmarks): the C broker carries the
messages outside the Python process that drives the run, so it does not compete with the run for the GIL.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.schemas.site_file import SiteFile

START_ATTEMPTS = 3
"""A free port found may be taken by someone else before Mosquitto binds it: try again on another."""


class MosquittoError(RuntimeError):
    """Mosquitto is missing or did not start (one line for the user)."""


@dataclass(frozen=True)
class RunningMosquitto:
    host: str
    port: int
    pid: int


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def mosquitto_process(
    spec: SiteFile,
    credentials_dir: Path,
    root: Path,
    *,
    host: str = "127.0.0.1",
    prefix: Sequence[str] = (),
    start_timeout_s: float = 30.0,
) -> Iterator[RunningMosquitto]:
    """Mosquitto for `spec`'s ids (passwords from `credentials_dir`), its config and persistence under `root`
    (which must be new: a snapshot left there would bring back an earlier broker's retained messages).
    `prefix` goes in front of the command (e.g. `taskset -c 1`)."""
    exe = shutil.which("mosquitto")
    if exe is None:
        raise MosquittoError("mosquitto is not installed (Debian: apt-get install mosquitto)")
    data = root / "mq-data"
    data.mkdir(parents=True, exist_ok=True)
    user = "root" if os.geteuid() == 0 else None
    for _ in range(START_ATTEMPTS):
        port = free_port(host)
        options = MosquittoOptions(bind=(host, port), data_dir=data, user=user)
        write_mosquitto_config(spec, credentials_dir, root / "mq", options)
        proc = subprocess.Popen(
            [*prefix, exe, "-c", str(root / "mq" / CONF)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            if _listening(proc, host, port, start_timeout_s):
                yield RunningMosquitto(host, port, proc.pid)
                return
        finally:
            proc.terminate()
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    raise MosquittoError(f"mosquitto did not start on {host} ({START_ATTEMPTS} attempts)")


def _listening(proc: subprocess.Popen[bytes], host: str, port: int, timeout_s: float) -> bool:
    """True once the port accepts connections; False if the process exits first (the port was taken)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            socket.create_connection((host, port), timeout=1).close()
            return True
        except OSError:
            if proc.poll() is not None:
                return False
            time.sleep(0.01)
    raise MosquittoError(f"mosquitto did not listen on {host}:{port} within {timeout_s:.0f} s")
