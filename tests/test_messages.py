"""The message contract: what nodes, robots and operators may say, and what is refused."""

from __future__ import annotations

import json

import pytest

from wsnav.schemas import topics
from wsnav.schemas.export import rendered, stale_files
from wsnav.schemas.messages import (
    MAX_COUNT,
    MAX_PAYLOAD_BYTES,
    NodeCommand,
    NodeInfo,
    NodeStatus,
    OperatorBlock,
    PayloadError,
    RobotGoal,
    RobotStatus,
    ZoneState,
    _Message,
    parse_payload,
)


def test_zone_state_round_trip_is_compact() -> None:
    msg = ZoneState(zone="z1", node="n1", state="blocked", seq=7)
    payload = msg.to_payload()
    assert json.loads(payload) == {"v": 1, "zone": "z1", "node": "n1", "state": "blocked", "seq": 7}
    assert parse_payload(ZoneState, payload) == msg


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"{not json", "ZoneState"),
        (b'{"v":1,"zone":"z1","node":"n1","state":"on fire","seq":1}', "state"),
        (b'{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":"one"}', "seq"),
        (b'{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":-1}', "seq"),
        (b'{"v":2,"zone":"z1","node":"n1","state":"blocked","seq":1}', "v"),
        (b'{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":1,"x":0}', "x"),
        (b'{"v":1,"zone":"z/1","node":"n1","state":"blocked","seq":1}', "zone"),
        (b"[]", "ZoneState"),
        (b" " * (MAX_PAYLOAD_BYTES + 1), "exceeds"),
    ],
)
def test_bad_zone_states_are_refused_with_a_reason(payload: bytes, reason: str) -> None:
    with pytest.raises(PayloadError) as err:
        parse_payload(ZoneState, payload)
    assert reason in str(err.value)
    assert "\n" not in str(err.value)


def test_goal_is_a_point_name_a_pose_or_a_cancel() -> None:
    assert parse_payload(RobotGoal, b'{"v":1,"goal":"B"}').goal == "B"
    assert parse_payload(RobotGoal, b'{"v":1,"goal":[1,2,0.5]}').goal == (1.0, 2.0, 0.5)
    assert parse_payload(RobotGoal, b'{"v":1,"cancel":true}').cancel
    for bad in (b'{"v":1}', b'{"v":1,"goal":"B","cancel":true}', b'{"v":1,"goal":[1,2]}'):
        with pytest.raises(PayloadError):
            parse_payload(RobotGoal, bad)


def test_operator_block_names_a_zone_or_a_polygon() -> None:
    block = parse_payload(OperatorBlock, b'{"v":1,"zone":"z4","expires_at":1700000000}')
    assert block.zone == "z4" and block.expires_at == 1.7e9
    assert parse_payload(OperatorBlock, b'{"v":1,"polygon":[[0,0],[1,0],[1,1]]}').polygon is not None
    for bad in (
        b'{"v":1}',
        b'{"v":1,"zone":"z4","polygon":[[0,0],[1,0],[1,1]]}',
        b'{"v":1,"polygon":[[0,0]]}',
    ):
        with pytest.raises(PayloadError):
            parse_payload(OperatorBlock, bad)


def test_status_messages() -> None:
    assert NodeStatus(node="n1", status="offline").to_payload() == b'{"v":1,"node":"n1","status":"offline"}'
    status = RobotStatus(robot="robot1", state="waiting", pose=(1.0, 2.0, 0.0), goal="B", reason="no path")
    assert parse_payload(RobotStatus, status.to_payload()) == status
    with pytest.raises(PayloadError):
        parse_payload(RobotStatus, b'{"v":1,"robot":"robot1","state":"dancing","pose":[0,0,0]}')


def test_node_commands() -> None:
    """A node parses these few bytes by hand (firmware/device/app.py): compact, `heartbeat_s` only where it
    belongs, bounded as the site file's heartbeat."""
    beat = NodeCommand(id=42, command="set_heartbeat", heartbeat_s=2)
    assert beat.to_payload() == b'{"v":1,"id":42,"command":"set_heartbeat","heartbeat_s":2.0}'
    assert NodeCommand(id=1, command="restart").to_payload() == b'{"v":1,"id":1,"command":"restart"}'
    assert parse_payload(NodeCommand, beat.to_payload()) == beat
    for bad, where in [
        (b'{"v":1,"id":1,"command":"set_heartbeat"}', "heartbeat_s goes with"),
        (b'{"v":1,"id":1,"command":"send_info","heartbeat_s":5}', "heartbeat_s goes with"),
        (b'{"v":1,"id":1,"command":"set_heartbeat","heartbeat_s":3601}', "heartbeat_s"),
        (b'{"v":1,"id":1,"command":"set_heartbeat","heartbeat_s":0}', "heartbeat_s"),
        (b'{"v":1,"id":0,"command":"restart"}', "id"),
        (b'{"v":1,"id":1073741824,"command":"restart"}', "id"),
        (b'{"v":1,"id":1,"command":"format_flash"}', "command"),
    ]:
        with pytest.raises(PayloadError, match=where):
            parse_payload(NodeCommand, bad)


