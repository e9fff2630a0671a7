"""The MQTT bus components talk through, against the real amqtt broker: delivery, retained state, the will on
a dropped link, subscriptions renewed after the broker restarts, and a refused login as one line."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.broker_fixtures import port_outside_ephemeral_range
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.amqtt.server import BrokerStartError
from wsnav.broker.credentials import write_credentials
from wsnav.runtime.bus import Message, Will
from wsnav.runtime.clock import Clock, SimClock
from wsnav.runtime.mqtt_bus import BusError, MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.site import load_site
from wsnav.schemas.topics import topic_matches

SITE = "tiny"


def bus_for(
    broker: BrokerThread,
    ident: str,
    *,
    clock: Clock | None = None,
    will: Will | None = None,
    birth: Will | None = None,
) -> MqttBus:
    return connect_with_credentials(
        broker.host, broker.port, broker.credentials(ident), clock=clock, will=will, birth=birth
    )


def receive(bus: MqttBus, count: int, timeout_s: float = 30.0) -> list[Message]:
    got: list[Message] = []
    deadline = time.monotonic() + timeout_s
    while len(got) < count and time.monotonic() < deadline:
        bus.wait(0.2)
        got += bus.poll()
    return got


def test_messages_are_queued_in_order_and_stamped_with_the_bus_clock(tmp_path: Path) -> None:
    clock = SimClock(start=100.0)
    with BrokerThread(tiny_site(tmp_path / "site")) as broker:
        robot = bus_for(broker, "robot1", clock=clock)
        node = bus_for(broker, "n1")
        robot.subscribe(topics.all_zone_states(SITE))
        time.sleep(0.3)  # the SUBACK; the bus subscribes asynchronously
        for i in range(20):
            node.publish(topics.zone_state(SITE, "z1", "n1"), str(i).encode())
        got = receive(robot, 20)
        assert [m.payload for m in got] == [str(i).encode() for i in range(20)]
        assert all(m.received_at == 100.0 and not m.retain for m in got)
        node.close()
        robot.close()


def restarted(site: Path, creds: Path, data: Path, port: int, timeout_s: float = 20.0) -> BrokerThread:
    """The broker started again on `port`, retried while the port is still taken (a restarted service would be
    retried too). The port lies below the ephemeral range: from it (port=0), the robot's own reconnects once
    connected to themselves on the broker's port and held it past the retries (CI, twice)."""
    deadline = time.monotonic() + timeout_s
    while True:
        broker = BrokerThread(site, creds, data_dir=data, port=port)
        try:
            broker.start()
            return broker
        except BrokerStartError as exc:
            broker.stop()
            if "address already in use" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def test_abort_publishes_the_will_and_a_restarted_broker_gets_the_subscriptions_again(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "site")
    status = topics.node_status(SITE, "n1")
    creds = tmp_path / "creds"
    write_credentials(load_site(site).spec, creds)
    port = port_outside_ephemeral_range()
    with BrokerThread(site, creds, data_dir=tmp_path / "data", port=port) as broker:
        robot = bus_for(broker, "robot1")
        robot.subscribe(topics.all_node_statuses(SITE))
        node = bus_for(broker, "n1", will=Will(status, b"offline"), birth=Will(status, b"online"))
        assert [m.payload for m in receive(robot, 1)] == [b"online"]
        node.abort()
        assert [m.payload for m in receive(robot, 1)] == [b"offline"]
    with restarted(site, creds, tmp_path / "data", port):
        assert robot.wait_connected(30.0)
        got = receive(robot, 1)  # the retained `offline`, through the subscription renewed on reconnect
        assert [(m.payload, m.retain) for m in got] == [(b"offline", True)]
        robot.close()


def test_a_wrong_password_fails_at_once_in_one_line(tmp_path: Path) -> None:
    """The broker's refusal ends the connect: paho retrying a refused login until the timeout only made the
    user wait (10 s in the CLI) for the same answer. The timeout here is an hour; the test's own limit is 300 s."""
    with BrokerThread(tiny_site(tmp_path / "site")) as broker:
        bus = MqttBus(broker.host, broker.port, client_id="robot1", username="robot1", password="x" * 16)
        with pytest.raises(BusError, match=r"MQTT broker 127\.0\.0\.1:\d+ refused the login") as err:
            bus.connect(timeout_s=3600.0)
        assert "\n" not in str(err.value)
        assert "password" in str(err.value)
        assert not bus.connected


@pytest.mark.parametrize(
    ("flt", "topic", "expected"),
    [
        ("wsn/s/zones/+/state/+", "wsn/s/zones/z1/state/n1", True),
        ("wsn/s/zones/+/state/+", "wsn/s/zones/z1/state", False),
        ("wsn/s/#", "wsn/s/zones/z1/state/n1", True),
        ("wsn/s/nodes/n1/status", "wsn/s/nodes/n2/status", False),
        ("wsn/s/#", "wsn/s", True),
        ("wsn/+/#", "wsn/s/robots/r1/goal", True),
        ("wsn/s/+", "wsn/s/robots/r1", False),
    ],
)
def test_topic_filters_match_as_in_mqtt(flt: str, topic: str, expected: bool) -> None:
    assert topic_matches(flt, topic) is expected


def test_a_full_queue_and_a_refused_subscription_are_logged_not_silent(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with BrokerThread(tiny_site(tmp_path / "site")) as broker:
        creds = broker.credentials("robot1")
        robot = MqttBus(
            broker.host,
            broker.port,
            client_id="robot1",
            username=creds.username,
            password=creds.password,
            max_queue=3,
        ).connect(timeout_s=30.0)
        node = bus_for(broker, "n1")
        with caplog.at_level("WARNING", logger="wsnav.runtime.mqtt_bus"):
            node.subscribe(topics.all_zone_states(SITE))  # a node may not read other nodes' zones
            robot.subscribe(topics.all_zone_states(SITE))
            time.sleep(0.3)  # the SUBACKs
            for i in range(5):
                node.publish(topics.zone_state(SITE, "z1", "n1"), str(i).encode())
            deadline = time.monotonic() + 30.0
            while robot.dropped_overflow < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert [m.payload for m in robot.poll()] == [b"2", b"3", b"4"], (
                "the newest kept, the oldest dropped"
            )
            assert robot.dropped_overflow == 2
            while not node.refused_subscriptions and time.monotonic() < deadline:
                time.sleep(0.05)
        assert node.refused_subscriptions == [topics.all_zone_states(SITE)]
        assert robot.refused_subscriptions == []
        text = caplog.text
        assert "inbound queue full (3 messages): 1 oldest dropped" in text
        assert f"the broker refused the subscription to {topics.all_zone_states(SITE)}" in text
        node.close()
        robot.close()


def test_oversized_payloads_are_dropped_on_arrival_and_counted(tmp_path: Path) -> None:
    """The brokers cap packets at 32 KiB; the bus drops anything over 16 KiB before it is queued or parsed."""
    with BrokerThread(tiny_site(tmp_path / "site")) as broker:
        robot = bus_for(broker, "robot1")
        node = bus_for(broker, "n1")
        robot.subscribe(topics.all_zone_states(SITE))
        time.sleep(0.3)  # the SUBACK; the bus subscribes asynchronously
        state = topics.zone_state(SITE, "z1", "n1")
        node.publish(state, b"x" * 20_000)
        node.publish(state, b"y" * 8_000)
        got = receive(robot, 1)
        assert [m.payload for m in got] == [b"y" * 8_000]
        assert robot.dropped_oversize == 1
        node.close()
        robot.close()
