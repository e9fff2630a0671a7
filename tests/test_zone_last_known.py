"""The last known zone states kept on disk (zones/last_known.py): a reader restarted with the broker down serves
them under the site's stale policy instead of every zone free, and a retained copy of a state it already knew
(a stopped node's last word) keeps its true age instead of looking fresh at every start."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import SCHOOL
from tests.robot_agent_rig import connect
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.runtime.bus import Message
from wsnav.runtime.cli_support import CliError
from wsnav.schemas import topics
from wsnav.schemas.messages import NodeStatus, ZoneState
from wsnav.schemas.site import Site
from wsnav.schemas.site_file import SiteFile, ZonePolicy
from wsnav.zones.cost_values import FREE_SPACE, LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import GridFrame
from wsnav.zones.intake import ZoneIntake
from wsnav.zones.last_known import LastKnownZones
from wsnav.zones.zone_rule import ZoneRule

T0 = 1_800_000_000.0
"""Unix time of the first run; the layer's clock is Unix time too (WallClock), as in the agent and bridges."""


class FakeUnixTime:
    """The store's time source, moved by hand (what `time.time()` would say)."""

    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def reader(
    spec: SiteFile, path: Path | None, now: float, policy: str = "keep"
) -> tuple[ZoneIntake, ZoneRule]:
    """A zone reader as the agent and the bridges build one, started at `now`."""
    spec = spec.model_copy(update={"policy": ZonePolicy(stale=policy)})  # type: ignore[arg-type]
    site_frame = GridFrame(400, 200, 0.05, 0.0, 0.0)
    layer = ZoneRule(spec, site_frame)
    memory = None if path is None else LastKnownZones(path, spec, unix_time=FakeUnixTime(now))
    intake = ZoneIntake(spec, layer, memory=memory)
    intake.restore(now)
    layer.refresh(now)
    return intake, layer


def state_message(
    spec: SiteFile, zone: str, node: str, state: str, seq: int, at: float, retain: bool
) -> Message:
    payload = ZoneState(zone=zone, node=node, state=state, seq=seq).to_payload()  # type: ignore[arg-type]
    return Message(topics.zone_state(spec.name, zone, node), payload, retain, at)


def status_message(spec: SiteFile, node: str, status: str, at: float, retain: bool) -> Message:
    payload = NodeStatus(node=node, status=status).to_payload()  # type: ignore[arg-type]
    return Message(topics.node_status(spec.name, node), payload, retain, at)


def first_run(spec: SiteFile, path: Path) -> None:
    """z4 reported blocked by its node n5 at T0, and the reader stopped."""
    intake, layer = reader(spec, path, T0)
    assert intake.handle(state_message(spec, "z4", "n5", "blocked", 41, T0, retain=False))
    assert layer.zone_costs()["z4"] == LETHAL_OBSTACLE
    assert intake.memory is not None
    intake.memory.flush()


@pytest.mark.parametrize(
    ("policy", "expected"),
    [("keep", LETHAL_OBSTACLE), ("unknown", NO_INFORMATION), ("lethal", LETHAL_OBSTACLE)],
)
def test_a_restart_with_the_broker_down_serves_the_last_states_under_the_stale_policy(
    school: Site, tmp_path: Path, policy: str, expected: int
) -> None:
    path = tmp_path / "zones-school.json"
    first_run(school.spec, path)
    later = T0 + 60.0  # a minute later: n5 (5 s heartbeat) is stale by then
    _, layer = reader(school.spec, path, later, policy)
    assert layer.zone_costs()["z4"] == expected
    _, without = reader(school.spec, None, later, policy)
    assert without.zone_costs()["z4"] == FREE_SPACE, "what a reader without the file serves: z4 free"


def test_a_restart_within_the_heartbeats_serves_the_state_as_fresh(school: Site, tmp_path: Path) -> None:
    path = tmp_path / "zones-school.json"
    first_run(school.spec, path)
    _, layer = reader(school.spec, path, T0 + 4.0, "unknown")
    assert layer.zone_costs()["z4"] == LETHAL_OBSTACLE
    layer.refresh(T0 + 16.0)  # 3 heartbeats of 5 s after it was heard, not after the restart
    assert layer.zone_costs()["z4"] == NO_INFORMATION


def test_the_retained_copy_of_a_known_state_does_not_make_a_silent_node_fresh(
    school: Site, tmp_path: Path
) -> None:
    path = tmp_path / "zones-school.json"
    first_run(school.spec, path)
    later = T0 + 60.0
    intake, layer = reader(school.spec, path, later, "unknown")
    # the broker is back and hands over what it kept of the stopped node: its birth and its last state
    intake.handle(status_message(school.spec, "n5", "online", later, retain=True))
    intake.handle(state_message(school.spec, "z4", "n5", "blocked", 41, later, retain=True))
    layer.refresh(later)
    assert layer.zone_costs()["z4"] == NO_INFORMATION, "the stopped node's retained word looked fresh"
    # without the file the same two retained messages make z4 blocked for three more heartbeats
    intake0, layer0 = reader(school.spec, None, later, "unknown")
    intake0.handle(status_message(school.spec, "n5", "online", later, retain=True))
    intake0.handle(state_message(school.spec, "z4", "n5", "blocked", 41, later, retain=True))
    assert layer0.zone_costs()["z4"] == LETHAL_OBSTACLE


