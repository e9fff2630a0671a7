"""The containers' health checks (wsnav/healthcheck.py) against the real broker: healthy only when an MQTT
client of the site would be served, and one line saying why not."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from tests.broker_fixtures import mosquitto_on
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.credentials import write_credentials
from wsnav.healthcheck import main
from wsnav.runtime.bus import Will
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.messages import NodeStatus, RobotStatus
from wsnav.schemas.site import load_site


def check(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    code = main(list(args))
    out = capsys.readouterr()
    return code, (out.out + out.err).strip()


def connect(broker: BrokerThread, ident: str, birth: Will | None = None) -> MqttBus:
    creds = broker.credentials(ident)
    bus = MqttBus(
        broker.host, broker.port, client_id=ident, username=ident, password=creds.password, birth=birth
    )
    return bus.connect()


def node_birth(node: str) -> Will:
    payload = NodeStatus(node=node, status="online").to_payload()
    return Will(topics.node_status("tiny", node), payload)


def test_broker_check_needs_a_working_login(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    site = tiny_site(tmp_path / "site")
    with BrokerThread(site) as broker:
        address = f"{broker.host}:{broker.port}"
        creds = broker.credentials_dir / "operator.json"
        assert check(capsys, "broker", "--broker", address, "--credentials", str(creds)) == (
            0,
            f"broker {address} accepts operator",
        )
        wrong = tmp_path / "wrong.json"
        raw = json.loads(creds.read_text())
        wrong.write_text(json.dumps(raw | {"password": "x" * 32}))
        code, text = check(
            capsys, "broker", "--broker", address, "--credentials", str(wrong), "--timeout", "2"
        )
        assert code == 1
        assert text.startswith(f"unhealthy: MQTT broker {address} refused the login") and "\n" not in text
    code, text = check(capsys, "broker", "--broker", address, "--credentials", str(tmp_path / "none.json"))
    assert (code, text.startswith("unhealthy: ")) == (1, True)


def test_nodes_check_names_the_nodes_not_online(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    site = tiny_site(tmp_path / "site")
    with BrokerThread(site) as broker:
        args = ["nodes", "--site", str(site), "--broker", f"{broker.host}:{broker.port}"]
        args += ["--credentials", str(broker.credentials_dir / "operator.json"), "--timeout", "2"]
        assert check(capsys, *args) == (1, "unhealthy: nodes not online: n1, n2")
        n1 = connect(broker, "n1", node_birth("n1"))
        assert check(capsys, *args) == (1, "unhealthy: nodes not online: n2")
        n2 = connect(broker, "n2", node_birth("n2"))
        assert check(capsys, *args) == (0, "2 nodes online")
        n1.close()
        n2.close()


def test_robot_check_wants_a_live_status_not_a_retained_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    site = tiny_site(tmp_path / "site")
    with BrokerThread(site) as broker:
        args = ["robot", "--site", str(site), "--robot", "robot1", "--broker", f"{broker.host}:{broker.port}"]
        args += ["--credentials", str(broker.credentials_dir / "operator.json"), "--timeout", "2"]
        robot = connect(broker, "robot1")
        status = RobotStatus(robot="robot1", state="idle", pose=(1.0, 4.0, 0.0)).to_payload()
        robot.publish(topics.robot_status("tiny", "robot1"), status, retain=True)
        assert check(capsys, *args) == (1, "unhealthy: no status from robot1 within 2 s")
        robot.close()
        # A robot that reports: its periodic status arrives while the check listens.
        robot = connect(broker, "robot1")
        stop = threading.Event()

        def report() -> None:
            while not stop.wait(0.2):
                robot.publish(topics.robot_status("tiny", "robot1"), status)

        reporter = threading.Thread(target=report, daemon=True)
        reporter.start()
        try:
            assert check(capsys, *args) == (0, "robot1 reports idle")
        finally:
            stop.set()
            reporter.join()
            robot.close()


@pytest.mark.slow
@pytest.mark.parametrize("writable", [True, False])
def test_mosquitto_that_cannot_save_its_store_is_unhealthy(
    writable: bool, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A Mosquitto that cannot write its store (the usual cause: started as root without `user`, it drops to
    `mosquitto`, who cannot write a root-owned folder; here the folder is replaced by a file) only logs an error
    at each autosave, and an operator block is gone at the next restart. The check says so."""
    import os
    import subprocess
    import time

    from tests.broker_fixtures import wait_listening
    from tests.conftest import require_tool
    from wsnav.broker.credentials import write_credentials
    from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
    from wsnav.broker.mosquitto.process import free_port
    from wsnav.schemas.site import load_site

    mosquitto = require_tool("mosquitto")
    site = tiny_site(tmp_path / "site")
    write_credentials(load_site(site).spec, tmp_path / "creds")
    port, data = free_port(), tmp_path / "data"
    user = "root" if os.geteuid() == 0 else None
    options = MosquittoOptions(bind=("127.0.0.1", port), data_dir=data, user=user, autosave_interval_s=1)
    write_mosquitto_config(load_site(site).spec, tmp_path / "creds", tmp_path / "mq", options)
    if not writable:
        data.rmdir()
        data.write_text("")
    proc = subprocess.Popen([mosquitto, "-c", str(tmp_path / "mq" / CONF)], stderr=subprocess.DEVNULL)
    try:
        wait_listening("127.0.0.1", port, proc)
        time.sleep(3.0)  # three autosave intervals
        code, line = check(capsys, "mosquitto-store", "--data", str(data), "--autosave", "1")
    finally:
        proc.terminate()
        proc.wait(30)
    if writable:
        assert code == 0 and "saved" in line, line
    else:
        assert code == 1 and "has not saved its store" in line and "--user" in line, line


def test_the_robot_check_never_logs_in_as_the_robot_so_the_running_robot_keeps_its_connection(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """On Mosquitto a client id is its login: docker-compose's robot check, logged in as robot1 every 10 s, took
    the running agent's connection over. A robot's (or any but the operator's) file is refused in one line; with
    the operator's the check reads the status and the robot stays connected."""
    site = tiny_site(tmp_path / "site")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    with mosquitto_on(site, creds, tmp_path / "mq", tmp_path / "data") as (endpoint, _proc):
        robot = connect_with_credentials(
            endpoint.host, endpoint.port, load_credentials(creds / "robot1.json")
        )
        stop = threading.Event()
        status = RobotStatus(robot="robot1", state="idle", pose=(1.0, 4.0, 0.0)).to_payload()

        def report() -> None:
            while not stop.wait(0.2):
                robot.publish(topics.robot_status("tiny", "robot1"), status)

        reporter = threading.Thread(target=report, daemon=True)
        reporter.start()
        try:
            args = [
                "robot",
                "--site",
                str(site),
                "--robot",
                "robot1",
                "--broker",
                f"{endpoint.host}:{endpoint.port}",
            ]
            code, text = check(capsys, *args, "--credentials", str(creds / "robot1.json"), "--timeout", "2")
            assert code == 1 and "\n" not in text and "operator" in text, text
            assert check(capsys, *args, "--credentials", str(creds / "operator.json"), "--timeout", "2") == (
                0,
                "robot1 reports idle",
            )
            time.sleep(0.3)
            assert robot.connected and robot.connects == 1, "the check took the robot's connection over"
        finally:
            stop.set()
            reporter.join()
            robot.close()
