"""Several operator tools at once, on both real brokers: the console, `wsnav watch`, `wsnav status`, the zone
simulator's world publisher and the health check run together, as processes, for several seconds. On Mosquitto
a client id is its login (`use_username_as_clientid`), and they all logged in as `operator`: 22 takeovers in 45 s,
`watch` saying "broker not reachable", a false banner on the console's page. Each now has a login of its own
with the operator's rights, and an identity still cannot take another's client id."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.broker_fixtures import Endpoint, client, wait_listening
from tests.conftest import require_tool
from tests.console_fixtures import chromium, start_console, until
from tests.stack_fixtures import SITE, WSNAV, Stack, make_site, stack_on
from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.runtime.login_copies import LoginCopies
from wsnav.schemas import topics
from wsnav.schemas.credentials import TOOL_COPIES, Credentials, tool_copies, tool_login
from wsnav.schemas.site import load_site

pytestmark = pytest.mark.timeout(180)

RUN_S = 8.0
COPIES_RUN_S = 3.0
TAKEOVER = "already connected, closing old connection"
"""What Mosquitto 2.0 logs when a connection takes an open client id over."""


@contextlib.contextmanager
def broker(kind: str, stack: Stack) -> Iterator[Path]:
    """The broker of `kind` as a process on the stack's port; yields its log file."""
    if kind == "amqtt":
        proc = stack.broker()
        yield proc.log
        return
    exe = require_tool("mosquitto")
    data = stack.work / "mq-data"
    data.mkdir()
    options = MosquittoOptions(bind=(stack.host, stack.port), data_dir=data, user="root")
    write_mosquitto_config(load_site(stack.site).spec, stack.creds, stack.work / "mq", options)
    proc = stack.start("mosquitto", [exe, "-c", str(stack.work / "mq" / CONF)])
    wait_listening(stack.host, stack.port, proc.popen)
    yield proc.log


def operator_args(stack: Stack) -> list[str]:
    return [
        "--site",
        str(stack.site),
        "--broker",
        stack.broker_addr,
        "--credentials",
        str(stack.creds / "operator.json"),
    ]


@pytest.mark.parametrize("kind", ["amqtt", "mosquitto"])
def test_console_watch_status_zone_sim_and_health_check_run_together_without_taking_each_other_over(
    kind: str, tmp_path: Path
) -> None:
    with stack_on(make_site(tmp_path / "site"), tmp_path) as stack, broker(kind, stack) as broker_log:
        quiet = tmp_path / "quiet.yaml"
        quiet.write_text("duration_s: 3600\n")
        stack.zones("--scenario", str(quiet))  # its world publisher stays connected as the operator's
        console, url = start_console(stack)
        password = json.loads((stack.creds / "operator.json").read_text())["password"]
        watch = stack.start("watch", [*WSNAV, "watch", *operator_args(stack), "--every", "0.3"])
        health = [
            sys.executable,
            "-m",
            "wsnav.healthcheck",
            "nodes",
            "--site",
            str(stack.site),
            "--broker",
            stack.broker_addr,
            "--credentials",
            str(stack.creds / "operator.json"),
        ]

        def link_up() -> bool:
            return bool(state(url, password)["broker_connected"])

        until(
            "the console connected and both nodes online", lambda: link_up() and nodes_online(url, password)
        )
        browser = contextlib.ExitStack()
        page = browser.enter_context(page_with_banner_watch(url, password))
        banner: list[float] = []
        statuses: list[subprocess.CompletedProcess[str]] = []
        checks: list[subprocess.CompletedProcess[str]] = []
        end = time.monotonic() + RUN_S
        while time.monotonic() < end:
            statuses.append(run([*WSNAV, "status", *operator_args(stack), "--json"]))
            checks.append(run(health))
            for _ in range(5):
                if not link_up():
                    banner.append(time.monotonic())
                time.sleep(0.05)
        shown_banner = page.evaluate("window.__bannerShown")
        browser.close()
        assert not shown_banner, f"the page's banner said: {shown_banner}"
        assert console.alive() and watch.alive(), stack.dump()
        if kind == "mosquitto":
            takeovers = [line for line in broker_log.read_text().splitlines() if TAKEOVER in line]
            assert not takeovers, takeovers[:5]
        assert not banner, f"the console's page showed 'broker not connected' {len(banner)} times"
        assert all(s.returncode == 0 for s in statuses), [s.stderr for s in statuses if s.returncode]
        assert all(json.loads(s.stdout)["broker_connected"] for s in statuses)
        assert all(c.returncode == 0 for c in checks), [c.stdout + c.stderr for c in checks if c.returncode]
        shown = watch.output()
        assert "OPERATOR BLOCKS" in shown, shown[-2000:]
        assert "not reachable" not in shown, "wsnav watch lost the broker"
        assert f"site {SITE}" in shown or SITE in shown