def test_a_node_that_spoke_since_is_fresh_again(school: Site, tmp_path: Path) -> None:
    path = tmp_path / "zones-school.json"
    first_run(school.spec, path)
    later = T0 + 60.0
    intake, layer = reader(school.spec, path, later, "unknown")
    assert layer.zone_costs()["z4"] == NO_INFORMATION
    intake.handle(state_message(school.spec, "z4", "n5", "clear", 42, later, retain=True))  # a newer seq
    assert layer.zone_costs()["z4"] == FREE_SPACE
    # a reboot of the node (new random seq after its birth) is news too
    intake.handle(status_message(school.spec, "n5", "online", later + 1, retain=False))
    intake.handle(state_message(school.spec, "z4", "n5", "blocked", 7, later + 1, retain=False))
    assert layer.zone_costs()["z4"] == LETHAL_OBSTACLE
    assert json.loads(path.read_text())["nodes"]["n5"]["seq"] == 7


@pytest.mark.parametrize(
    "content",
    [
        "{not json",
        json.dumps({"format": 1, "site": "warehouse", "nodes": {}}),
        json.dumps({"format": 1, "site": "school", "nodes": {"n5": {"state": "blocked"}, "n9": 3}}),
        json.dumps({"format": 1, "site": "school", "nodes": {"zz": {"state": "blocked", "seq": 1,
                                                              "payload": "", "heard_unix": 0}}}),
    ],
)  # fmt: skip
def test_a_bad_or_foreign_file_is_one_warning_and_a_start_without_it(
    school: Site, tmp_path: Path, content: str, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "zones-school.json"
    path.write_text(content)
    intake, layer = reader(school.spec, path, T0)
    assert layer.zone_costs()["z4"] == FREE_SPACE
    assert len([r for r in caplog.records if r.levelname == "WARNING"]) <= 1
    intake.handle(state_message(school.spec, "z4", "n5", "blocked", 3, T0, retain=False))
    assert json.loads(path.read_text())["nodes"]["n5"]["state"] == "blocked"
    assert [p.name for p in tmp_path.iterdir()] == ["zones-school.json"], "a temporary file was left behind"


def test_a_state_dir_that_cannot_be_written_is_one_line(school: Site, tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(CliError, match=r"--state-dir .*file/state: Not a directory"):
        LastKnownZones.in_dir(blocker / "state", school.spec)


def test_heartbeats_are_written_at_most_once_per_interval_and_changes_at_once(
    school: Site, tmp_path: Path
) -> None:
    path = tmp_path / "zones-school.json"
    clock = FakeUnixTime(T0)
    memory = LastKnownZones(path, school.spec, unix_time=clock, write_interval_s=2.0)
    memory.accepted("n5", "clear", 1, b"{}")
    assert json.loads(path.read_text())["nodes"]["n5"]["seq"] == 1
    clock.t += 0.5
    memory.accepted("n5", "clear", 2, b"{}")  # a heartbeat: waits for the interval
    assert json.loads(path.read_text())["nodes"]["n5"]["seq"] == 1
    clock.t += 0.1
    memory.accepted("n5", "blocked", 3, b"{}")  # a change: at once
    assert json.loads(path.read_text())["nodes"]["n5"]["state"] == "blocked"


def test_the_robot_restarted_with_the_broker_down_keeps_a_zone_blocked_a_moment_before(
    tmp_path: Path,
) -> None:
    """Real processes: `wsnav robot --state-dir` sees z1 blocked through the broker; restarted with the broker
    gone, it still refuses a goal in z1 (the school keeps a stale node's last word), where it used to start with
    every zone free."""
    state_dir = tmp_path / "state"
    with BrokerThread(SCHOOL) as broker:
        node = connect(broker, "n1")
        state = ZoneState(zone="z1", node="n1", state="blocked", seq=7)
        node.publish(topics.zone_state("school", "z1", "n1"), state.to_payload(), qos=1, retain=True)
        node.close()
        address = f"{broker.host}:{broker.port}"
        creds = tmp_path / "robot1.json"  # kept: the broker's own go with it
        shutil.copy(broker.credentials_dir / "robot1.json", creds)
        args = ["robot", "--site", str(SCHOOL), "--broker", address, "--credentials", str(creds), "--sim"]
        args += ["--start", "A", "--goal", "18,7.2", "--exit-on-arrival", "--state-dir", str(state_dir)]
        first = subprocess.run(
            [sys.executable, "-m", "wsnav.cli", *args], capture_output=True, text=True, timeout=120
        )
        assert first.returncode == 1, first.stdout + first.stderr
    assert json.loads((state_dir / "zones-school.json").read_text())["nodes"]["n1"]["state"] == "blocked"
    again = subprocess.run(
        [sys.executable, "-m", "wsnav.cli", *args, "--connect-timeout", "1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert "unreachable: starting from the last known zone states" in again.stdout, (
        again.stdout + again.stderr
    )
    assert again.returncode == 1, again.stdout + again.stderr
    last = again.stdout.splitlines()[-1]
    assert " cancelled " in last and "z1" in last
