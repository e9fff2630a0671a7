"""`wsnav zones` and scenario files: bad input is one line naming file, key and problem; a good run blocks the
zone for a robot listening on the real broker; the example scenarios load; raffles match the experiment's."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from tests.cli_fixtures import error_line
from tests.conftest import SITES
from tests.zone_sim_fixtures import SITE, sim_site, subscriber
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.cli import main
from wsnav.experiments.run_plan import plan_runs
from wsnav.runtime.clock import SimClock
from wsnav.schemas import topics
from wsnav.schemas.messages import SimWorld, ZoneState, parse_payload
from wsnav.schemas.site import load_site
from wsnav.zone_sim.raffle import draws
from wsnav.zone_sim.scenario import ScenarioError, load_scenario


@pytest.mark.parametrize(
    ("body", "expected"),
    [
        ("blocks:\n  - {zone: z9, from_s: 1}\n", r"scenario\.yaml: blocks\[0\]\.zone: unknown zone 'z9'"),
        (
            "blocks:\n  - {zone: z1, from_s: 5, to_s: 2}\n",
            r"scenario\.yaml: blocks\[0\]: to_s must be after from_s",
        ),
        (
            "blocks:\n  - {zone: z1, from_s: soon}\n",
            r"scenario\.yaml: blocks\[0\]\.from_s: Input should be a valid",
        ),
        ("raffles:\n  - {route: A->C, every_s: 5, count: 2}\n", r"raffles\[0\]\.route: unknown route 'A->C'"),
        (
            "raffles:\n  - {route: A->B, every_s: 5, hold_s: 9, count: 2}\n",
            r"raffles\[0\]: hold_s must not exceed",
        ),
        ("failures:\n  - {node: n7, at_s: 1, kind: kill}\n", r"failures\[0\]\.node: unknown node 'n7'"),
        ("failures:\n  - {node: n1, at_s: 1, kind: explode}\n", r"failures\[0\]\.kind: Input should be"),
        ("blockz: []\n", r"scenario\.yaml: blockz: Extra inputs are not permitted"),
        ("blocks: [\n", r"scenario\.yaml: not valid YAML"),
        ("- 1\n", r"scenario\.yaml: a scenario file must be a YAML mapping"),
    ],
)
def test_a_bad_scenario_file_is_one_line_naming_file_key_and_problem(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], body: str, expected: str
) -> None:
    site = sim_site(tmp_path / "site")
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(body)
    line = error_line(
        capsys,
        [
            "zones",
            "--site",
            str(site),
            "--broker",
            "127.0.0.1:1",
            "--credentials",
            str(tmp_path),
            "--scenario",
            str(scenario),
        ],
    )
    assert line.startswith(f"wsnav: error: {scenario}: ")
    assert re.search(expected, line), line


def test_bad_arguments_and_missing_credentials_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    site = str(sim_site(tmp_path / "site"))
    base = ["zones", "--site", site, "--broker", "127.0.0.1:1", "--credentials", str(tmp_path / "none")]
    assert "unknown zone 'z9'" in error_line(capsys, [*base, "--block", "z9"])
    assert "n1.json: missing" in error_line(capsys, [*base, "--block", "z1"])
    assert "--miss-rate" in error_line(capsys, [*base, "--block", "z1", "--miss-rate", "1.5"])
    assert "not allowed with argument" in error_line(capsys, [*base, "--block", "z1", "--scenario", "x.yaml"])


def test_zones_block_runs_the_nodes_and_a_robot_sees_the_zone_blocked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    site = sim_site(tmp_path / "site")
    with BrokerThread(site) as broker:
        robot = subscriber(broker, SimClock())
        argv = ["zones", "--site", str(site), "--broker", f"{broker.host}:{broker.port}"]
        argv += ["--credentials", str(broker.credentials_dir), "--block", "z1", "--duration", "2.5"]
        assert main(argv) == 0
        time.sleep(0.5)
        got = robot.poll()
        robot.close()
    out = capsys.readouterr().out
    assert "obstacle placed in z1" in out and "3 nodes" in out
    states = {(m.topic, parse_payload(ZoneState, m.payload).state) for m in got if "/zones/" in m.topic}
    assert (topics.zone_state(SITE, "z1", "n1"), "blocked") in states
    assert (topics.zone_state(SITE, "z2", "n2"), "blocked") not in states
    worlds = [
        parse_payload(SimWorld, m.payload, max_bytes=8192) for m in got if m.topic == topics.sim_world(SITE)
    ]
    assert [o.zone for o in worlds[0].obstacles] == ["z1"]
    assert worlds[-1].obstacles == []  # the world is emptied when the simulator stops


def test_the_example_scenarios_load_on_the_school_site() -> None:
    spec = load_site(SITES / "school").spec
    folder = SITES / "school" / "scenarios"
    loaded = {p.name: load_scenario(p, spec) for p in sorted(folder.glob("*.yaml"))}
    assert set(loaded) >= {"z4_blocked.yaml", "raffle.yaml", "node_failure.yaml"}
    z4 = loaded["z4_blocked.yaml"].timeline(spec, 0)
    assert [(e.t, e.kind, e.target) for e in z4] == [(5.0, "block", "z4"), (60.0, "clear", "z4")]
    with pytest.raises(ScenarioError, match=r"no such scenario file"):
        load_scenario(folder / "missing.yaml", spec)


def test_raffle_draws_are_the_experiments_blocked_zones_for_the_same_seed() -> None:
    spec = load_site(SITES / "school").spec
    runs = plan_runs(spec, ["full"], runs=20, seed=11)
    for route in ("A->B", "B->C", "C->D"):
        expected = [r.blocked for r in runs if r.route == route]
        assert draws(spec, route, seed=11, count=20) == expected
    assert draws(spec, "A->B", 11, 20) != draws(spec, "A->B", 12, 20)
