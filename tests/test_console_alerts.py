"""The console's alerts and block extensions from messages alone (no broker): what raises an alert, what ends it,
that an acknowledgement outlives the board that took it, and what an extension publishes. The page's side is in
test_console_browser.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.site_fixtures import tiny_site
from wsnav.console import operator_commands as commands
from wsnav.console.alerts import EXPIRING_S, AckStore, AlertBoard
from wsnav.console.operator_commands import CommandError
from wsnav.console.site_view import SiteView
from wsnav.navigation.behaviors.right_of_way import yield_reason
from wsnav.navigation.costmap.layers import OtherRobot
from wsnav.schemas import topics
from wsnav.schemas.messages import OPERATOR_CANCEL_REASON, NodeStatus, OperatorBlock, RobotStatus
from wsnav.schemas.site import Site, load_site


@pytest.fixture
def site(tmp_path: Path) -> Site:
    return load_site(tiny_site(tmp_path / "tiny"))


class Console:
    """A SiteView and an AlertBoard fed as the console's bus thread feeds them."""

    def __init__(self, site: Site, acks: AckStore | None = None) -> None:
        self.view = SiteView(site)
        self.board = AlertBoard(acks)

    def feed(self, topic: str, payload: bytes, at: float, retained: bool = False) -> list[dict[str, object]]:
        self.view.apply(topic, payload, at, retained)
        happened, self.view.events = self.view.events, []
        self.board.on_events(happened, self.view)
        self.board.on_clock(self.view, at)
        return self.board.entries()

    def node(self, word: str, at: float, retained: bool = False) -> list[dict[str, object]]:
        payload = NodeStatus(node="n1", status=word).to_payload()  # type: ignore[arg-type]
        return self.feed(topics.node_status("tiny", "n1"), payload, at, retained)

    def robot(self, state: str, at: float, reason: str | None = None) -> list[dict[str, object]]:
        status = RobotStatus(robot="robot1", state=state, pose=(1.0, 1.0, 0.0), reason=reason)  # type: ignore[arg-type]
        return self.feed(topics.robot_status("tiny", "robot1"), status.to_payload(), at)


def test_a_node_offline_is_an_alert_kept_acknowledged_by_the_store_and_raised_anew(
    site: Site, tmp_path: Path
) -> None:
    db = tmp_path / "state" / "events-tiny.sqlite"
    console = Console(site, AckStore(db, 0.0))
    assert console.node("online", 10.0, retained=True) == []
    assert console.node("offline", 11.0, retained=True) == [], "a broker's replay raised an alert"
    console.node("online", 12.0)
    [alert] = console.node("offline", 20.0)
    assert alert["kind"] == "node_offline" and alert["subject"] == "n1" and not alert["acknowledged"]
    assert not console.board.acknowledge("no-such-alert", 21.0)
    assert console.board.acknowledge(str(alert["id"]), 21.0)
    # Another console on the same file that saw the same occurrence (a page of a restarted console) knows the ack.
    again = Console(site, AckStore(db, 30.0))
    again.node("online", 12.0)
    assert again.node("offline", 20.0) == [{**alert, "acknowledged": True}]
    assert console.node("online", 25.0) == [], "the alert outlived its condition"
    [anew] = console.node("offline", 40.0)
    assert anew["id"] != alert["id"] and not anew["acknowledged"]


def test_a_robot_stuck_or_giving_up_is_an_alert_an_operators_cancel_is_not(site: Site) -> None:
    console = Console(site)
    console.robot("navigating", 1.0)
    [stuck] = console.robot("waiting", 2.0, "no way to the goal")
    assert stuck["kind"] == "robot_stuck"
    assert console.robot("waiting", 3.0, "no way to the goal, still") == [stuck], "it still waits"
    assert console.robot("navigating", 4.0) == []
    assert console.robot("cancelled", 5.0, OPERATOR_CANCEL_REASON) == []
    # a new goal in a blocked zone: cancelled again, by the robot this time (the state word did not change)
    [aborted] = console.robot("cancelled", 6.0, "z1")
    assert aborted["kind"] == "robot_aborted" and "z1" in str(aborted["text"])
    assert console.robot("navigating", 7.0) == []