def test_topics_round_trip() -> None:
    cases = {
        topics.zone_state("school", "z4", "n7"): ("zone_state", {"zone": "z4", "node": "n7"}),
        topics.node_status("school", "n7"): ("node_status", {"node": "n7"}),
        topics.node_command("school", "n7"): ("node_command", {"node": "n7"}),
        topics.robot_status("school", "robot1"): ("robot_status", {"robot": "robot1"}),
        topics.robot_goal("school", "robot1"): ("robot_goal", {"robot": "robot1"}),
        topics.operator_block("school", "spill-3"): ("operator_block", {"block_id": "spill-3"}),
        topics.sim_world("school"): ("sim_world", {}),
    }
    for name, (kind, fields) in cases.items():
        parsed = topics.parse(name)
        assert parsed is not None and parsed.kind == kind and parsed.site == "school", name
        for key, value in fields.items():
            assert getattr(parsed, key) == value
    assert topics.zone_state("school", "z4", "n7") == "wsn/school/zones/z4/state/n7"


@pytest.mark.parametrize(
    "name",
    [
        "wsn/school/zones/z4/state",
        "other/school/nodes/n1/status",
        "wsn/school/zones/+/state/n1",
        "wsn//x",
        "",
    ],
)
def test_foreign_topics_are_not_parsed(name: str) -> None:
    assert topics.parse(name) is None


def test_ids_with_topic_separators_are_refused() -> None:
    for bad in ("z/1", "z+", "#", "", "a" * 33):
        with pytest.raises(ValueError):
            topics.zone_state("school", bad, "n1")


def test_exported_json_schemas_are_up_to_date() -> None:
    assert stale_files() == [], "schemas/json is out of date: run 'make schemas'"


def test_duplicate_keys_are_refused_not_last_wins() -> None:
    """`"state"` twice would mean `blocked` to one parser and `clear` to another: refused in one line."""
    payload = b'{"v": 1, "zone": "z1", "node": "n1", "state": "clear", "state": "blocked", "seq": 1}'
    with pytest.raises(PayloadError, match="duplicate key 'state'"):
        parse_payload(ZoneState, payload)
    assert parse_payload(ZoneState, payload.replace(b'"state": "clear", ', b"")).state == "blocked"


HUGE = "9" * 900


@pytest.mark.parametrize(
    ("model", "fields"),
    [
        (NodeInfo, {"node": "n1", "fw": "1.0", "reset": "power_on", "uptime_s": 5, "reconnects": 0}),
        (
            NodeInfo,
            {"node": "n1", "fw": "1.0", "reset": "power_on", "uptime_s": 5, "reconnects": 0, "heap_free": 1},
        ),
        (
            NodeInfo,
            {
                "node": "n1",
                "fw": "1.0",
                "reset": "power_on",
                "uptime_s": 5,
                "reconnects": 0,
                "bad_commands": 0,
            },
        ),
        (RobotStatus, {"robot": "r1", "state": "idle", "pose": [0, 0, 0], "replans": 3}),
        (ZoneState, {"zone": "z1", "node": "n1", "state": "clear", "seq": 1}),
    ],
)
def test_a_900_digit_integer_is_refused_in_every_count(
    model: type[_Message], fields: dict[str, object]
) -> None:
    """900-digit `uptime_s` and `replans` passed the contract and reached the operator's page."""
    counts = [name for name, value in fields.items() if isinstance(value, int) and name != "v"]
    for name in counts:
        good = json.dumps({"v": 1, **fields, name: MAX_COUNT})
        assert getattr(parse_payload(model, good), name) == MAX_COUNT
        bad = json.dumps({"v": 1, **fields}).replace(f'"{name}": {fields[name]}', f'"{name}": {HUGE}')
        assert HUGE in bad
        with pytest.raises(PayloadError, match=name):
            parse_payload(model, bad)


def test_every_integer_in_the_contract_has_an_upper_bound() -> None:
    """Read from the exported JSON Schemas (what the firmware and other languages follow): a new unbounded
    integer field fails here."""
    unbounded: list[str] = []

    def walk(node: object, where: str) -> None:
        if isinstance(node, dict):
            if (
                node.get("type") == "integer"
                and not {"maximum", "exclusiveMaximum", "const", "enum"} & node.keys()
            ):
                unbounded.append(where)
            for key, value in node.items():
                walk(value, f"{where}/{key}")
        elif isinstance(node, list):
            for i, value in enumerate(node):
                walk(value, f"{where}/{i}")

    for name, text in rendered().items():
        walk(json.loads(text), name)
    assert unbounded == []
