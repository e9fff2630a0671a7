"""The broker a benchmark measures through: `wsnav broker run` as its own process, with the full security model,
on fresh credentials for the site in a folder the benchmark owns (so a run never touches the repo's sites)."""

from __future__ import annotations

from pathlib import Path

from broker.credentials import write_credentials
from broker.embedded import BrokerProcess
from schemas.site import load_site


def fresh_broker(site: Path, root: Path) -> BrokerProcess:
    """Credentials for `site` written to root/creds and a broker on them (data in root/amqtt-data); not started:
    use it as a context manager. Its `credentials_dir` is where the benchmark's clients load theirs from."""
    creds = root / "creds"
    write_credentials(load_site(site).spec, creds)
    return BrokerProcess(site, creds, data_dir=root / "amqtt-data")
