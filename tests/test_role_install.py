"""A small install per role: `pip install wsnav[broker]` into a fresh environment (pip from its index and cache, as a
Raspberry Pi would) holds no numpy, and its `wsnav broker run` serves a node. Every install pulled the whole
research environment before (719 MB: llvmlite, scipy, pandas, numba, matplotlib) where a Pi needs amqtt, paho-mqtt
and pydantic."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.broker_fixtures import Endpoint, client
from tests.conftest import REPO
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerProcess
from wsnav.broker.credentials import write_credentials
from wsnav.schemas import topics
from wsnav.schemas.messages import ZoneState
from wsnav.schemas.site import load_site

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]  # a fresh venv and pip on a loaded machine

PIN = ["-c", str(REPO / "constraints.txt")]
BUILD_LEFTOVERS = (
    ".git",
    ".venv",
    "build",
    "out",
    "*.egg-info",
    "__pycache__",
    ".pytest_cache",
    ".ruff_cache",
)


def test_the_broker_role_installs_into_a_fresh_environment_without_numpy_and_serves_a_node(
    tmp_path: Path,
) -> None:
    # From a copy: pip builds in the source tree (build/), where another build or a stale file would mix in.
    source = tmp_path / "src"
    shutil.copytree(REPO, source, symlinks=True, ignore=shutil.ignore_patterns(*BUILD_LEFTOVERS))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    install = subprocess.run(
        [python, "-m", "pip", "install", "-q", "--disable-pip-version-check", *PIN, f"{source}[broker]"],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert install.returncode == 0, install.stderr[-3000:]
    for heavy in ("numpy", "scipy", "numba", "pandas", "matplotlib"):
        probe = subprocess.run([python, "-I", "-c", f"import {heavy}"], capture_output=True, timeout=60)
        assert probe.returncode != 0, f"the broker role installed {heavy}"

    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    broker = BrokerProcess(site, creds)
    # The installed wsnav, not this checkout: -I leaves the working directory off sys.path.
    broker.args[:1] = [str(python), "-I"]
    with broker:
        ep = Endpoint("amqtt", broker.host, broker.port, creds)
        topic = topics.zone_state(load_site(site).name, "z1", "n1")
        payload = ZoneState(zone="z1", node="n1", state="blocked", seq=1).to_payload()
        with client(ep, "operator", "watch") as watch, client(ep, "n1") as n1:
            assert watch.subscribe(topic) == [1]
            n1.publish(topic, payload, retain=True)
            assert watch.wait_for(topic, payload).payload == payload
    check = subprocess.run(
        [venv / "bin" / "wsnav", "site", "check", site],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert check.returncode == 2 and check.stderr.count("\n") == 1, check.stderr
    assert "needs numpy" in check.stderr and "wsnav[robot]" in check.stderr, check.stderr
    files = subprocess.run(
        [python, "-I", "-c", "import wsnav.broker.amqtt.server as s; print(s.__file__)"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert str(venv) in files.stdout, files.stdout + files.stderr