def test_a_robot_giving_way_to_another_robot_is_not_stuck_until_it_finds_no_way_on(site: Site) -> None:
    """A fleet robot waits on purpose while a robot with right of way passes (its status says so): the "robot
    stuck" alert fired on every such wait. The reason is the agent's own text (`yield_reason`)."""
    console = Console(site)
    gives_way = yield_reason(OtherRobot("robot2", (2.0, 1.0, 3.14), 0.2, "navigating", 0, 10.0))
    console.robot("navigating", 1.0)
    assert console.robot("waiting", 2.0, gives_way) == [], "giving way raised a 'stuck' alert"
    assert console.robot("waiting", 3.0, gives_way) == []
    # released, then no way on while still waiting: stuck now, though the state word did not change
    [stuck] = console.robot("waiting", 4.0, "no way to the goal")
    assert stuck["kind"] == "robot_stuck"
    assert console.robot("waiting", 5.0, gives_way) == [], "the alert outlived its cause"
    assert console.robot("navigating", 6.0) == []


def test_a_block_near_its_expiry_is_an_alert_that_an_extension_ends(site: Site) -> None:
    console = Console(site)
    _, pub = commands.block(site, now=100.0, duration_s=EXPIRING_S + 30, zone="z1", reason="spill")
    block_id = topics.parse(pub.topic).block_id  # type: ignore[union-attr]
    assert console.feed(pub.topic, pub.payload, 100.0) == []
    console.board.on_clock(console.view, 131.0)
    [expiring] = console.board.entries()
    assert expiring["kind"] == "block_expiring" and expiring["until"] == pytest.approx(190.0)
    current = console.view.blocks[str(block_id)].block
    extended = commands.extend(site, str(block_id), current, now=131.0, by_s=600)
    assert extended.topic == pub.topic and extended.retain and extended.payload
    sent = json.loads(extended.payload)
    assert sent["expires_at"] == pytest.approx(790.0) and sent["zone"] == "z1" and sent["reason"] == "spill"
    assert console.feed(extended.topic, extended.payload, 132.0) == []
    assert [b.block.expires_at for b in console.view.blocks.values()] == [790.0]


def test_an_extension_is_logged_as_one_not_as_a_new_block(site: Site) -> None:
    view = SiteView(site)
    _, pub = commands.block(site, now=0.0, duration_s=60, zone="z2", block_id="b1")
    view.apply(pub.topic, pub.payload, 0.0)
    block = view.blocks["b1"].block
    later = commands.extend(site, "b1", block, now=10.0, by_s=120)
    view.apply(later.topic, later.payload, 10.0)
    assert [(e.kind, e.text) for e in view.events] == [
        ("block_set", "block b1 set: zone z2"),
        ("block_extended", "block b1 extended: zone z2, 170 s left"),
    ]


def test_what_an_extension_refuses(site: Site) -> None:
    forever = OperatorBlock(zone="z1")
    with pytest.raises(CommandError, match="until lifted"):
        commands.extend(site, "b1", forever, now=0.0, by_s=60)
    soon = OperatorBlock(zone="z1", expires_at=100.0)
    for by_s in (0.0, -5.0, 8 * 86400.0):
        with pytest.raises(CommandError, match="at most 7 days"):
            commands.extend(site, "b1", soon, now=0.0, by_s=by_s)
    far = OperatorBlock(zone="z1", expires_at=6.5 * 86400)
    with pytest.raises(CommandError, match="at most 7 days from now"):
        commands.extend(site, "b1", far, now=0.0, by_s=86400)
    with pytest.raises(CommandError, match="not a valid block id"):
        commands.extend(site, "a/b", soon, now=0.0, by_s=60)
    # an expired block still shown is extended from now, not from its past expiry
    late = commands.extend(site, "b1", soon, now=500.0, by_s=60)
    assert json.loads(late.payload)["expires_at"] == pytest.approx(560.0)


def test_an_acknowledgement_the_disk_refuses_holds_in_memory_and_stops_nothing(
    site: Site, tmp_path: Path
) -> None:
    """A store that fails (here: its connection closed under it, standing in for a full or vanished disk) must not
    stop the bus thread that raises alerts, nor fail the page's request."""
    store = AckStore(tmp_path / "events-tiny.sqlite", 0.0)
    console = Console(site, store)
    console.node("online", 1.0)
    store.close()
    [alert] = console.node("offline", 2.0)
    assert console.board.acknowledge(str(alert["id"]), 3.0)
    assert console.board.entries()[0]["acknowledged"] is True
