"""An emulated node sends what a board running firmware/device/app.py sends: the same topics, retain and QoS, a
will of `offline`, birth then state on connect, and payloads byte-identical to the schemas models."""

from __future__ import annotations

import random
from pathlib import Path

from tests.zone_sim_fixtures import SITE, drive, settle, sim_site, subscriber, wait_online
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.runtime.clock import SimClock
from wsnav.schemas import topics
from wsnav.schemas.messages import NodeInfo, NodeStatus, ZoneState, parse_payload
from wsnav.schemas.site import load_site
from wsnav.zone_sim.emulated_node import Sent
from wsnav.zone_sim.firmware_modules import SEQ_BASE_BITS, NodeLogic, diagnostics
from wsnav.zone_sim.scenario import Block, Scenario
from wsnav.zone_sim.simulator import ZoneSimulator

FIRMWARE_VERSION = diagnostics.FIRMWARE_VERSION


def test_emulated_nodes_send_the_contracts_bytes_as_the_firmware_does(tmp_path: Path) -> None:
    site_dir = sim_site(tmp_path / "site")
    clock = SimClock()
    sent: list[Sent] = []
    with BrokerThread(site_dir) as broker:
        robot = subscriber(broker, clock)
        robot.subscribe(topics.all_node_infos(SITE))  # retained: arrives even if this lands after the publish
        sim = ZoneSimulator(
            load_site(site_dir),
            broker.credentials_dir,
            (broker.host, broker.port),
            clock,
            Scenario(blocks=[Block(zone="z1", from_s=0.5)]),
            seed=3,
            on_sent=sent.append,
        )
        sim.start()
        wait_online(sim, clock, 3)
        drive(sim, clock, until=clock.now() + 3.0)
        sim.kill_node("n2")
        delivered = settle(robot)
        sim.stop()
        robot.close()

    infos: list[NodeInfo] = []
    for s in sent:
        parsed = topics.parse(s.topic)
        assert parsed is not None and parsed.node == s.node
        assert (s.retain, s.qos) == (True, 0 if parsed.kind == "node_info" else 1)
        if parsed.kind == "node_info":  # the firmware's diagnostics, without what only a board can measure
            info = parse_payload(NodeInfo, s.payload)
            assert info.to_payload() == s.payload and info.node == s.node
            assert (info.reset, info.rssi, info.heap_free, info.fw) == (
                "power_on",
                None,
                None,
                FIRMWARE_VERSION,
            )
            infos.append(info)
        elif parsed.kind == "zone_state":
            msg = parse_payload(ZoneState, s.payload)
            assert s.topic == topics.zone_state(SITE, msg.zone, s.node)
            assert (
                ZoneState(zone=msg.zone, node=s.node, state=msg.state, seq=msg.seq).to_payload() == s.payload
            )
        else:
            status = parse_payload(NodeStatus, s.payload)
            assert s.topic == topics.node_status(SITE, s.node)
            assert NodeStatus(node=s.node, status=status.status).to_payload() == s.payload

    assert sorted(i.node for i in infos) == ["n1", "n2", "n3"]  # one each, right after connecting
    assert all(i.reconnects == 0 and i.error is None for i in infos)

    # On connect: birth `online`, then the current state with the boot's seq base + 1, as NodeLogic decides.
    n1 = [s for s in sent if s.node == "n1" and not s.topic.endswith("/info")]
    base = random.Random("3/node/n1").getrandbits(SEQ_BASE_BITS)
    logic = NodeLogic(SITE, "z1", "n1", 200, 400, 1000, base)
    expected = [(topic, payload) for topic, payload, _r, _q in logic.on_connect(0)]
    assert [(s.topic, s.payload) for s in n1[:2]] == expected
    assert b'"blocked"' in n1[-1].payload

    # The broker passed every byte through, and the will is the firmware's `offline`.
    wire = {(m.topic, m.payload) for m in delivered}
    assert {(s.topic, s.payload) for s in sent} <= wire
    assert (topics.node_status(SITE, "n2"), NodeStatus(node="n2", status="offline").to_payload()) in wire
    assert logic.will() == (
        topics.node_status(SITE, "n1"),
        b'{"v":1,"node":"n1","status":"offline"}',
        True,
        1,
    )
