"""MQTT intake of the zone layer: each kind of bad message is dropped and counted and leaves the costmap
byte-identical; the seq rule tolerates reboots and wrap-around; and the same holds through the real broker with
a node's own credentials, the firmware's own payloads, and a node that tries to speak for another."""

from __future__ import annotations

import json
import logging
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.site_fixtures import tiny_site
from wsnav import firmware
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.runtime.bus import Message, Will
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.messages import NodeStatus, OperatorBlock, ZoneState
from wsnav.schemas.site import Site, load_site
from wsnav.zones.cost_values import LETHAL_OBSTACLE
from wsnav.zones.geometry import GridFrame, polygon_window
from wsnav.zones.intake import ZoneIntake
from wsnav.zones.zone_rule import ZoneRule

# The firmware's own state machine (pyright cannot follow a module loaded at run time).
NodeLogic: Any = firmware.load_device_modules("node_logic")["node_logic"].NodeLogic

SCHOOL = "school"


class Agent:
    """The agent's zone pipeline: intake -> zone layer -> layered costmap."""

    def __init__(self, site: Site) -> None:
        self.layer = ZoneRule(site.spec, GridFrame.of_grid(site.grid))
        self.intake = ZoneIntake(site.spec, self.layer)
        self.costmap = LayeredCostmap(
            site.grid, InflationParams(), zone_layer=self.layer, obstacle_layer=False
        )

    def feed(self, topic: str, payload: bytes | str, t: float = 0.0, retain: bool = True) -> bool:
        raw = payload.encode() if isinstance(payload, str) else payload
        changed = self.intake.handle(Message(topic, raw, retain, t))
        self.costmap.update_zones(t)
        return changed


def state(zone: str, node: str, word: str, seq: int) -> bytes:
    return ZoneState.model_validate({"zone": zone, "node": node, "state": word, "seq": seq}).to_payload()


def z_topic(zone: str, node: str, site: str = SCHOOL) -> str:
    return topics.zone_state(site, zone, node)


BAD = [
    (
        "oversized",
        z_topic("z1", "n1"),
        b'{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":9' + b" " * 2000 + b"}",
    ),
    ("malformed", z_topic("z1", "n1"), b'{"v":1,"zone":"z1","node":"n1","state":"blocked",'),
    ("malformed", z_topic("z1", "n1"), b"\xff\xfe"),
    ("invalid", z_topic("z1", "n1"), b'{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":"9"}'),
    ("invalid", z_topic("z1", "n1"), b'{"v":1,"zone":"z1","node":"n1","state":"on_fire","seq":9}'),
    ("invalid", z_topic("z1", "n1"), b'{"v":2,"zone":"z1","node":"n1","state":"blocked","seq":9}'),
    ("invalid", z_topic("z1", "n1"), b'["blocked"]'),
    ("invalid", z_topic("z1", "n1"), b'{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":9.5}'),
    ("invalid", z_topic("z1", "n1"), b'{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":9,"extra":1}'),
    ("unknown_zone", z_topic("z9", "n1"), state("z9", "n1", "blocked", 9)),
    ("unknown_node", z_topic("z1", "n99"), state("z1", "n99", "blocked", 9)),
    ("wrong_node", z_topic("z1", "n3"), state("z1", "n3", "blocked", 9)),
    ("mismatch", z_topic("z1", "n1"), state("z2", "n1", "blocked", 9)),
    ("mismatch", z_topic("z1", "n1"), state("z1", "n2", "blocked", 9)),
    ("old_seq", z_topic("z1", "n1"), state("z1", "n1", "blocked", 5)),
    ("old_seq", z_topic("z1", "n1"), state("z1", "n1", "blocked", 4)),
    ("wrong_site", z_topic("z1", "n1", site="other"), state("z1", "n1", "blocked", 9)),
    ("unknown_topic", "wsn/school/zones/z1/state", state("z1", "n1", "blocked", 9)),
    ("unknown_topic", "elsewhere/school/zones/z1/state/n1", state("z1", "n1", "blocked", 9)),
    ("unknown_topic", topics.robot_status(SCHOOL, "robot1"), b"{}"),
    (
        "unknown_node",
        topics.node_status(SCHOOL, "n99"),
        NodeStatus(node="n99", status="offline").to_payload(),
    ),
    ("mismatch", topics.node_status(SCHOOL, "n1"), NodeStatus(node="n2", status="offline").to_payload()),
    ("invalid", topics.node_status(SCHOOL, "n1"), b'{"v":1,"node":"n1","status":"gone"}'),
    ("unknown_zone", topics.operator_block(SCHOOL, "b1"), OperatorBlock(zone="z9").to_payload()),
    ("invalid", topics.operator_block(SCHOOL, "b1"), b'{"v":1,"zone":"z1","polygon":[[0,0],[1,0],[1,1]]}'),
    ("invalid", topics.operator_block(SCHOOL, "b1"), b'{"v":1,"polygon":[[0,0],[1,0]]}'),
    (
        "oversized",
        topics.operator_block(SCHOOL, "b1"),
        b'{"v":1,"zone":"z1","reason":"' + b"x" * 9000 + b'"}',
    ),
]


