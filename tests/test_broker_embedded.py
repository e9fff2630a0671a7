"""The embeddable broker (asyncio context manager and thread), the QoS of retained messages and the keepalive
fix (docs/broker-amqtt.md): a node that goes silent gets its will published."""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
import time
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
from amqtt.broker import Broker
from paho.mqtt.enums import CallbackAPIVersion

from tests.broker_fixtures import TIMEOUT, Endpoint, client
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerThread, embedded_broker
from wsnav.broker.amqtt.patch import SHUTDOWN_GRACE_S
from wsnav.schemas import topics

SITE = "tiny"


def test_async_context_manager_generates_credentials_and_stops(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    state = topics.zone_state(SITE, "z1", "n1")

    async def main() -> None:
        async with embedded_broker(site, data_dir=tmp_path / "data") as broker:
            ep = Endpoint("amqtt", broker.host, broker.port, broker.credentials_dir)
            assert broker.credentials("n1").username == "n1"

            def exchange() -> None:
                with client(ep, "n1") as node, client(ep, "robot1") as robot:
                    assert robot.subscribe(topics.all_zone_states(SITE)) == [1]
                    node.publish(state, b"blocked", retain=True)
                    robot.wait_for(state, b"blocked")

            await asyncio.to_thread(exchange)
            creds = broker.credentials_dir
        assert not creds.exists()  # the temporary credentials are gone with the broker

    asyncio.run(asyncio.wait_for(main(), TIMEOUT * 2))


def test_retained_qos0_is_delivered_at_qos0(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    state = topics.zone_state(SITE, "z1", "n1")
    with BrokerThread(site) as broker:
        ep = Endpoint("amqtt", broker.host, broker.port, broker.credentials_dir)
        with client(ep, "n1") as node:
            node.publish(state, b"qos0", qos=0, retain=True)
            node.publish(topics.node_status(SITE, "n1"), b"online", qos=1, retain=True)  # after the QoS 0 one
        with client(ep, "robot1") as robot:
            assert robot.subscribe(f"wsn/{SITE}/nodes/#") == [1]
            robot.wait_for(topics.node_status(SITE, "n1"), b"online")
            assert robot.subscribe(topics.all_zone_states(SITE)) == [1]
            got = robot.wait_for(state, b"qos0")
        assert got.retain and got.qos == 0


def test_silent_client_is_dropped_and_its_will_published(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    status = topics.node_status(SITE, "n1")
    with BrokerThread(site) as broker:
        ep = Endpoint("amqtt", broker.host, broker.port, broker.credentials_dir)
        with client(ep, "robot1") as robot:
            assert robot.subscribe(status) == [1]
            node = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="n1")
            node.username_pw_set("n1", ep.password("n1"))
            connected = threading.Event()
            node.on_connect = lambda *_: connected.set()
            node.will_set(status, b"offline", qos=1, retain=True)
            node.connect(ep.host, ep.port, keepalive=2)
            node.loop_start()
            assert connected.wait(TIMEOUT)
            node.publish(status, b"online", qos=1, retain=True).wait_for_publish(TIMEOUT)
            robot.wait_for(status, b"online")
            node.loop_stop()  # the socket stays open, but the node never speaks again (power cut, hang)
            robot.wait_for(status, b"offline")  # within 1.5 x 2 s, not never
            sock = node.socket()
            if sock is not None:
                sock.close()


def test_a_subscriber_that_never_acknowledges_costs_one_warning_line_not_a_traceback(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """amqtt gives up on the delivery after 5 s; the operator reads one line, and the broker goes on serving."""
    site = tiny_site(tmp_path / "site")
    state = topics.zone_state(SITE, "z1", "n1")
    caplog.set_level(logging.WARNING)
    # An experiment worker run earlier in this process sets amqtt's level to CRITICAL (experiments/worker.py).
    caplog.set_level(logging.WARNING, logger="amqtt")
    with BrokerThread(site) as broker:
        ep = Endpoint("amqtt", broker.host, broker.port, broker.credentials_dir)
        silent = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="robot1", manual_ack=True)
        silent.username_pw_set("robot1", broker.credentials("robot1").password)
        silent.connect(broker.host, broker.port)
        silent.loop_start()
        try:
            subscribed = threading.Event()
            silent.on_subscribe = lambda *_: subscribed.set()
            silent.subscribe(topics.all_zone_states(SITE), qos=1)
            assert subscribed.wait(TIMEOUT)
            with client(ep, "n1") as node:
                node.publish(state, b"blocked")
                deadline = time.monotonic() + TIMEOUT
                while "Timeout waiting for PUBACK" not in caplog.text and time.monotonic() < deadline:
                    time.sleep(0.1)
                node.publish(state, b"clear")  # still served
        finally:
            silent.loop_stop()
            silent.disconnect()
    timeouts = [r for r in caplog.records if "Timeout waiting for PUBACK" in r.getMessage()]
    assert len(timeouts) == 1 and timeouts[0].levelno == logging.WARNING
    assert [r.getMessage() for r in caplog.records if r.exc_info] == []


def test_a_stop_whose_session_cleanup_hangs_still_closes_every_connection_within_the_grace(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A robot's link must see the broker go at once: with a session's cleanup stuck (as under load), it saw the
    close only after two keepalives (60 s), and the robot went on trusting a zone map nobody updated."""

    async def stuck(self: Broker, handler: object) -> None:
        await asyncio.sleep(8.0)

    assert SHUTDOWN_GRACE_S < 4.0
    monkeypatch.setattr(Broker, "_stop_handler", stuck)
    site = tiny_site(tmp_path / "site")
    with BrokerThread(site) as broker:
        ep = Endpoint("amqtt", broker.host, broker.port, broker.credentials_dir)
        with client(ep, "robot1") as robot:
            stopping = threading.Thread(target=broker.stop, args=(1.0,))
            deadline = time.monotonic() + 5.0  # the cleanup is stuck for 8 s
            stopping.start()
            while not robot.disconnects:
                assert time.monotonic() < deadline, "the robot's client still thinks it is connected"
                time.sleep(0.05)
            stopping.join()


def test_a_stop_closes_every_connection_at_once_even_one_that_never_logged_in(tmp_path: Path) -> None:
    """amqtt's shutdown ends logged-in sessions only; a socket still in its handshake stayed open after the broker
    was gone, and a client whose cleanup hung was told only by its keepalive (60 s with paho's 30 s)."""

    site = tiny_site(tmp_path / "site")
    with BrokerThread(site) as broker:
        idle = socket.create_connection((broker.host, broker.port), timeout=TIMEOUT)
        time.sleep(0.3)  # accepted and admitted, no CONNECT sent
        broker.stop()
    idle.settimeout(2.0)
    try:
        assert idle.recv(1) == b"", "the broker answered a client that never sent CONNECT"
    except ConnectionResetError:
        pass  # aborted: the same news for the client
    finally:
        idle.close()
