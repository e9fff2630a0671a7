"""The broker a benchmark measures through, with the full security model on fresh credentials in a folder the
benchmark owns (so a run never touches the repo's sites): `wsnav broker run` (amqtt) or Mosquitto from
`wsnav broker mosquitto-config`, each as its own process, optionally pinned to CPUs (`taskset`)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from wsnav.broker.amqtt.embedded import BrokerProcess
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.process import MosquittoError, mosquitto_process
from wsnav.schemas.site import load_site
from wsnav.schemas.site_file import SiteFile

BROKERS = ("amqtt", "mosquitto")


@dataclass(frozen=True)
class RunningBroker:
    """Where a benchmark's broker listens, and its process id (for its CPU time)."""

    host: str
    port: int
    pid: int


def fresh_broker(site: Path, root: Path, extra_args: list[str] | None = None) -> BrokerProcess:
    """Credentials for `site` written to root/creds and a broker on them (data in root/amqtt-data); not started:
    use it as a context manager. Its `credentials_dir` is where the benchmark's clients load theirs from;
    `extra_args` go to `wsnav broker run`."""
    creds = root / "creds"
    write_credentials(load_site(site).spec, creds)
    return BrokerProcess(site, creds, data_dir=root / "amqtt-data", extra_args=extra_args)


def _pinned(
    args: list[str], cpus: str | None, nice: int | None = None, new_session: bool = True
) -> list[str]:
    """`taskset -c CPUS` in front: the process and every thread it starts run on those CPUs only. With `nice`:
    in a session of its own (`setsid`, unless the caller starts it in one: `new_session=False`), whose
    scheduling group (Linux autogroup) gets nice N: a negative N (root only) lets the broker take its core back
    from other jobs on a shared machine, as if the core were its own (the Pi's broker does not share its core
    with a dozen benchmark jobs). A plain `nice` would not do: each session is its own group, and the groups
    share the CPU equally whatever their processes' nice. Every step execs, so the broker keeps the pid."""
    placed = args if cpus is None else ["taskset", "-c", cpus, *args]
    if nice is None:
        return placed
    grouped = ["sh", "-c", f'echo {int(nice)} > /proc/self/autogroup && exec "$@"', "sh", *placed]
    return ["setsid", *grouped] if new_session else grouped


def in_group_of_own(nice: int, module: str, argv: list[str] | None) -> int | None:
    """Put this benchmark's process (and the processes it starts) in a scheduling group of its own with `nice`, as
    `_pinned` does for a broker: None once it is in one, else the exit code of `python -m module argv` run again
    in a new session (`setsid`), which does it. At a site the robot and the nodes are machines of their own; on
    this shared machine other jobs kept a benchmark's subscriber off the CPU for 70-400 ms at a time."""
    if os.getsid(0) == os.getpid():
        with open("/proc/self/autogroup", "w") as group:
            group.write(str(nice))
        return None
    args = sys.argv[1:] if argv is None else argv
    return subprocess.call(["setsid", "-w", sys.executable, "-m", module, *args])


@contextlib.contextmanager
def mosquitto_broker(
    spec: SiteFile, creds: Path, root: Path, cpus: str | None = None, nice: int | None = None
) -> Iterator[RunningBroker]:
    """Mosquitto on a free loopback port from the site's own configuration (`wsnav broker mosquitto-config`:
    the same passwords and per-id ACL as amqtt's), its files and persistence under `root`."""
    try:
        with mosquitto_process(spec, creds, root, prefix=_pinned([], cpus, nice)) as running:
            yield RunningBroker(running.host, running.port, running.pid)
    except MosquittoError as exc:
        raise SystemExit(str(exc)) from None


@contextlib.contextmanager
def amqtt_broker(
    site: Path,
    creds: Path,
    cpus: str | None = None,
    extra_args: list[str] | None = None,
    nice: int | None = None,
) -> Iterator[RunningBroker]:
    """`wsnav broker run` (retained messages in memory, no --data) on a free loopback port."""
    broker = BrokerProcess(site, creds, extra_args=extra_args)
    broker.args = _pinned(broker.args, cpus, nice, new_session=False)  # (it starts one)
    with broker:
        assert broker.proc is not None
        yield RunningBroker(broker.host, broker.port, broker.proc.pid)


@contextlib.contextmanager
def site_broker(
    kind: str,
    site: Path,
    creds: Path,
    root: Path,
    cpus: str | None = None,
    amqtt_args: list[str] | None = None,
    nice: int | None = None,
) -> Iterator[RunningBroker]:
    """The broker named `kind` (one of BROKERS) for `site`, on credentials already written to `creds`;
    `amqtt_args` go to `wsnav broker run`; `cpus` and `nice` place it (`_pinned`)."""
    if kind == "mosquitto":
        with mosquitto_broker(load_site(site).spec, creds, root, cpus, nice) as running:
            yield running
    elif kind == "amqtt":
        with amqtt_broker(site, creds, cpus, amqtt_args, nice) as running:
            yield running
    else:
        raise ValueError(f"unknown broker {kind!r} (one of {', '.join(BROKERS)})")
