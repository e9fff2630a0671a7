"""Operator blocks outlive a console restart, on both real brokers: the console keeps them in its store under
`--state-dir`, and when it starts again against a broker that lost them it publishes them again, retained (an
expired block and a lifted one stay gone). The broker here is killed with -9 and restarted on an empty store:
the worst a broker does (Mosquitto lost blocks acknowledged up to 30 s before a kill -9; a full disk, all)."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import pytest

from tests.broker_fixtures import Endpoint, client, wait_listening
from tests.conftest import require_tool
from tests.console_fixtures import start_console, until
from tests.stack_fixtures import SITE, WSNAV, Proc, Stack, make_site, stack_on
from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.schemas import topics
from wsnav.schemas.site import load_site

pytestmark = pytest.mark.timeout(180)

BRIEF_S = 6
"""Long enough for the console to show it on a loaded machine (a command takes 1-2 s there)."""


def start_broker(kind: str, stack: Stack, data: Path) -> Proc:
    """The broker of `kind` on the stack's port, its store in `data` (new: nothing of an earlier run)."""
    data.mkdir(parents=True)
    if kind == "amqtt":
        proc = stack.start(
            "broker",
            [
                *WSNAV,
                "broker",
                "run",
                "--site",
                str(stack.site),
                "--credentials",
                str(stack.creds),
                "--bind",
                stack.broker_addr,
                "--data",
                str(data),
            ],
        )
    else:
        exe = require_tool("mosquitto")
        options = MosquittoOptions(bind=(stack.host, stack.port), data_dir=data, user="root")
        write_mosquitto_config(load_site(stack.site).spec, stack.creds, data / "conf", options)
        proc = stack.start("mosquitto", [exe, "-c", str(data / "conf" / CONF)])
    wait_listening(stack.host, stack.port, proc.popen)
    return proc


def operator(stack: Stack, *args: str) -> None:
    done = subprocess.run(
        [
            *WSNAV,
            *args[:1],
            "--site",
            str(stack.site),
            "--broker",
            stack.broker_addr,
            "--credentials",
            str(stack.creds / "operator.json"),
            *args[1:],
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stdout + done.stderr


def page_blocks(stack: Stack, url: str) -> set[str]:
    import base64
    import urllib.request

    password = json.loads((stack.creds / "operator.json").read_text())["password"]
    req = urllib.request.Request(url + "/api/state")
    req.add_header("Authorization", "Basic " + base64.b64encode(f"operator:{password}".encode()).decode())
    with urllib.request.urlopen(req, timeout=20) as res:
        return {b["id"] for b in json.loads(res.read())["blocks"]}


@pytest.mark.parametrize("kind", ["amqtt", "mosquitto"])
def test_a_block_comes_back_after_the_console_and_the_broker_are_killed_and_restarted(
    kind: str, tmp_path: Path
) -> None:
    with stack_on(make_site(tmp_path / "site"), tmp_path) as stack:
        broker = start_broker(kind, stack, tmp_path / "data-1")
        console, url = start_console(stack)
        operator(stack, "block", "lower", "--id", "op-lifted")
        operator(stack, "unblock", "op-lifted")
        operator(stack, "block", "upper", "--id", "op-kept", "--reason", "spill")
        brief_set = time.monotonic()
        operator(stack, "block", "lower", "--id", "op-brief", "--for", f"{BRIEF_S}s")
        until("the console holds both blocks", lambda: page_blocks(stack, url) == {"op-kept", "op-brief"})
        time.sleep(0.5)
        console.kill9()
        broker.kill9()
        time.sleep(max(0.0, brief_set + BRIEF_S + 0.5 - time.monotonic()))  # op-brief has expired

        start_broker(kind, stack, tmp_path / "data-2")  # an empty store: it lost every block
        console, url = start_console(stack)
        assert "op-kept" in page_blocks(stack, url), "the page shows the block at once"
        endpoint = Endpoint(kind, stack.host, stack.port, stack.creds)
        with client(endpoint, "robot1", f"robot1-check-{time.monotonic_ns()}") as robot:
            robot.subscribe(topics.all_operator_blocks(SITE))
            got = robot.wait_for(topics.operator_block(SITE, "op-kept"), timeout=15)
            assert json.loads(got.payload) == {"v": 1, "zone": "upper", "reason": "spill"}
            time.sleep(1.0)
            assert set(robot.topics()) == {topics.operator_block(SITE, "op-kept")}, "only op-kept came back"
        with client(endpoint, "robot1", f"robot1-late-{time.monotonic_ns()}") as late:
            late.subscribe(topics.all_operator_blocks(SITE))
            assert late.wait_for(topics.operator_block(SITE, "op-kept"), timeout=10).retain
        assert page_blocks(stack, url) == {"op-kept"}
        assert console.alive()
