"""What one identity may hold on the broker, tried as an insider with one credential would.

Measured before these limits: 100,000 subscription filters from one robot (node -> robot latency p50 7 s on
amqtt), 2,000 parked persistent sessions from one node (never expired), 45,000 x 16 KB retained messages from one
robot (68 -> 738 MB), one node's QoS 0 flood delaying the other nodes' updates by seconds. Retained messages are
bounded by the ACL on both brokers; the other limits are amqtt's (Mosquitto 2.0 has no per-client subscription
cap or publish rate: docs/security.md says what that leaves open).
"""

from __future__ import annotations

import contextlib
import queue
import socket
import struct
import time
from collections.abc import Iterator
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from tests.broker_fixtures import TIMEOUT, Client, Endpoint, client, connect_reason, wsnav
from tests.conftest import require_tool
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.config import BrokerOptions
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.credentials import write_credentials
from wsnav.broker.identity_limits import IdentityLimits
from wsnav.broker.mosquitto.process import mosquitto_process
from wsnav.schemas import topics
from wsnav.schemas.site import load_site

SITE = "tiny"
RATE, BURST = 50.0, 20
SUB_RATE, SUB_BURST = 20.0, 10
LOGIN_RATE, LOGIN_BURST = 20.0, 10
LIMITS = IdentityLimits(
    max_subscriptions=64,
    session_expiry_s=2,
    node_publish_rate=RATE,
    node_publish_burst=BURST,
    subscribe_rate=SUB_RATE,
    subscribe_burst=SUB_BURST,
    login_rate=LOGIN_RATE,
    login_burst=LOGIN_BURST,
)


@pytest.fixture(scope="module")
def site_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_site(tmp_path_factory.mktemp("site"))


@pytest.fixture(scope="module")
def creds_dir(site_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("creds") / "creds"
    write_credentials(load_site(site_dir).spec, out)
    return out


@pytest.fixture(scope="module")
def amqtt(site_dir: Path, creds_dir: Path) -> Iterator[Endpoint]:
    options = BrokerOptions(bind=("127.0.0.1", 0), limits=LIMITS)
    with BrokerThread(site_dir, creds_dir, options=options) as broker:
        yield Endpoint("amqtt", broker.host, broker.port, creds_dir)


@pytest.fixture(scope="module")
def mosquitto(
    site_dir: Path, creds_dir: Path, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Endpoint]:
    require_tool("mosquitto")
    with mosquitto_process(load_site(site_dir).spec, creds_dir, tmp_path_factory.mktemp("mosquitto")) as mq:
        yield Endpoint("mosquitto", mq.host, mq.port, creds_dir)


@pytest.fixture(params=["amqtt", "mosquitto"])
def endpoint(request: pytest.FixtureRequest) -> Endpoint:
    return request.getfixturevalue(request.param)


def test_a_robot_holds_one_retained_message_however_many_topics_it_tries(endpoint: Endpoint) -> None:
    """The robot credential used to publish anywhere under robots/<itself>/: 45,000 retained messages."""
    status = topics.robot_status(SITE, "robot1")
    with client(endpoint, "robot1", "robot1") as robot:
        for i in range(50):
            robot.publish(f"wsn/{SITE}/robots/robot1/junk/{i}", b"x" * 1000, qos=1, retain=True)
        robot.publish(status, b'{"marker": 1}', qos=1, retain=True)
    with client(endpoint, "operator", "operator-limits") as watcher:
        watcher.subscribe(f"wsn/{SITE}/robots/#")
        watcher.wait_for(status)
        time.sleep(1.0)  # any other retained message comes with the status's batch
        assert watcher.topics() == [status]
    with client(endpoint, "operator", "operator-limits") as operator:
        operator.publish(status, b"", qos=1, retain=True)


def test_one_session_is_granted_at_most_its_subscriptions_and_the_site_still_flows(amqtt: Endpoint) -> None:
    state = topics.zone_state(SITE, "z1", "n1")
    with client(amqtt, "robot1", "robot1") as greedy, client(amqtt, "robot1", "robot1-legit") as legit:
        filters = [f"wsn/{SITE}/zones/z1/state/x{i}" for i in range(200)]
        codes = greedy.subscribe(filters)
        assert (
            codes.count(1) == LIMITS.max_subscriptions and codes.count(128) == 200 - LIMITS.max_subscriptions
        )
        assert codes[: LIMITS.max_subscriptions] == [1] * LIMITS.max_subscriptions
        assert greedy.subscribe(f"wsn/{SITE}/zones/#") == [128]
        assert legit.subscribe(f"wsn/{SITE}/zones/#") == [1]  # the limit is per session, not per identity
        greedy.mqtt.unsubscribe(filters[:10])
        deadline = time.monotonic() + TIMEOUT
        while greedy.subscribe(f"wsn/{SITE}/zones/#") != [1]:  # unsubscribing gives the room back
            assert time.monotonic() < deadline, "room not given back after UNSUBSCRIBE"
            time.sleep(0.1)
        with client(amqtt, "n1", "n1") as node:
            node.publish(state, b'{"marker": 2}', qos=1)
        legit.wait_for(state, b'{"marker": 2}')
        greedy.wait_for(state, b'{"marker": 2}')


def session_present(endpoint: Endpoint, ident: str, client_id: str) -> bool:
    """Log in with a persistent session and disconnect: did the broker still hold one for this client id?"""
    answers: queue.Queue[bool] = queue.Queue()
    c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=False)
    c.username_pw_set(ident, endpoint.password(ident))
    c.on_connect = lambda _c, _u, flags, reason, _p: answers.put(bool(flags.session_present))
    c.connect(endpoint.host, endpoint.port)
    c.loop_start()
    try:
        present = answers.get(timeout=TIMEOUT)
        c.subscribe(
            topics.zone_state(SITE, "z1", ident) if ident.startswith("n") else f"wsn/{SITE}/zones/#", 1
        )
        time.sleep(0.1)
        return present
    finally:
        with contextlib.suppress(Exception):
            c.disconnect()
        c.loop_stop()