@pytest.mark.parametrize("kind", ["amqtt", "mosquitto"])
def test_two_copies_of_one_tool_run_together_without_taking_each_other_over(
    kind: str, tmp_path: Path
) -> None:
    """Two `wsnav watch` logged in as the same `operator.watch`: on Mosquitto each took the other's connection
    over (a client id is its login). A second copy now logs in as `operator.watch.2`."""
    with stack_on(make_site(tmp_path / "site"), tmp_path) as stack, broker(kind, stack) as broker_log:
        watches = [
            stack.start(f"watch{i}", [*WSNAV, "watch", *operator_args(stack), "--every", "0.3"])
            for i in (1, 2)
        ]
        until("both copies drawn", lambda: all("OPERATOR BLOCKS" in w.output() for w in watches))
        time.sleep(COPIES_RUN_S)
        assert all(w.alive() for w in watches), stack.dump()
        if kind == "mosquitto":
            takeovers = [line for line in broker_log.read_text().splitlines() if TAKEOVER in line]
            assert not takeovers, takeovers[:5]
        for w in watches:
            shown = w.output()
            assert "OPERATOR BLOCKS" in shown, shown[-2000:]
            assert "not reachable" not in shown, "a copy of wsnav watch lost the broker"


def test_copies_of_a_tool_on_one_host_hold_different_logins_and_free_them(tmp_path: Path) -> None:
    """Which login each copy takes (runtime.login_copies): never one another copy of this host holds, also after
    moving on from a lost connection; a copy that ends frees its login."""
    creds = Credentials(username="operator", password="p" * 32, role="operator", site=SITE)
    logins = tool_copies(tool_login(creds, "watch"))
    assert logins[:2] == ["operator.watch", "operator.watch.2"] and len(logins) == TOOL_COPIES
    first, second = LoginCopies(logins, tmp_path), LoginCopies(logins, tmp_path)
    a, b = first.take(), second.take()
    assert a != b
    first.move_on()  # a lost connection: on to a login no copy holds
    second.move_on()
    assert len({a, b, first.current, second.current}) == 4
    third, fourth = LoginCopies(logins, tmp_path), LoginCopies(logins, tmp_path)
    assert [third.take(), fourth.take()] == [a, b], "the logins moved away from are free again"
    held = first.current
    first.release()
    assert LoginCopies(logins, tmp_path).take() == held


def test_an_identity_cannot_take_over_an_operator_tools_client_id_on_mosquitto(tmp_path: Path) -> None:
    """The tools' logins are names no site id can have ('.'); a robot asking for `operator.console` as its
    client id is given its own (the client id is its username), and the console stays connected."""
    with stack_on(make_site(tmp_path / "site"), tmp_path) as stack, broker("mosquitto", stack) as broker_log:
        console, url = start_console(stack)
        password = json.loads((stack.creds / "operator.json").read_text())["password"]
        until("the console connected", lambda: state(url, password)["broker_connected"])
        endpoint = Endpoint("mosquitto", stack.host, stack.port, stack.creds)
        with client(endpoint, "robot1", "operator.console") as robot:
            robot.subscribe(topics.all_operator_blocks(SITE))
            time.sleep(1.0)
        assert state(url, password)["broker_connected"]
        assert TAKEOVER not in broker_log.read_text()
        assert console.alive()


@contextlib.contextmanager
def page_with_banner_watch(url: str, password: str) -> Iterator[Any]:
    """The console's page in Chromium, logged in, recording every text its banner shows from then on."""
    with chromium() as browser:
        page = browser.new_context(bypass_csp=True).new_page()
        page.goto(url + "/")
        page.fill("input[name=password]", password)
        page.click("button[type=submit]")
        page.wait_for_url(url + "/")
        page.wait_for_function("document.querySelector('#zone-upper')?.dataset.state === 'clear'")
        page.evaluate(
            """() => {
              window.__bannerShown = [];
              const banner = document.getElementById("banner");
              new MutationObserver(() => {
                if (!banner.hidden) window.__bannerShown.push(banner.textContent);
              }).observe(banner, { attributes: true, childList: true, characterData: true, subtree: true });
            }"""
        )
        yield page


def run(args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, capture_output=True, text=True, timeout=60)


def state(url: str, password: str) -> dict[str, object]:
    import base64
    import urllib.request

    req = urllib.request.Request(url + "/api/state")
    req.add_header("Authorization", "Basic " + base64.b64encode(f"operator:{password}".encode()).decode())
    with urllib.request.urlopen(req, timeout=20) as res:
        return json.loads(res.read())


def nodes_online(url: str, password: str) -> bool:
    nodes = state(url, password)["nodes"]
    assert isinstance(nodes, list)
    return len(nodes) == 2 and all(n.get("online") for n in nodes)
