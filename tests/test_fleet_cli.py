"""`wsnav fleet --sim` and `wsnav fleet-experiment` as a user runs them: every robot of the school on the embedded
broker, each with its own credentials and connection; bad arguments as one line."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from tests.cli_fixtures import error_line
from tests.conftest import SCHOOL
from tests.site_fixtures import tiny_site
from wsnav.cli import main


def test_fleet_runs_all_ten_robots_of_the_school_and_sends_the_goals_given(
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = ["fleet", "--sim", "--site", str(SCHOOL), "--duration", "10", "--speed", "0", "--every", "10"]
    assert main([*argv, "--goal", "robot1=A", "--goal", "robot3=C"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("10 robots of site school on 127.0.0.1:")
    rows = {line.split()[0]: line for line in out if line.startswith("  robot")}
    assert sorted(rows) == sorted(f"robot{i}" for i in range(1, 11))
    assert "navigating" in rows["robot1"] and "goal A" in rows["robot1"]
    assert "navigating" in rows["robot3"] and "goal C" in rows["robot3"]
    assert "idle" in rows["robot2"]
    assert out[-1] == "collisions: 0"


def test_fleet_refuses_bad_input_in_one_line(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    base = ["fleet", "--sim", "--site", str(SCHOOL), "--duration", "1"]
    assert "--goal 'robot11=A': expected ROBOT=POINT" in error_line(capsys, [*base, "--goal", "robot11=A"])
    assert "--goal 'robot1=Z'" in error_line(capsys, [*base, "--goal", "robot1=Z"])
    assert "robot1 has no start point" in error_line(
        capsys, ["fleet", "--sim", "--site", str(tiny_site(tmp_path))]
    )
    missing = error_line(capsys, [*base, "--broker", "127.0.0.1:1", "--credentials", str(tmp_path)])
    assert "--broker needs --credentials DIR with every robot's" in missing
    assert "no such agent config" in error_line(capsys, [*base, "--config", str(tmp_path / "x.yaml")])


def test_fleet_experiment_writes_its_table_report_and_trails(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    out = tmp_path / "fleet"
    argv = [
        "fleet-experiment",
        "--site",
        str(SCHOOL),
        "--minutes",
        "0.5",
        "--configs",
        "full",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    with (out / "fleet.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["robot"] for r in rows] == [f"robot{i}" for i in range(1, 11)]
    assert all(r["collisions"] == "0" for r in rows)
    assert all(float(r["distance_m"]) > 1.0 for r in rows)  # every robot was sent somewhere and drove
    assert (out / "trails.png").stat().st_size > 10_000
    report = (out / "report.md").read_text()
    assert "| full | 10 | 0 |" in report
    assert "wsnav fleet-experiment --site" in report