def test_one_node_parks_at_most_its_share_of_persistent_sessions(amqtt: Endpoint) -> None:
    """40 persistent sessions under distinct client ids: the oldest parked ones make way (2,000 stayed before)."""
    ids = [f"n1-parked-{i}" for i in range(40)]
    for cid in ids:
        assert not session_present(amqtt, "n1", cid)
    kept = [cid for cid in reversed(ids) if session_present(amqtt, "n1", cid)]
    assert 0 < len(kept) <= LIMITS.max_sessions
    assert ids[-1] in kept and ids[0] not in kept


def test_a_parked_session_expires(amqtt: Endpoint) -> None:
    assert not session_present(amqtt, "robot1", "robot1-expiry")
    assert session_present(amqtt, "robot1", "robot1-expiry")  # kept while within the expiry
    time.sleep(LIMITS.session_expiry_s + 2.5)  # amqtt's monitor looks once a second, on whole seconds
    assert not session_present(amqtt, "robot1", "robot1-expiry")


def test_a_flooding_node_is_held_to_its_rate_loses_nothing_and_the_other_node_gets_through(
    amqtt: Endpoint,
) -> None:
    """Backpressure: the broker reads a node's PUBLISH packets no faster than its rate (the excess waits in the
    sockets, TCP slows the sender), so the flood costs the broker nothing and nothing the node sent is lost."""
    flood_topic = topics.zone_state(SITE, "z1", "n1")
    other_topic = topics.zone_state(SITE, "z2", "n2")
    count = 300
    with client(amqtt, "operator", "operator-flood") as watcher, client(amqtt, "n2", "n2") as other:
        watcher.subscribe([f"wsn/{SITE}/zones/#", f"wsn/{SITE}/sim/#"])
        with client(amqtt, "n1", "n1") as flooder:
            t0 = time.monotonic()
            for i in range(count):
                flooder.mqtt.publish(flood_topic, b"%d" % i, qos=0)
            other.publish(other_topic, b'{"marker": 3}', qos=1)
            watcher.wait_for(other_topic, b'{"marker": 3}')
            early = sum(1 for m in watcher.received if m.topic == flood_topic)
            elapsed = time.monotonic() - t0
            assert early <= BURST + RATE * elapsed + 1, (early, elapsed)  # no faster than the rate allows
            watcher.wait_for(flood_topic, b"%d" % (count - 1), timeout=TIMEOUT + count / RATE)
            flooded = [m.payload for m in watcher.received if m.topic == flood_topic]
            assert flooded == [b"%d" % i for i in range(count)]  # all of it, in order
            assert not flooder.disconnects
        with client(amqtt, "operator", "operator-flood-2") as operator:  # only nodes' PUBLISH is rate-limited
            for i in range(300):
                operator.mqtt.publish(f"wsn/{SITE}/sim/flood", b"%d" % i, qos=0)
            watcher.wait_for(f"wsn/{SITE}/sim/flood", b"299")
            assert (
                time.monotonic() - t0 < 300 / RATE + count / RATE
            )  # the operator was not held to a node's rate


