"""Node failures through the real amqtt broker: a node that dies without DISCONNECT goes stale for a subscriber
that judges by message age and its will says `offline`; a reboot says `online` again with a fresh seq base."""

from __future__ import annotations

import json
import time
from pathlib import Path

from tests.zone_sim_fixtures import HEARTBEAT_S, drive, settle, sim_site, subscriber, wait_online
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.runtime.bus import Message
from wsnav.runtime.clock import SimClock
from wsnav.schemas import topics
from wsnav.schemas.messages import NodeStatus, ZoneState, parse_payload
from wsnav.schemas.site import load_site
from wsnav.zone_sim.simulator import ZoneSimulator


class Ages:
    """What a robot would track: when each node's last zone state arrived, and its last status word."""

    def __init__(self) -> None:
        self.last_state_at: dict[str, float] = {}
        self.status: dict[str, list[str]] = {}
        self.seqs: dict[str, list[int]] = {}

    def take(self, messages: list[Message]) -> None:
        for m in messages:
            parsed = topics.parse(m.topic)
            if parsed is None or parsed.node is None:
                continue
            if parsed.kind == "zone_state":
                self.last_state_at[parsed.node] = m.received_at
                self.seqs.setdefault(parsed.node, []).append(parse_payload(ZoneState, m.payload).seq)
            elif parsed.kind == "node_status":
                self.status.setdefault(parsed.node, []).append(parse_payload(NodeStatus, m.payload).status)


def test_a_killed_node_goes_stale_and_offline_and_comes_back_after_a_reboot(tmp_path: Path) -> None:
    site_dir = sim_site(tmp_path / "site")
    clock = SimClock()
    with BrokerThread(site_dir) as broker:
        robot = subscriber(broker, clock)
        sim = ZoneSimulator(load_site(site_dir), broker.credentials_dir, (broker.host, broker.port), clock)
        sim.start()
        wait_online(sim, clock, 3)
        ages = Ages()
        drive(sim, clock, until=clock.now() + 3.0)
        sim.kill_node("n1")
        killed_at = clock.now()
        # Watch for 5 heartbeats, polling as the robot's loop would.
        while clock.now() < killed_at + 5 * HEARTBEAT_S:
            drive(sim, clock, until=clock.now() + 0.25)
            ages.take(robot.poll())
        ages.take(settle(robot, quiet_s=0.3))
        now = clock.now()
        assert now - ages.last_state_at["n1"] > 3 * HEARTBEAT_S  # stale by the 3-heartbeat rule
        assert now - ages.last_state_at["n2"] <= 1.5 * HEARTBEAT_S  # its neighbours are still fresh
        assert now - ages.last_state_at["n3"] <= 1.5 * HEARTBEAT_S
        assert ages.status["n1"] == ["online", "offline"]  # the will, published by the broker
        assert ages.status["n2"] == ["online"]
        before = list(ages.seqs["n1"])

        sim.reboot_node("n1")
        wait_online(sim, clock, 3)
        drive(sim, clock, until=clock.now() + 2.0)
        ages.take(settle(robot, quiet_s=0.3))
        assert ages.status["n1"] == ["online", "offline", "online"]
        after = ages.seqs["n1"][len(before) :]
        assert len(after) >= 2 and after[0] != before[-1] + 1  # a new boot, a new random seq base
        assert after == list(range(after[0], after[0] + len(after)))
        assert sim.nodes["n1"].boots == 2
        sim.stop()
        robot.close()


def test_a_hung_node_is_dropped_by_the_broker_after_one_and_a_half_keepalives(tmp_path: Path) -> None:
    site_dir = sim_site(tmp_path / "site")
    with BrokerThread(site_dir) as broker:
        config = broker.credentials_dir / "n1.json"
        raw = json.loads(config.read_text())
        raw["keepalive_s"] = 5  # the firmware's smallest: the broker gives up after 7.5 s of silence
        config.write_text(json.dumps(raw))
        clock = SimClock()
        robot = subscriber(broker, clock)
        sim = ZoneSimulator(
            load_site(site_dir), broker.credentials_dir, (broker.host, broker.port), clock, nodes=["n1"]
        )
        sim.start()
        wait_online(sim, clock, 1)
        sim.kill_node("n1", hang=True)  # socket open, nothing sent: only the keepalive check can notice
        status: list[str] = []
        deadline = time.monotonic() + 20.0
        while "offline" not in status and time.monotonic() < deadline:
            robot.wait(0.5)
            status += [
                parse_payload(NodeStatus, m.payload).status for m in robot.poll() if "/status" in m.topic
            ]
        assert status == ["online", "offline"]
        sim.stop()
        robot.close()
