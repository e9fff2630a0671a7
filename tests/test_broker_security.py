"""Authentication and topic ACL, with real paho clients over TCP, against the amqtt broker and against real
Mosquitto started from the generated config: both must enforce the same model.

"Never reaches a subscriber" is checked with a sentinel: after the forbidden publish, the same connection
publishes a permitted message; once the subscriber has the sentinel, the forbidden one would have arrived first.
"""

from __future__ import annotations

import os
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.broker_fixtures import TIMEOUT, Client, Endpoint, client, connect_reason, wait_listening
from tests.conftest import require_tool
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.broker.mosquitto.process import free_port
from wsnav.schemas import topics
from wsnav.schemas.site import load_site

SITE = "tiny"


@pytest.fixture(scope="module")
def site_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_site(tmp_path_factory.mktemp("site"), robots=[{"id": "robot1"}, {"id": "robot2"}])


@pytest.fixture(scope="module")
def creds_dir(site_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("creds") / "creds"
    write_credentials(load_site(site_dir).spec, out)
    return out


@pytest.fixture(scope="module", params=["amqtt", "mosquitto"])
def endpoint(
    request: pytest.FixtureRequest, site_dir: Path, creds_dir: Path, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Endpoint]:
    if request.param == "amqtt":
        with BrokerThread(site_dir, creds_dir) as broker:
            yield Endpoint("amqtt", broker.host, broker.port, creds_dir)
        return
    mosquitto = require_tool("mosquitto")
    work = tmp_path_factory.mktemp("mosquitto")
    port = free_port()
    options = MosquittoOptions(
        bind=("127.0.0.1", port), data_dir=work / "data", user="root" if os.geteuid() == 0 else None
    )
    (work / "data").mkdir()
    write_mosquitto_config(load_site(site_dir).spec, creds_dir, work / "conf", options)
    proc = subprocess.Popen([mosquitto, "-c", str(work / "conf" / CONF)], stderr=subprocess.PIPE)
    try:
        wait_listening("127.0.0.1", port, proc)
        yield Endpoint("mosquitto", "127.0.0.1", port, creds_dir)
    finally:
        proc.terminate()
        proc.wait(30)
        if proc.stderr:
            proc.stderr.close()


def test_right_password_is_accepted(endpoint: Endpoint) -> None:
    assert not connect_reason(endpoint, "n1", endpoint.password("n1"), client_id="n1").is_failure


def test_no_credentials_are_refused(endpoint: Endpoint) -> None:
    assert connect_reason(endpoint, None, None).is_failure


def test_username_without_password_is_refused(endpoint: Endpoint) -> None:
    assert connect_reason(endpoint, "n1", None, client_id="n1").is_failure


def test_wrong_password_is_refused(endpoint: Endpoint) -> None:
    assert connect_reason(endpoint, "n1", "x" * 32, client_id="n1").is_failure
    assert connect_reason(endpoint, "n1", endpoint.password("n2"), client_id="n1").is_failure


def test_unknown_user_is_refused(endpoint: Endpoint) -> None:
    assert connect_reason(endpoint, "intruder", endpoint.password("n1")).is_failure


def test_node_cannot_publish_into_another_zone(endpoint: Endpoint) -> None:
    own = topics.zone_state(SITE, "z1", "n1")
    forbidden = [
        topics.zone_state(SITE, "z2", "n1"),  # right node, wrong zone
        topics.zone_state(SITE, "z2", "n2"),  # another node's topic
        topics.node_status(SITE, "n2"),
        topics.operator_block(SITE, "b1"),
        "wsn/other/zones/z1/state/n1",
    ]
    with client(endpoint, "operator", "watcher") as watcher, client(endpoint, "n1") as node:
        assert watcher.subscribe(f"wsn/{SITE}/#") == [1]
        for topic in forbidden:
            node.publish(topic, b'{"state": "blocked"}')
        node.publish(own, b"sentinel")
        watcher.wait_for(own, b"sentinel")
        assert not set(forbidden) & set(watcher.topics())


def test_node_publishes_its_own_diagnostics_and_no_one_elses(endpoint: Endpoint) -> None:
    own = topics.node_info(SITE, "n1")
    forbidden = [
        topics.node_info(SITE, "n2"),  # another node's diagnostics
        f"wsn/{SITE}/nodes/n1/debug",  # nothing else new under its own node
        "homeassistant/binary_sensor/wsnav_tiny/z1_n1/config",  # discovery is the operator's (Pi side)
    ]
    with client(endpoint, "operator", "watcher") as watcher, client(endpoint, "n1") as node:
        assert watcher.subscribe(f"wsn/{SITE}/#") == [1]
        assert watcher.subscribe("homeassistant/#") == [1]
        for topic in forbidden:
            node.publish(topic, b'{"v":1}')
        node.publish(own, b"sentinel")
        watcher.wait_for(own, b"sentinel")
        assert not set(forbidden) & set(watcher.topics())


def test_only_the_operator_commands_a_node(endpoint: Endpoint) -> None:
    """A node or a robot (a stolen password) cannot restart a node: their commands never reach anyone; the
    operator's does."""
    n1, n2 = topics.node_command(SITE, "n1"), topics.node_command(SITE, "n2")
    with (
        client(endpoint, "operator", "watcher") as watcher,
        client(endpoint, "n1") as node,
        client(endpoint, "robot1") as robot,
    ):
        assert watcher.subscribe(f"wsn/{SITE}/#") == [1]
        for sender in (node, robot):
            for topic in (n1, n2):
                sender.publish(topic, b'{"v":1,"id":1,"command":"restart"}')
        node.publish(topics.node_status(SITE, "n1"), b"sentinel")
        robot.publish(topics.robot_status(SITE, "robot1"), b"sentinel")
        watcher.wait_for(topics.node_status(SITE, "n1"), b"sentinel")
        watcher.wait_for(topics.robot_status(SITE, "robot1"), b"sentinel")
        assert not {n1, n2} & set(watcher.topics())
        assert node.subscribe(n1) == [1]
        watcher.publish(n1, b"from-the-operator")
        node.wait_for(n1, b"from-the-operator")


def test_a_node_reads_its_own_commands_and_no_other_nodes(endpoint: Endpoint) -> None:
    own, other = topics.node_command(SITE, "n1"), topics.node_command(SITE, "n2")
    with client(endpoint, "operator") as op, client(endpoint, "n1") as node:
        assert node.subscribe(own) == [1]
        for foreign in (other, topics.all_node_commands(SITE), f"wsn/{SITE}/nodes/#"):
            granted = node.subscribe(foreign)
            if endpoint.kind == "amqtt":  # Mosquitto grants any filter and drops each message on delivery
                assert granted == [128]
        op.publish(other, b"for-n2")
        op.publish(own, b"sentinel")
        node.wait_for(own, b"sentinel")
        assert other not in node.topics()


def test_only_the_operator_sends_update_chunks_and_only_the_node_asks_for_them(endpoint: Endpoint) -> None:
    """OTA (`wsnav firmware ota`): a forged chunk from another node's or a robot's password never reaches the node
    being updated; nor does a request in its name; the operator's chunk and the node's own request do."""
    chunk1, chunk2 = topics.node_ota_chunk(SITE, "n1"), topics.node_ota_chunk(SITE, "n2")
    req1, req2 = topics.node_ota_request(SITE, "n1"), topics.node_ota_request(SITE, "n2")
    with (
        client(endpoint, "operator", "watcher") as watcher,
        client(endpoint, "n1") as n1,
        client(endpoint, "n2") as n2,
        client(endpoint, "robot1") as robot,
    ):
        assert watcher.subscribe(f"wsn/{SITE}/#") == [1]
        assert n1.subscribe(chunk1) == [1]
        for sender in (n2, robot):
            sender.publish(chunk1, b"\x00\x01forged")
        n2.publish(req1, b'{"v":1,"file":0,"offset":0}')
        n1.publish(chunk2, b"\x00\x01forged")
        n1.publish(req1, b"sentinel")
        n2.publish(req2, b"sentinel")
        robot.publish(topics.robot_status(SITE, "robot1"), b"sentinel")
        watcher.wait_for(req1, b"sentinel")
        watcher.wait_for(req2, b"sentinel")
        watcher.wait_for(topics.robot_status(SITE, "robot1"), b"sentinel")
        assert not {chunk1, chunk2} & set(watcher.topics())
        assert [m.payload for m in watcher.received if m.topic == req1] == [b"sentinel"]
        watcher.publish(chunk1, b"from-the-operator")
        n1.wait_for(chunk1, b"from-the-operator")
        assert [m.payload for m in n1.received if m.topic == chunk1] == [b"from-the-operator"]


def test_a_node_reads_its_own_update_chunks_and_no_other_nodes(endpoint: Endpoint) -> None:
    own, other = topics.node_ota_chunk(SITE, "n1"), topics.node_ota_chunk(SITE, "n2")
    with client(endpoint, "operator") as op, client(endpoint, "n1") as node:
        assert node.subscribe(own) == [1]
        granted = node.subscribe(other)
        if endpoint.kind == "amqtt":  # Mosquitto grants any filter and drops each message on delivery
            assert granted == [128]
        op.publish(other, b"for-n2")
        op.publish(own, b"sentinel")
        node.wait_for(own, b"sentinel")
        assert other not in node.topics()


def test_robot_cannot_publish_zone_states(endpoint: Endpoint) -> None:
    forbidden = [
        topics.zone_state(SITE, "z1", "n1"),
        topics.node_status(SITE, "n1"),
        topics.operator_block(SITE, "b1"),
        topics.robot_status(SITE, "robot2"),
    ]
    sentinel = topics.robot_status(SITE, "robot1")
    with client(endpoint, "operator", "watcher") as watcher, client(endpoint, "robot1") as robot:
        assert watcher.subscribe(f"wsn/{SITE}/#") == [1]
        for topic in forbidden:
            robot.publish(topic, b'{"state": "blocked"}')
        robot.publish(sentinel, b"sentinel")
        watcher.wait_for(sentinel, b"sentinel")
        assert not set(forbidden) & set(watcher.topics())


def test_the_dashboard_reads_the_site_and_moves_nothing(endpoint: Endpoint) -> None:
    """The read-only identity for Home Assistant: every write a stolen dashboard password would try is dropped."""
    forbidden = [
        topics.zone_state(SITE, "z1", "n1"),
        topics.node_status(SITE, "n1"),
        topics.operator_block(SITE, "b1"),
        topics.robot_goal(SITE, "robot1"),
        topics.robot_status(SITE, "robot1"),
        topics.sim_world(SITE),
        "homeassistant/binary_sensor/x/config",
    ]
    state = topics.zone_state(SITE, "z2", "n2")
    with (
        client(endpoint, "operator", "watcher") as watcher,
        client(endpoint, "dashboard") as dashboard,
        client(endpoint, "n2") as node,
    ):
        assert watcher.subscribe([f"wsn/{SITE}/#", "homeassistant/#"]) == [1, 1]
        assert dashboard.subscribe([f"wsn/{SITE}/#", "homeassistant/#"]) == [1, 1]
        node.publish(state, b"clear")
        dashboard.wait_for(state, b"clear")
        for topic in forbidden:
            dashboard.publish(topic, b'{"state": "blocked"}')
        dashboard.publish("homeassistant/status", b"online")
        watcher.wait_for("homeassistant/status", b"online")
        assert not set(forbidden) & set(watcher.topics())


def test_robot_reads_zones_and_operator_gives_goals(endpoint: Endpoint) -> None:
    goal = topics.robot_goal(SITE, "robot1")
    state = topics.zone_state(SITE, "z2", "n2")
    with (
        client(endpoint, "robot1") as robot,
        client(endpoint, "operator") as op,
        client(endpoint, "n2") as node,
    ):
        assert robot.subscribe(topics.all_zone_states(SITE)) == [1]
        assert robot.subscribe(goal) == [1]
        node.publish(state, b"clear")
        op.publish(goal, b'"B"')
        robot.wait_for(state, b"clear")
        robot.wait_for(goal, b'"B"')


def test_a_robot_reads_another_robots_status_and_nothing_else_of_it(endpoint: Endpoint) -> None:
    """A fleet: robot2 sees where robot1 is (its status), but cannot read robot1's goals, nor speak for it."""
    status, goal = topics.robot_status(SITE, "robot1"), topics.robot_goal(SITE, "robot1")
    with (
        client(endpoint, "robot1") as robot1,
        client(endpoint, "robot2") as robot2,
        client(endpoint, "operator", "watcher") as watcher,
    ):
        assert robot2.subscribe(status) == [1]
        granted = robot2.subscribe(goal)
        if endpoint.kind == "amqtt":
            assert granted == [128]  # Mosquitto grants any filter and drops each message on delivery instead
        assert watcher.subscribe(f"wsn/{SITE}/robots/#") == [1]
        watcher.publish(goal, b'{"goal": "B"}')
        robot1.publish(status, b"robot1-here")
        robot2.wait_for(status, b"robot1-here")
        assert goal not in robot2.topics()
        for forbidden in (status, goal):
            robot2.publish(forbidden, b"spoofed")
        sentinel = topics.robot_status(SITE, "robot2")
        robot2.publish(sentinel, b"sentinel")
        watcher.wait_for(sentinel, b"sentinel")
        seen = sorted(r.payload for r in watcher.received if r.topic in (status, goal))
        assert seen == sorted([b'{"goal": "B"}', b"robot1-here"])  # the spoofed ones never reached anyone


def test_client_that_subscribes_to_nothing_receives_nothing(endpoint: Endpoint) -> None:
    """amqtt 0.12.1: a new client used to get the retained messages matching *other* clients' filters."""
    state = topics.zone_state(SITE, "z1", "n1")
    goal = topics.robot_goal(SITE, "robot1")
    with client(endpoint, "operator", "watcher") as watcher, client(endpoint, "n1") as node:
        assert watcher.subscribe(f"wsn/{SITE}/#") == [1]
        node.publish(state, b"retained-for-fact-1", retain=True)
        watcher.wait_for(state, b"retained-for-fact-1")
        with client(endpoint, "robot1") as quiet:
            # Only now subscribe to one topic that has no retained message, and have it used: by the time the
            # sentinel arrives, anything the broker pushed at connect time has arrived too.
            assert quiet.subscribe(goal) == [1]
            watcher.publish(goal, b"sentinel")
            quiet.wait_for(goal, b"sentinel")
            assert quiet.topics() == [goal]
        node.publish(state, b"", retain=True)  # clear it for the other tests


def test_subscriptions_outside_the_rules_are_refused(endpoint: Endpoint) -> None:
    if endpoint.kind == "mosquitto":
        pytest.skip("Mosquitto grants any filter and filters each message on delivery instead")
    with client(endpoint, "n1") as node, client(endpoint, "robot1") as robot:
        assert node.subscribe(topics.all_zone_states(SITE)) == [128]
        assert robot.subscribe("#") == [128]
        assert robot.subscribe("wsn/+/zones/#") == [128]
        assert robot.subscribe(topics.zone_state(SITE, "z1", "n1")) == [1]
        assert node.subscribe(topics.zone_state(SITE, "z1", "n1")) == [1]


def test_will_on_a_foreign_topic_never_reaches_a_subscriber(endpoint: Endpoint) -> None:
    """amqtt does not check wills against the ACL: our auth plugin refuses the connect; Mosquitto 2.0 accepts
    it and drops the will when it fires. Either way no subscriber may see it."""
    foreign = topics.node_status(SITE, "n2")
    own = topics.node_status(SITE, "n1")
    with client(endpoint, "operator", "watcher") as watcher:
        assert watcher.subscribe(f"wsn/{SITE}/#") == [1]
        liar = Client(endpoint, "n1", "n1", endpoint.password("n1"))
        reason = liar.connect(will=(foreign, b"offline"))
        if endpoint.kind == "amqtt":
            assert reason.is_failure
        if not reason.is_failure:
            sock = liar.mqtt.socket()
            assert isinstance(sock, socket.socket)
            sock.shutdown(socket.SHUT_RDWR)  # an abnormal end: the broker fires the will
        liar.close()
        with client(endpoint, "n1") as node:
            node.publish(own, b"sentinel")
            watcher.wait_for(own, b"sentinel")
        assert foreign not in watcher.topics()
        assert not connect_reason(
            endpoint, "n1", endpoint.password("n1"), client_id="n1", will=(own, b"x")
        ).is_failure


def test_client_id_of_another_id_is_refused_by_amqtt(endpoint: Endpoint) -> None:
    if endpoint.kind == "mosquitto":
        pytest.skip("Mosquitto 2 cannot reserve client ids for their owners (documented difference)")
    assert connect_reason(endpoint, "robot1", endpoint.password("robot1"), client_id="n1").is_failure
    assert not connect_reason(
        endpoint, "robot1", endpoint.password("robot1"), client_id="robot1-x"
    ).is_failure


def test_refused_client_cannot_hijack_a_connected_clients_id(endpoint: Endpoint) -> None:
    """amqtt 0.12.1 dropped the old session of a client id *before* checking the password: a refused
    client using `robot1` as its client id left the real robot1 connected but deaf."""
    state = topics.zone_state(SITE, "z1", "n1")
    with client(endpoint, "robot1") as robot, client(endpoint, "n1") as node:
        assert robot.subscribe(topics.all_zone_states(SITE)) == [1]
        assert connect_reason(endpoint, None, None, client_id="robot1").is_failure
        assert connect_reason(endpoint, "robot1", "wrong-password-wrong", client_id="robot1").is_failure
        node.publish(state, b"still-heard")
        robot.wait_for(state, b"still-heard")
        # amqtt refuses a site id as another identity's client id; Mosquitto renames it to the username.
        reason = connect_reason(endpoint, "n2", endpoint.password("n2"), client_id="robot1")
        assert reason.is_failure == (endpoint.kind == "amqtt")
        node.publish(state, b"still-heard-2")
        robot.wait_for(state, b"still-heard-2")
        assert robot.disconnects == []


# Client ids of the operator's tools: the zone simulator's link, a health check, an experiment link.
OPERATOR_TOOL_IDS = ["operator-zone-sim", "health-operator-4242", "operator-experiment"]


@pytest.mark.parametrize("tool_id", OPERATOR_TOOL_IDS)
def test_node_cannot_resume_an_operator_tools_persistent_session(endpoint: Endpoint, tool_id: str) -> None:
    """A node reusing an operator tool's client id with clean_session=0 used to inherit its subscriptions on
    amqtt and receive operator blocks, robot goals and robot statuses outside its own ACL."""
    block, goal = topics.operator_block(SITE, "b1"), topics.robot_goal(SITE, "robot1")
    status = topics.robot_status(SITE, "robot1")
    own = topics.node_status(SITE, "n1")
    with client(endpoint, "operator", tool_id, clean_session=False) as tool:
        assert tool.subscribe(f"wsn/{SITE}/#") == [1]
    with (
        client(endpoint, "n1", tool_id, clean_session=False) as thief,
        client(endpoint, "operator") as op,
        client(endpoint, "robot1") as robot,
    ):
        op.publish(block, b'{"v": 1, "zone": "z1"}')
        op.publish(goal, b'"B"')
        robot.publish(status, b'{"v": 1}')
        assert thief.subscribe(own) == [1]
        thief.publish(own, b"sentinel")
        thief.wait_for(own, b"sentinel")
        assert thief.topics() == [own]
    with client(endpoint, "operator", tool_id, clean_session=True):
        pass  # the operator's own session ends clean (and proves the identity still logs in)


@pytest.mark.parametrize("tool_id", [*OPERATOR_TOOL_IDS, "robot1"])
def test_node_using_another_identitys_client_id_kicks_no_one(endpoint: Endpoint, tool_id: str) -> None:
    """With clean sessions a second client with the same id used to disconnect the first (and both kept
    kicking each other as they reconnected); on Mosquitto any identity could kick the robot."""
    ident = "robot1" if tool_id == "robot1" else "operator"
    state = topics.zone_state(SITE, "z1", "n1")
    with client(endpoint, ident, tool_id) as victim:
        assert victim.subscribe(state) == [1]
        reason = connect_reason(endpoint, "n1", endpoint.password("n1"), client_id=tool_id)
        if endpoint.kind == "amqtt" and tool_id == "robot1":
            assert reason.is_failure  # a site id is reserved for its owner
        with client(endpoint, "n1") as node:
            node.publish(state, b"victim-still-hears")
        victim.wait_for(state, b"victim-still-hears")
        assert victim.disconnects == []


def test_oversized_retained_message_is_refused_never_stored_or_delivered(endpoint: Endpoint) -> None:
    """One 100 KB retained message used to be stored (memory, SQLite) and pushed to the robot; the cap (32 KiB)
    is 4x the largest valid payload, which still passes."""
    state = topics.zone_state(SITE, "z1", "n1")
    big = b'{"pad": "' + b"x" * 100_000 + b'"}'
    largest_valid = b'{"pad": "' + b"y" * 8_000 + b'"}'
    with client(endpoint, "operator", "watcher") as watcher:
        assert watcher.subscribe(f"wsn/{SITE}/#") == [1]
        with client(endpoint, "n1") as node:
            node.publish(state, largest_valid, retain=True)
            watcher.wait_for(state, largest_valid)
            node.mqtt.publish(state, big, qos=1, retain=True)
            deadline = time.monotonic() + TIMEOUT
            while not node.disconnects and time.monotonic() < deadline:
                time.sleep(0.05)
            assert node.disconnects, "the broker kept the connection of an oversized publish"
        with client(endpoint, "n1") as node:
            node.publish(topics.node_status(SITE, "n1"), b"sentinel")
            watcher.wait_for(topics.node_status(SITE, "n1"), b"sentinel")
        assert all(len(m.payload) < 10_000 for m in watcher.received)
    with client(endpoint, "robot1") as fresh:
        assert fresh.subscribe(state) == [1]
        assert fresh.wait_for(state).payload == largest_valid  # the retained copy is the last valid one
    with client(endpoint, "n1") as node:
        node.publish(state, b"", retain=True)