def raw_flood(endpoint: Endpoint, packets: int, seconds: float = 1.5) -> tuple[socket.socket, int]:
    """Node n1 logged in over a raw socket, then up to `packets` QoS 0 PUBLISHes (220 B each) as fast as the
    kernel takes them, for at most `seconds` or until the broker cuts it off; returns the socket (open unless
    cut off) and the count sent. The rate limit reads them slowly: the rest wait in the socket buffers."""
    sock = socket.create_connection((endpoint.host, endpoint.port), timeout=TIMEOUT)
    password = endpoint.password("n1").encode()
    connect = b"\x00\x04MQTT\x04\xc2\x00\x1e" + b"".join(
        struct.pack("!H", len(f)) + f for f in (b"n1-flood", b"n1", password)
    )
    sock.sendall(bytes([0x10, len(connect)]) + connect)
    assert sock.recv(4) == b"\x20\x02\x00\x00", "n1 refused"
    topic = topics.zone_state(SITE, "z1", "n1").encode()
    sock.setblocking(False)
    pending, made, size, deadline = bytearray(), 0, 0, time.monotonic() + seconds
    while time.monotonic() < deadline and (made < packets or pending):
        if len(pending) < 65536 and made < packets:
            body = struct.pack("!H", len(topic)) + topic + b"flood %06d " % made + b"x" * 200
            packet = bytes([0x30, len(body) & 0x7F | 0x80, len(body) >> 7]) + body
            pending += packet
            size, made = len(packet), made + 1
        try:
            del pending[: sock.send(pending)]
        except BlockingIOError:
            time.sleep(0.01)
        except ConnectionError:
            break  # the broker cut the flooder off
    return sock, made - len(pending) // size


def flood_seen(watcher: Client) -> int:
    return sum(1 for m in watcher.received if m.payload.startswith(b"flood "))


@pytest.mark.parametrize(("how", "packets"), [("leaves", 250), ("leaves", 10**6), ("revoked", 250)])
def test_a_flood_stops_within_a_second_of_the_flooder_leaving_or_being_revoked(
    amqtt: Endpoint, site_dir: Path, creds_dir: Path, how: str, packets: int
) -> None:
    """The flood that outlived its sender: held to its rate, 2.5 MB waited in the dead connection's buffers
    and kept z1 flipping at the robots for 9 minutes after the flooder exited, and 3 minutes after a revoke.
    A client more than MAX_BACKLOG_BYTES behind its rate is disconnected, and what a departed or revoked
    client sent over its rate is discarded. 250 packets (55 KB) wait under that cap: 5 s of the rate."""
    with client(amqtt, "operator", f"operator-flood-{how}") as watcher:
        watcher.subscribe(f"wsn/{SITE}/zones/#")
        sock, sent = raw_flood(amqtt, packets)
        try:
            assert sent >= 250, sent  # far more than the rate lets through in the test's 3 s
            watcher.wait_for(topics.zone_state(SITE, "z1", "n1"))  # the flood does reach the robots
            if how == "revoked":
                write_credentials(load_site(site_dir).spec, creds_dir, renew=frozenset({"n1"}))
            else:
                sock.close()
            time.sleep(1.0)
            after_a_second = flood_seen(watcher)
            time.sleep(2.0)
            assert flood_seen(watcher) == after_a_second, (sent, after_a_second, flood_seen(watcher))
            assert after_a_second < sent  # the rest was discarded
        finally:
            sock.close()
    with client(amqtt, "n1", "n1") as node, client(amqtt, "operator", "operator-after-flood") as robot:
        robot.subscribe(topics.zone_state(SITE, "z1", "n1"))
        node.publish(topics.zone_state(SITE, "z1", "n1"), b'{"marker": 4}', qos=1)
        robot.wait_for(topics.zone_state(SITE, "z1", "n1"), b'{"marker": 4}')  # the node itself still works


def test_subscribe_packets_and_logins_are_held_to_their_rate(amqtt: Endpoint) -> None:
    """40 SUBSCRIBE packets of one identity cannot be taken faster than burst + rate allows, nor 25 logins."""
    with client(amqtt, "robot1", "robot1-subs") as robot:
        t0 = time.monotonic()
        for i in range(40):
            assert robot.subscribe(f"wsn/{SITE}/zones/z1/state/s{i}") == [1]
        assert time.monotonic() - t0 >= (40 - SUB_BURST) / SUB_RATE * 0.95
    t0 = time.monotonic()
    for i in range(25):
        assert not connect_reason(amqtt, "n2", amqtt.password("n2"), client_id=f"n2-login-{i}").is_failure
    assert time.monotonic() - t0 >= (25 - LOGIN_BURST) / LOGIN_RATE * 0.95


def test_the_limits_are_checked_on_the_command_line(site_dir: Path, creds_dir: Path) -> None:
    for args, words in (
        (["--node-publish-rate", "-1"], "--node-publish-rate"),
        (["--max-subscriptions", "0"], "--max-subscriptions"),
        (["--session-expiry", "0"], "--session-expiry"),
    ):
        done = wsnav(
            "broker", "run", "--site", site_dir, "--credentials", creds_dir, "--bind", "127.0.0.1:0", *args
        )
        assert done.returncode == 2, done
        assert words in done.stderr and "Traceback" not in done.stderr
