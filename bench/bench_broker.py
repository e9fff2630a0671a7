"""The broker a benchmark measures through, with the full security model on fresh credentials in a folder the
benchmark owns (so a run never touches the repo's sites): `wsnav broker run` (amqtt) or Mosquitto from
`wsnav broker mosquitto-config`, each as its own process, optionally pinned to CPUs (`taskset`)."""

from __future__ import annotations

import contextlib
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


def fresh_broker(site: Path, root: Path) -> BrokerProcess:
    """Credentials for `site` written to root/creds and a broker on them (data in root/amqtt-data); not started:
    use it as a context manager. Its `credentials_dir` is where the benchmark's clients load theirs from."""
    creds = root / "creds"
    write_credentials(load_site(site).spec, creds)
    return BrokerProcess(site, creds, data_dir=root / "amqtt-data")


def _pinned(args: list[str], cpus: str | None) -> list[str]:
    """`taskset -c CPUS` in front: the process and every thread it starts run on those CPUs only."""
    return args if cpus is None else ["taskset", "-c", cpus, *args]


@contextlib.contextmanager
def mosquitto_broker(
    spec: SiteFile, creds: Path, root: Path, cpus: str | None = None
) -> Iterator[RunningBroker]:
    """Mosquitto on a free loopback port from the site's own configuration (`wsnav broker mosquitto-config`:
    the same passwords and per-id ACL as amqtt's), its files and persistence under `root`."""
    try:
        with mosquitto_process(spec, creds, root, prefix=_pinned([], cpus)) as running:
            yield RunningBroker(running.host, running.port, running.pid)
    except MosquittoError as exc:
        raise SystemExit(str(exc)) from None


@contextlib.contextmanager
def amqtt_broker(
    site: Path, creds: Path, cpus: str | None = None, extra_args: list[str] | None = None
) -> Iterator[RunningBroker]:
    """`wsnav broker run` (retained messages in memory, no --data) on a free loopback port."""
    broker = BrokerProcess(site, creds, extra_args=extra_args)
    broker.args = _pinned(broker.args, cpus)
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
) -> Iterator[RunningBroker]:
    """The broker named `kind` (one of BROKERS) for `site`, on credentials already written to `creds`;
    `amqtt_args` go to `wsnav broker run`."""
    if kind == "mosquitto":
        with mosquitto_broker(load_site(site).spec, creds, root, cpus) as running:
            yield running
    elif kind == "amqtt":
        with amqtt_broker(site, creds, cpus, amqtt_args) as running:
            yield running
    else:
        raise ValueError(f"unknown broker {kind!r} (one of {', '.join(BROKERS)})")
