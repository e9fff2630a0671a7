"""What runs inside a worker process (the local pool's or a Dask worker's): its set-up, and one run on a broker
of its own. The runner (experiments.runner) and the cluster (experiments.cluster) both dispatch to it."""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.process import mosquitto_process
from wsnav.experiments.run_plan import RunSpec
from wsnav.experiments.single_run import BrokerAt, RunResult, run_once
from wsnav.schemas.site import Site, load_site
from wsnav.schemas.site_file import SiteFile

RUN_BROKERS = ("amqtt", "mosquitto")
"""The broker each run starts for itself: amqtt (the Pi's broker) in the worker's process, or a Mosquitto
process beside it, which takes the messages off the worker's GIL (same rows, 13-17% less wall time a run)."""

_site: Site | None = None
_site_dir: Path | None = None
_broker: BrokerAt | None = None
_run_broker = "amqtt"
_record: Path | None = None


def quiet_worker_logs() -> None:
    """Dropped retained messages of the previous run and the broker's chatter about clients that the last run
    closed are expected: neither is worth a line on the console."""
    logging.getLogger("amqtt").setLevel(logging.CRITICAL)
    for component in ("wsnav.robot_agent", "wsnav.navigation", "wsnav.zones"):
        logging.getLogger(component).setLevel(logging.ERROR)


def init_worker(
    site_dir: Path, broker: BrokerAt | None, run_broker: str = "amqtt", record: Path | None = None
) -> None:
    """`record`: a folder for each run's MCAP record, or None."""
    global _site, _site_dir, _broker, _run_broker, _record
    quiet_worker_logs()
    _site = load_site(site_dir)
    _site_dir = site_dir
    _broker = broker
    _run_broker = run_broker
    _record = record


def work(spec: RunSpec) -> tuple[RunSpec, RunResult]:
    """One run; without an external broker, on a fresh embedded one, so no retained message of an earlier
    run reaches this one and the same seed gives the same row whatever ran before in this worker."""
    assert _site is not None and _site_dir is not None
    if _broker is not None:
        return spec, run_once(_site, spec, _broker, _record)
    return run_with_own_broker(_site, spec, _run_broker, _record)


_credentials: dict[str, tuple[SiteFile, tempfile.TemporaryDirectory[str]]] = {}


def _credentials_of(site: Site) -> Path:
    """The site's credentials, written once per worker process: a run's broker is fresh (no retained message
    of an earlier run), its passwords need not be (hashing them anew cost 75 ms a run)."""
    known = _credentials.get(site.name)
    if known is None or known[0] != site.spec:
        known = (site.spec, tempfile.TemporaryDirectory(prefix="wsnav-credentials-"))
        write_credentials(site.spec, Path(known[1].name))
        _credentials[site.name] = known
    return Path(known[1].name)


def run_with_own_broker(
    site: Site, spec: RunSpec, kind: str = "amqtt", record: Path | None = None
) -> tuple[RunSpec, RunResult]:
    """One run on a fresh broker of its own (`kind`, one of RUN_BROKERS; credentials in a temporary folder):
    needs the parsed site only. `record`: a folder for the run's MCAP record, or None."""
    if kind == "mosquitto":
        creds = _credentials_of(site)
        with (
            tempfile.TemporaryDirectory(prefix="wsnav-run-") as tmp,
            mosquitto_process(site.spec, creds, Path(tmp)) as mq,
        ):
            return spec, run_once(site, spec, BrokerAt(mq.host, mq.port, creds), record)
    with BrokerThread(site) as own:
        return spec, run_once(site, spec, BrokerAt(own.host, own.port, own.credentials_dir), record)