@pytest.mark.parametrize(("reason", "topic", "payload"), BAD, ids=[f"{i}-{b[0]}" for i, b in enumerate(BAD)])
def test_each_bad_message_is_dropped_counted_and_leaves_the_costmap_identical(
    school: Site, reason: str, topic: str, payload: bytes
) -> None:
    agent = Agent(school)
    assert agent.feed(z_topic("z1", "n1"), state("z1", "n1", "clear", 5)) is False
    before = agent.costmap.master.tobytes()
    version = agent.costmap.version
    costs = agent.layer.zone_costs()
    assert agent.feed(topic, payload, t=1.0) is False
    assert dict(agent.intake.dropped) == {reason: 1}
    assert agent.intake.accepted == 1
    assert agent.costmap.master.tobytes() == before
    assert agent.costmap.version == version
    assert agent.layer.zone_costs() == costs


def test_a_flood_of_garbage_never_raises(school: Site) -> None:
    agent = Agent(school)
    rng = np.random.default_rng(3)
    before = agent.costmap.master.tobytes()
    for i in range(300):
        payload = rng.integers(0, 256, size=int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
        topic = [
            z_topic("z1", "n1"),
            topics.node_status(SCHOOL, "n2"),
            topics.operator_block(SCHOOL, f"b{i}"),
        ][i % 3]
        agent.feed(topic, payload, t=float(i))
    agent.feed(z_topic("z1", "n1"), '{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":1e400}')
    agent.feed(z_topic("z1", "n1"), '{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":-1}')
    agent.feed(
        z_topic("z1", "n1"),
        json.dumps({"v": 1, "zone": "z1", "node": "n1", "state": "blocked", "seq": 2**40}),
    )
    assert agent.costmap.master.tobytes() == before
    assert agent.intake.accepted == 0
    assert sum(agent.intake.dropped.values()) + agent.intake.cleared == 303  # a random payload may be empty
    assert set(agent.intake.dropped) <= {"malformed", "invalid"}


def test_a_flood_of_one_bad_kind_logs_a_few_lines_but_counts_every_drop_and_a_new_kind_is_logged_at_once(
    school: Site, caplog: pytest.LogCaptureFixture
) -> None:
    agent = Agent(school)
    caplog.set_level(logging.WARNING, logger="wsnav.zones.intake")
    for i in range(1000):  # 25 s of bus time, 40 malformed messages a second
        agent.feed(z_topic("z1", "n1"), b"garbage", t=i * 0.025)
    assert agent.intake.dropped == {"malformed": 1000}
    flood_lines = [r.getMessage() for r in caplog.records]
    assert 1 <= len(flood_lines) <= 3, flood_lines
    assert "dropped wsn/school/zones/z1/state/n1 (malformed): not JSON" in flood_lines[0]

    caplog.clear()
    agent.feed(z_topic("z9", "n1"), state("z9", "n1", "blocked", 9), t=25.0)
    assert agent.intake.dropped == {"malformed": 1000, "unknown_zone": 1}
    assert [r.getMessage() for r in caplog.records] == [
        "zone intake: dropped wsn/school/zones/z9/state/n1 (unknown_zone): no zone 'z9' in the site"
    ]

    caplog.clear()
    agent.feed(z_topic("z1", "n1"), state("z1", "n1", "clear", 1), t=40.0)  # a good message after the flood
    summaries = [r.getMessage() for r in caplog.records]
    assert len(summaries) == 1 and "(malformed)" in summaries[0], summaries
    summed = [int(m) for m in re.findall(r"dropped (\d+) zone messages", " ".join(flood_lines + summaries))]
    assert 1 + sum(summed) == 1000
    assert agent.intake.accepted == 1

    caplog.clear()
    agent.feed(z_topic("z1", "n1"), b"garbage again", t=60.0)  # a quiet interval later: logged at once again
    assert [r.getMessage() for r in caplog.records] == [
        "zone intake: dropped wsn/school/zones/z1/state/n1 (malformed): not JSON"
    ]
    assert agent.intake.dropped == {"malformed": 1001, "unknown_zone": 1}


def test_good_messages_change_the_map_and_an_empty_retained_payload_removes_a_block(school: Site) -> None:
    agent = Agent(school)
    assert agent.feed(z_topic("z4", "n5"), state("z4", "n5", "blocked", 1)) is True
    assert agent.layer.blocked_zones() == ["z4"]
    assert agent.costmap.cost_at(25.0, 15.0) == LETHAL_OBSTACLE
    block = OperatorBlock(zone="z2", expires_at=100.0).to_payload()
    assert agent.feed(topics.operator_block(SCHOOL, "wet-floor"), block) is True
    assert agent.layer.blocked_zones() == ["z2", "z4"]
    assert agent.feed(topics.operator_block(SCHOOL, "wet-floor"), b"") is True
    assert agent.layer.blocked_zones() == ["z4"]
    assert agent.intake.accepted == 3 and not agent.intake.dropped
    assert sorted(agent.intake.subscriptions()) == sorted(
        ["wsn/school/zones/+/state/+", "wsn/school/nodes/+/status", "wsn/school/operator/blocks/+"]
    )


def test_a_cleared_node_topic_is_counted_not_dropped_and_keeps_what_the_layer_knew(school: Site) -> None:
    """`wsnav broker revoke` clears a node's retained state and status: not garbage, and not a `clear` word."""
    agent = Agent(school)
    assert agent.feed(z_topic("z4", "n5"), state("z4", "n5", "blocked", 1)) is True
    assert agent.feed(z_topic("z4", "n5"), b"") is False
    assert agent.feed(topics.node_status(SCHOOL, "n5"), b"") is False
    assert agent.layer.blocked_zones() == ["z4"]
    assert agent.intake.cleared == 2 and not agent.intake.dropped


def test_seq_must_increase_but_a_reboot_after_its_birth_and_a_wrap_are_accepted(school: Site) -> None:
    agent = Agent(school)
    topic, status = z_topic("z2", "n3"), topics.node_status(SCHOOL, "n3")
    agent.feed(topic, state("z2", "n3", "clear", 1000))
    assert agent.intake.accepted == 1
    agent.feed(topic, state("z2", "n3", "blocked", 1000))
    assert agent.intake.dropped["old_seq"] == 1, "the same seq with another state is old"
    assert agent.feed(topic, state("z2", "n3", "clear", 1000)) is False
    assert (agent.intake.dropped["old_seq"], agent.intake.duplicates) == (1, 1), (
        "a QoS 1 redelivery of the last state (same bytes) is a duplicate, not a drop"
    )
    assert agent.layer.blocked_zones() == []
    # The node reboots: birth, then a state from a new random base below the old seq.
    agent.feed(status, NodeStatus(node="n3", status="online").to_payload(), t=1.0)
    assert agent.feed(topic, state("z2", "n3", "blocked", 17), t=1.0) is True
    assert agent.layer.blocked_zones() == ["z2"]
    assert agent.feed(topic, state("z2", "n3", "clear", 16), t=2.0) is False, (
        "only the first state after birth"
    )
    assert agent.intake.dropped["old_seq"] == 2
    # Wrap-around at the firmware's 2**30 - 1 (after a reboot whose random base lay near the top).
    agent.feed(status, NodeStatus(node="n3", status="online").to_payload(), t=2.5)
    assert agent.feed(topic, state("z2", "n3", "clear", 2**30 - 1), t=3.0) is True
    assert agent.feed(topic, state("z2", "n3", "blocked", 2**30 - 1000), t=3.5) is False, "not a wrap: old"
    assert agent.feed(topic, state("z2", "n3", "blocked", 0), t=4.0) is True
    assert agent.layer.blocked_zones() == ["z2"]


def test_two_captured_states_far_apart_cannot_be_replayed_in_turn(school: Site) -> None:
    """The old wrap rule accepted any drop of more than 2**29 as a wrap: A, B, A, B... all accepted."""
    agent = Agent(school)
    topic = z_topic("z2", "n3")
    a, b = state("z2", "n3", "blocked", 5), state("z2", "n3", "clear", 5 + 2**29 + 1)
    assert agent.feed(topic, a, t=1.0) is True
    accepted = [agent.feed(topic, payload, t=2.0 + i) for i, payload in enumerate([b, a, b, a, b, a])]
    assert accepted == [False] * 6
    assert agent.layer.blocked_zones() == ["z2"]
    # b is refused; a, the last accepted state byte for byte, is as harmless as a QoS 1 redelivery of it.
    assert (agent.intake.dropped["old_seq"], agent.intake.duplicates) == (3, 3)


def receive_into(agent: Agent, bus: MqttBus, until: object, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        bus.wait(0.1)
        for message in bus.poll():
            agent.intake.handle(message)
        agent.costmap.update_zones(time.monotonic())
        if callable(until) and until():
            return
    raise AssertionError("timed out waiting for the broker's messages")


def node_bus(broker: BrokerThread, node: str, logic: Any) -> MqttBus:
    will_topic, will_payload, _, _ = logic.will()
    birth_topic, birth_payload, _, _ = logic.birth()
    return connect_with_credentials(
        broker.host,
        broker.port,
        broker.credentials(node),
        will=Will(will_topic, will_payload),
        birth=Will(birth_topic, birth_payload),
    )


def test_through_the_real_broker_a_node_blocks_its_zone_and_a_spoofing_node_changes_nothing(
    tmp_path: Path,
) -> None:
    site = load_site(tiny_site(tmp_path / "site"))
    agent = Agent(site)
    with BrokerThread(site.directory) as broker:
        robot = connect_with_credentials(broker.host, broker.port, broker.credentials("robot1"))
        for topic_filter in agent.intake.subscriptions():
            robot.subscribe(topic_filter)
        time.sleep(0.3)  # the SUBACKs
        n1 = NodeLogic("tiny", "z1", "n1", 0, 0, 5000, seq_base=41)
        n1_bus = node_bus(broker, "n1", n1)
        for topic, payload, retain, qos in n1.on_connect(0):  # the birth again, and the current state
            n1_bus.publish(topic, payload, qos=qos, retain=retain)
        n1.step(True, 10)  # debounced at once: the sensor sees someone
        topic, payload, retain, qos = n1.state_message(10)
        n1_bus.publish(topic, payload, qos=qos, retain=retain)
        receive_into(agent, robot, lambda: agent.layer.blocked_zones() == ["z1"])
        before = agent.costmap.master.tobytes()
        accepted = agent.intake.accepted

        # n2 watches z2: it tries to clear z1 under n1's topic (the broker refuses it silently), then under its
        # own topic with a payload naming z1 (the intake drops it), then replays n1's old payload on its own topic.
        n2 = NodeLogic("tiny", "z2", "n2", 0, 0, 5000)
        n2_bus = node_bus(broker, "n2", n2)
        n2_bus.publish(topics.zone_state("tiny", "z1", "n1"), state("z1", "n1", "clear", 10**6), retain=True)
        n2_bus.publish(topics.zone_state("tiny", "z2", "n2"), state("z1", "n2", "clear", 10**6), retain=True)
        n2_bus.publish(topics.zone_state("tiny", "z2", "n2"), state("z1", "n1", "clear", 10**6), retain=True)
        n2_bus.publish(topics.zone_state("tiny", "z2", "n2"), b"not json at all", retain=True)
        receive_into(agent, robot, lambda: sum(agent.intake.dropped.values()) >= 3)
        time.sleep(0.5)
        receive_into(agent, robot, lambda: True)
        assert agent.intake.dropped == {"mismatch": 2, "malformed": 1}
        assert agent.layer.blocked_zones() == ["z1"]
        assert agent.costmap.master.tobytes() == before
        assert agent.intake.accepted == accepted + 1, "only n2's birth was accepted"
        for bus in (n2_bus, n1_bus, robot):
            bus.close()


@pytest.mark.parametrize(
    "polygon",
    [
        "[[NaN, 1], [2, 1], [2, 2]]",
        "[[Infinity, 1], [2, 1], [2, 2]]",
        "[[1e400, 1], [2, 1], [2, 2]]",
        "[[-1e6, -1e6], [1e6, -1e6], [1e6, 1e6], [-1e6, 1e6]]",
        "[[1, 1], [20000, 1], [1, 2]]",
        "[[1, 1], [2, 1], [1, 2e8]]",
    ],
    ids=["nan", "inf", "overflow", "1e6-m", "20-km-sliver", "far-point"],
)
def test_operator_block_geometry_out_of_bounds_is_refused_before_any_work(school: Site, polygon: str) -> None:
    """A block reaching +-1e6 m froze the agent for 13 s (6.5 GB); NaN or infinite ones were internal errors."""
    agent = Agent(school)
    payload = f'{{"v": 1, "polygon": {polygon}}}'.encode()
    assert agent.feed(topics.operator_block(SCHOOL, "huge"), payload) is False
    assert agent.layer.blocked_zones() == []
    assert agent.intake.dropped["invalid"] == 1 and not agent.intake.dropped["internal_error"]


def test_duplicate_keys_in_a_zone_state_are_dropped(school: Site) -> None:
    agent = Agent(school)
    payload = b'{"v": 1, "zone": "z2", "node": "n3", "state": "clear", "state": "blocked", "seq": 1}'
    assert agent.feed(z_topic("z2", "n3"), payload) is False
    assert agent.intake.dropped["malformed"] == 1
    assert agent.layer.blocked_zones() == []


def test_a_block_edge_crossing_the_whole_map_is_clipped_not_lost(school: Site) -> None:
    """The outline of an edge that runs far outside the map is still marked where it crosses it."""
    frame = GridFrame.of_grid(school.grid)
    width_m, height_m = frame.width * frame.resolution, frame.height * frame.resolution
    y = frame.origin_y + height_m / 2
    far = [(-9_000.0, y), (9_000.0, y), (9_000.0, y + 0.001)]  # a sliver: only its long edge covers cells
    window = polygon_window(far, frame)
    row = int((y - frame.origin_y) / frame.resolution)
    assert window.mask.shape[1] == frame.width
    assert bool(window.mask[row - window.row0].all()), f"the edge across {width_m:.0f} m is not fully marked"
