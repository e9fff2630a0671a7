"""The console's view of a site, from messages alone (no broker): what each zone shows and why, what is
dropped, and what the operator's requests turn into."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from tests.site_fixtures import tiny_site
from wsnav.console import operator_commands as commands
from wsnav.console.operator_commands import CommandError
from wsnav.console.site_view import TRAIL_POINTS, TRAIL_S, SiteView
from wsnav.console.terminal import render
from wsnav.schemas import topics
from wsnav.schemas.messages import (
    MAX_PAYLOAD_BYTES,
    ROBOT_PATH_POINTS,
    NodeInfo,
    NodeStatus,
    OperatorBlock,
    RobotStatus,
    ZoneState,
    ZoneStateValue,
    parse_payload,
)
from wsnav.schemas.site import Site, load_site
from wsnav.zones.geometry import GridFrame
from wsnav.zones.zone_rule import ZoneRule

HB = 5.0  # tiny_site's heartbeat; stale after 3 heartbeats


@pytest.fixture
def site(tmp_path: Path) -> Site:
    return load_site(tiny_site(tmp_path / "tiny"))


def zone_msg(node: str, zone: str, state: ZoneStateValue, seq: int = 1) -> tuple[str, bytes]:
    return topics.zone_state("tiny", zone, node), ZoneState(
        zone=zone, node=node, state=state, seq=seq
    ).to_payload()


def test_zone_states_follow_nodes_silence_wills_and_operator_blocks(site: Site) -> None:
    """tiny's policy is the default: any node blocked blocks, a stale or offline node's last word is kept."""
    view = SiteView(site)
    assert view.zone_states(0.0) == {"z1": "clear", "z2": "clear"}, "the robots take an unheard zone as clear"
    view.apply(*zone_msg("n1", "z1", "blocked"), 100.0)
    view.apply(*zone_msg("n2", "z2", "caution"), 100.0)
    assert view.zone_states(101.0) == {"z1": "blocked", "z2": "caution"}
    assert view.zone_states(100.0 + 3 * HB + 0.1) == {"z1": "blocked", "z2": "caution"}
    assert view.entry(("zone", "z1"), 100.0 + 3 * HB + 0.1)["stale_nodes"] == ["n1"]  # type: ignore[index]
    view.apply(topics.node_status("tiny", "n1"), NodeStatus(node="n1", status="offline").to_payload(), 116.0)
    assert view.zone_state("z1", 116.0) == "blocked", "an offline node's last word holds its zone under keep"
    assert view.entry(("zone", "z1"), 116.0)["stale_nodes"] == ["n1"]  # type: ignore[index]
    block = OperatorBlock(zone="z2", expires_at=125.0, reason="spill").to_payload()
    view.apply(*zone_msg("n2", "z2", "caution", seq=2), 117.0)
    assert view.apply(topics.operator_block("tiny", "b1"), block, 117.0) == {("block", "b1"), ("zone", "z2")}
    assert view.zone_state("z2", 118.0) == "blocked"
    assert view.entry(("block", "b1"), 118.0) == {
        "id": "b1", "zone": "z2", "polygon": None, "expires_at": 125.0, "left_s": 7.0, "reason": "spill",
    }  # fmt: skip
    assert view.expire(125.0) == {("block", "b1"), ("zone", "z2")}
    assert view.zone_state("z2", 125.0) == "caution"


def robots_view(tmp_path: Path, policy: dict[str, object], watchers: int) -> tuple[SiteView, ZoneRule]:
    """The console's view and a robot's zone layer on a site whose z1 is watched by `watchers` nodes."""
    nodes = [
        {"id": f"n{i}", "zone": "z1", "sensor": {"type": "pir", "pin": 5}} for i in range(1, watchers + 1)
    ]
    nodes.append({"id": "m", "zone": "z2", "sensor": {"type": "pir", "pin": 5}})
    s = load_site(tiny_site(tmp_path / "policy", nodes=nodes, policy=policy))
    return SiteView(s), ZoneRule(s.spec, GridFrame.of_grid(s.grid))


def test_majority_fusion_shows_what_the_robot_does_with_one_blocked_node_of_three(tmp_path: Path) -> None:
    """Under `fuse: majority` one node of three saying blocked is a caution to the robot: the console showed
    blocked while the robot drove through."""
    view, robot = robots_view(tmp_path, {"fuse": "majority"}, 3)
    for node, state in (("n1", "blocked"), ("n2", "clear"), ("n3", "clear")):
        topic, payload = zone_msg(node, "z1", state)  # type: ignore[arg-type]
        view.apply(topic, payload, 10.0)
        robot.on_zone_state(parse_payload(ZoneState, payload), 10.0)
    assert robot.blocked_zones() == []
    assert view.zone_state("z1", 11.0) == "caution"
    view.apply(*zone_msg("n2", "z1", "blocked", seq=2), 12.0)
    assert view.zone_state("z1", 12.5) == "blocked", "two of three is a majority"


def test_under_stale_keep_a_silent_nodes_last_blocked_word_still_shows_blocked(tmp_path: Path) -> None:
    """`stale: keep`: the robot keeps avoiding a zone whose node said blocked and fell silent; the console showed
    'stale' instead. It shows blocked, and names the silent node."""
    view, robot = robots_view(tmp_path, {"stale": "keep"}, 1)
    topic, payload = zone_msg("n1", "z1", "blocked")
    view.apply(topic, payload, 10.0)
    robot.on_zone_state(parse_payload(ZoneState, payload), 10.0)
    later = 10.0 + 10 * HB
    robot.refresh(later)
    assert robot.blocked_zones() == ["z1"]
    assert view.zone_state("z1", later) == "blocked"
    assert view.entry(("zone", "z1"), later)["stale_nodes"] == ["n1"]  # type: ignore[index]


def test_bad_messages_are_dropped_counted_and_change_nothing(site: Site) -> None:
    view = SiteView(site)
    view.apply(*zone_msg("n1", "z1", "clear"), 1.0)
    before = view.snapshot(2.0)
    bad = [
        (topics.zone_state("tiny", "z1", "n1"), b"{not json"),
        (topics.zone_state("tiny", "z1", "n1"), b"x" * 5000),
        (
            topics.zone_state("tiny", "z2", "n1"),
            ZoneState(zone="z2", node="n1", state="blocked", seq=2).to_payload(),
        ),
        (
            topics.zone_state("tiny", "z1", "ghost"),
            ZoneState(zone="z1", node="ghost", state="blocked", seq=2).to_payload(),
        ),
        (
            topics.robot_status("tiny", "robot1"),
            b'{"v": 1, "robot": "robot2", "state": "idle", "pose": [0, 0, 0]}',
        ),
        ("wsn/other/zones/z1/state/n1", b"{}"),
        ("wsn/tiny/nodes/n1/info", b"[1, 2]"),
        ("wsn/tiny/nodes/n1/info", b"x" * 4000),
    ]
    for topic, payload in bad:
        assert view.apply(topic, payload, 2.0) == set(), topic
    assert view.snapshot(2.0) == before
    assert sum(view.dropped.values()) == len(bad)


def test_node_diagnostics_are_shown_field_by_field(site: Site) -> None:
    view = SiteView(site)
    info = NodeInfo(
        node="n2", fw="0.2.0", reset="watchdog", uptime_s=3600, rssi=-71, heap_free=9100, reconnects=2,
        error="[Errno 113] EHOSTUNREACH",
    )  # fmt: skip
    assert view.apply(topics.node_info("tiny", "n2"), info.to_payload(), 5.0) == {("node", "n2")}
    shown = view.entry(("node", "n2"), 6.0)
    assert shown is not None and shown["info"] == {
        "fw": "0.2.0", "reset": "watchdog", "uptime_s": 3600, "rssi": -71, "heap_free": 9100, "reconnects": 2,
        "error": "[Errno 113] EHOSTUNREACH",
    }  # fmt: skip
    assert "reset=watchdog" in render(view.snapshot(6.0))
    view.apply(topics.node_info("tiny", "n2"), b"", 7.0)
    assert (view.entry(("node", "n2"), 7.0) or {})["info"] is None


def test_a_malformed_node_info_is_dropped_with_one_log_line(
    site: Site, caplog: pytest.LogCaptureFixture
) -> None:
    view = SiteView(site)
    good = NodeInfo(node="n1", fw="0.2.0", reset="power_on", uptime_s=5, reconnects=0).to_payload()
    view.apply(topics.node_info("tiny", "n1"), good, 1.0)
    bad = b'{"v":1,"node":"n1","fw":"0.2.0","reset":"gremlins","uptime_s":5,"reconnects":0}'
    with caplog.at_level(logging.WARNING, logger="wsnav.console.site_view"):
        for t in (2.0, 3.0, 4.0):  # a retained bad message comes back on every reconnect: logged once
            assert view.apply(topics.node_info("tiny", "n1"), bad, t) == set()
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "wsn/tiny/nodes/n1/info" in lines[0] and "reset" in lines[0], lines
    assert (view.entry(("node", "n1"), 5.0) or {})["info"] == {
        "fw": "0.2.0", "reset": "power_on", "uptime_s": 5, "reconnects": 0,
    }  # fmt: skip


def test_robot_trail_keeps_the_last_minutes(site: Site) -> None:
    view = SiteView(site)
    for i in range(0, 700, 2):
        status = RobotStatus(robot="robot1", state="navigating", pose=(i * 0.01, 1.0, 0.0), t=1000.0 + i)
        view.apply(topics.robot_status("tiny", "robot1"), status.to_payload(), 1000.0 + i)
    trail = view.robot_trail("robot1")
    assert trail[0][0] >= 1000.0 + 698 - 300 and trail[-1][1] == pytest.approx(6.98, abs=0.05)
    assert view.entry(("robot", "robot1"), 1000.0 + 699)["age_s"] == 1.0  # type: ignore[index]


def test_a_robot_credential_cannot_grow_its_trail_without_limit(site: Site) -> None:
    """20,000 statuses with a fixed `t` grew /api/state from 2.7 KB to 188 KB: the trail is aged by the console's
    own receipt time and capped in points."""
    import json

    view = SiteView(site)
    for i in range(20_000):
        status = RobotStatus(robot="robot1", state="navigating", pose=((i % 2) * 1.0, 1.0, 0.0), t=5.0)
        view.apply(topics.robot_status("tiny", "robot1"), status.to_payload(), 1000.0 + i * 0.01)
    assert len(view.robot_trail("robot1")) <= TRAIL_POINTS
    assert len(json.dumps(view.snapshot(1200.0))) < 40_000
    quiet = RobotStatus(robot="robot1", state="idle", pose=(3.0, 1.0, 0.0), t=5.0)
    view.apply(topics.robot_status("tiny", "robot1"), quiet.to_payload(), 1200.0 + TRAIL_S + 1)
    assert len(view.robot_trail("robot1")) == 1, "points older than TRAIL_S by the console's clock are gone"


def test_a_full_robot_status_with_its_path_fits_the_payload_limit() -> None:
    status = RobotStatus(
        robot="robot-with-a-long-name",
        state="navigating",
        pose=(-123.456, -123.456, -3.142),
        goal=(-123.456, -123.456, -3.142),
        blocked_zones=[f"zone-{i:03d}" for i in range(12)],
        replans=123456,
        plan_length_m=12345.678,
        reason="r" * 200,
        path=[(-123.45, -123.45)] * ROBOT_PATH_POINTS,
        t=1795473361.287,
    )
    assert len(status.to_payload()) <= MAX_PAYLOAD_BYTES
    assert parse_payload(RobotStatus, status.to_payload()) == status


def test_operator_requests_are_checked_against_the_site(site: Site) -> None:
    block_id, pub = commands.block(site, now=1000.0, duration_s=600, zone="z1", reason="wet floor")
    assert pub.retain and pub.topic == f"wsn/tiny/operator/blocks/{block_id}"
    assert parse_payload(OperatorBlock, pub.payload).expires_at == 1600.0
    assert commands.parse_duration("10m") == 600 and commands.parse_duration("2h") == 7200
    refused = {
        "unknown zone 'z9'": lambda: commands.block(site, now=0, duration_s=60, zone="z9"),
        "outside the map": lambda: commands.block(
            site, now=0, duration_s=60, polygon=[(0, 0), (50, 0), (1, 1)]
        ),
        "at most 7 days": lambda: commands.block(site, now=0, duration_s=1e9, zone="z1"),
        "unknown point 'C'": lambda: commands.goal(site, "robot1", "C"),
        "in a wall": lambda: commands.goal(site, "robot1", (0.01, 0.01, 0.0)),
        "unknown robot 'r2'": lambda: commands.cancel(site, "r2"),
        "not a duration": lambda: commands.parse_duration("soon"),
    }
    for words, call in refused.items():
        with pytest.raises(CommandError, match=words):
            call()
    assert commands.unblock(site, "b1").payload == b""


def test_numbers_no_json_can_carry_or_no_map_can_hold_are_refused_and_the_state_stays_valid_json(
    site: Site,
) -> None:
    """A retained status with NaN made GET /api/state answer 500 and the event stream emit invalid JSON; a
    goal of 1e308 (or a yaw of 1e308) from `wsnav goal` or the page raised instead of a one-line refusal."""
    import json

    view = SiteView(site)
    status = topics.robot_status("tiny", "robot1")
    for payload in (
        b'{"v":1,"robot":"robot1","state":"idle","pose":[0,0,0],"t":NaN}',
        b'{"v":1,"robot":"robot1","state":"idle","pose":[1.7e308,0,0]}',
        b'{"v":1,"robot":"robot1","state":"idle","pose":[1,1,Infinity]}',
    ):
        assert view.apply(status, payload, 1.0) == set()
    assert sum(view.dropped.values()) == 3
    json.dumps(view.snapshot(2.0), allow_nan=False)  # what the web app and `status --json` send
    for target, why in (
        ((1e308, 2.0, 0.0), "lies outside the map"),
        ((2.0, 2.0, 1e308), "expected radians"),
        ((float("nan"), 2.0, 0.0), "finite"),
    ):
        with pytest.raises(CommandError, match=why):
            commands.goal(site, "robot1", target)


def test_last_heard_counts_live_messages_only_not_the_brokers_replay(site: Site) -> None:
    """A node hung for minutes read "last heard 2 s" because the broker replayed its retained state to the
    console; after a broker restart every node read as heard just now. Age comes from live messages only, while
    the replayed word still shows what the node last said."""
    view = SiteView(site)
    topic, payload = zone_msg("n1", "z1", "blocked")
    view.apply(topic, payload, 500.0, retained=True)
    node = view.entry(("node", "n1"), 501.0)
    assert node is not None
    assert (node["state"], node["heard_at"], node["age_s"], node["fresh"]) == ("blocked", None, None, False)
    view.apply(*zone_msg("n1", "z1", "blocked", seq=2), 502.0)
    node = view.entry(("node", "n1"), 503.0)
    assert node is not None and (node["age_s"], node["fresh"]) == (1.0, True)


def test_events_come_from_live_messages_only(site: Site) -> None:
    """The event log's entries: blocks set, lifted and expired, a node offline and back, a robot arrived; a
    broker's replay of retained messages (console start, reconnect) is no event."""
    view = SiteView(site)
    block = OperatorBlock(zone="z1", expires_at=150.0, reason="spill").to_payload()
    view.apply(topics.operator_block("tiny", "old"), block, 99.0, retained=True)
    view.apply(
        topics.node_status("tiny", "n1"), NodeStatus(node="n1", status="online").to_payload(), 99.0, True
    )
    assert view.events == []
    view.apply(topics.operator_block("tiny", "b1"), block, 100.0)
    view.apply(topics.operator_block("tiny", "b1"), block, 100.5)  # the same again: no new event
    view.apply(topics.operator_block("tiny", "old"), b"", 101.0)
    view.apply(topics.node_status("tiny", "n1"), NodeStatus(node="n1", status="offline").to_payload(), 102.0)
    view.apply(topics.node_status("tiny", "n1"), NodeStatus(node="n1", status="online").to_payload(), 103.0)
    arrived = RobotStatus(robot="robot1", state="arrived", pose=(1.0, 1.0, 0.0), goal="A")
    view.apply(topics.robot_status("tiny", "robot1"), arrived.to_payload(), 104.0)
    view.apply(topics.robot_status("tiny", "robot1"), arrived.to_payload(), 104.5)
    view.expire(150.0)
    assert [(e.t, e.kind, e.subject) for e in view.events] == [
        (100.0, "block_set", "b1"),
        (101.0, "block_lifted", "old"),
        (102.0, "node_offline", "n1"),
        (103.0, "node_online", "n1"),
        (104.0, "robot_arrived", "robot1"),
        (150.0, "block_expired", "b1"),
    ]
    assert view.events[0].text == "block b1 set: zone z1 (spill)"


def test_watch_fits_an_80_by_24_terminal_keeping_the_header_and_outage_line(site: Site) -> None:
    """`wsnav watch` in 80x24 scrolled its header and the outage line away."""
    from wsnav.console.terminal import fit

    view = SiteView(site)
    snap = view.snapshot(10.0)
    snap["broker_connected"] = False
    long = render(snap) + "\n" + "\n".join(f"row {i} " + "x" * 120 for i in range(40))
    shown = fit(long, 24, 80).splitlines()
    assert len(shown) <= 23 and all(len(line) <= 80 for line in shown)
    assert shown[0].startswith("site tiny") and "not reachable" in shown[1]
    assert shown[-1].startswith("... ") and "more lines" in shown[-1]
    assert fit("a\nb", 24, 80) == "a\nb"
