"""`wsnav experiment --backend ros`: the experiment's plan on ROS 1 navigation, against a real roscore (the
experiment starts its own), real rospy and actionlib, `wsnav sim --ros --clock` and `wsnav ros bridge`.

move_base is not packaged for Debian, so CI runs it on the ROS tests' move_base stand-in, as a process
(tests/move_base_standin.py: the real actionlib server of tests/test_ros_bridge_move_base.py, driving a straight
line). What the stand-in leaves out (navfn, DWA, the costmaps, recoveries) is not tested here: these tests check
that the backend runs the plan's runs on whatever move_base it is given, drives the robot in simulated time,
measures the navigation process and reports which backend it was.
"""

from __future__ import annotations

import contextlib
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import psutil
import yaml

from tests.conftest import REPO, SITES
from tests.ros_fixtures import require_ros
from wsnav.experiments.report import read_runs, write_report
from wsnav.ros_bridge.costmap_params import check_global_costmap
from wsnav.ros_experiment import move_base_params

STANDIN = f"{sys.executable} -m tests.move_base_standin"
ROUTE_M = 1.0


def wsnav(*args: str | Path, timeout: float = 170) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "wsnav.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO,
    )


def short_route_school(directory: Path) -> Path:
    """The school with one route of ROUTE_M metres along the south corridor (A east to S), raffling z5, a zone
    far from it: the obstacle is placed and the nodes report it, and the robot's way stays straight."""
    site_dir = directory / "school"
    shutil.copytree(SITES / "school", site_dir)
    spec = yaml.safe_load((site_dir / "site.yaml").read_text())
    x, y, _ = spec["points"]["A"]
    spec["points"]["S"] = [x + ROUTE_M, y, 0.0]
    spec["routes"] = [{"from": "A", "to": "S", "raffle": [["z5"]]}]
    (site_dir / "site.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
    return site_dir


def test_each_configuration_gets_robotis_parameters_with_its_own_numbers() -> None:
    """`default` is ROBOTIS' stock Burger set without the zone layer; `full` the paper's reduced set (no periodic
    replanning, 5 Hz global costmap, 2 m local costmap at 5 Hz) with a zone layer the bridge accepts."""
    default, zones, full = (move_base_params(c) for c in ("default", "zones", "full"))
    assert check_global_costmap(default["global_costmap"], "/wsn/zone_grid").zone_layer is None
    for params in (zones, full):
        check = check_global_costmap(params["global_costmap"], "/wsn/zone_grid")
        assert check.errors == [] and check.zone_layer == "wsn_zone_layer"
    rates = [
        (
            p["planner_frequency"],
            p["global_costmap"]["update_frequency"],
            p["local_costmap"]["width"],
            p["local_costmap"]["update_frequency"],
        )
        for p in (default, zones, full)
    ]
    assert rates == [(5.0, 10.0, 3.0, 10.0), (5.0, 10.0, 3.0, 10.0), (0.0, 5.0, 2.0, 5.0)]
    assert default["base_local_planner"] == "dwa_local_planner/DWAPlannerROS"
    assert default["DWAPlannerROS"]["max_vel_x"] == 0.22


def test_without_move_base_the_ros_backend_says_so_in_one_line(tmp_path: Path) -> None:
    """Here, as on CI, nothing provides move_base (Debian does not package it): the default command is missing."""
    done = wsnav("experiment", "--backend", "ros", "--runs", "1", "--out", tmp_path / "out")
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "move_base is not installed" in lines[0], done.stderr
    assert not (tmp_path / "out" / "runs.csv").exists()


def test_each_configuration_drives_the_route_on_the_move_base_it_is_given(tmp_path: Path) -> None:
    require_ros()
    site = short_route_school(tmp_path)
    out = tmp_path / "out"
    done = wsnav(
        "experiment",
        "--backend",
        "ros",
        "--move-base-cmd",
        STANDIN,
        "--site",
        site,
        "--runs",
        "1",
        "--out",
        out,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    table, header = read_runs(out)
    assert sorted(table["config"]) == ["default", "full", "zones"]
    col = {c: table[c].to_numpy() for c in table.columns}
    shown = table.to_string()
    assert (col["outcome"] == "arrived").all(), shown
    assert (col["blocked"] == "z5").all(), shown
    # Driven by the stand-in over /cmd_vel, measured by the simulated robot: the route's length, in the
    # simulated time /clock gave, never faster than the Burger's 0.22 m/s.
    distance, time_s = col["distance_m"].astype(float), col["time_s"].astype(float)
    assert ((distance > ROUTE_M - 0.2) & (distance < ROUTE_M + 0.5)).all(), shown
    assert ((time_s >= distance / 0.22) & (time_s < 60)).all(), shown
    assert (col["collisions"] == 0).all(), shown
    # Replans counted from the plans the stand-in published (at its planner_frequency: 5 Hz in default and
    # zones, none in full); recoveries missing, since it publishes no /move_base/recovery_status: never a 0.
    replans = dict(zip(col["config"], col["replans"].astype(float), strict=True))
    for config in ("default", "zones"):
        seconds = float(table.loc[table["config"] == config, "time_s"].iloc[0])
        assert 0.5 * 5.0 * seconds < replans[config] < 1.5 * 5.0 * seconds + 2, shown
    assert replans["full"] < 3, shown  # only re-sent goals are planned again
    assert bool(table["recoveries"].isna().all()) and bool(table["agent_cpu_s"].isna().all()), shown
    assert (col["process_cpu_s"].astype(float) > 0).all(), shown
    assert (col["peak_mem_mb"].astype(float) > 10).all(), shown
    assert "- Backend: ROS 1: move_base" in header
    report = (out / "report.md").read_text()
    assert "move_base's process CPU" in report
    assert "agent-step CPU" not in report.split("## By route")[1], "a column no run measured has no figure"
    row = next(line for line in report.splitlines() if line.startswith("| A->S | default |"))
    assert row.split(" | ")[10] == "n/a", row  # recoveries: not measured

    # The same plan from the other backend: the report compares them run by run.
    other = table.copy()
    other.loc[other["config"] == "default", "outcome"] = "aborted"
    other["distance_m"] = other["distance_m"] + 1.0
    sim_header = header.replace("- Backend: ROS 1: move_base", "- Backend: simulated")
    write_report(table, out, header, (), (other, sim_header))
    compared = (out / "report.md").read_text()
    assert "## Backends compared run by run: ros (this report) and sim" in compared
    row = next(line for line in compared.splitlines() if line.startswith("| default | A->S | 0 |"))
    assert "| arrived | aborted |" in row
    unrelated = pd.DataFrame(other.assign(seed=other["seed"] + 1))
    done = wsnav(
        "experiment", "--report-only", "--out", out, "--compare", _written(tmp_path, unrelated, header)
    )
    assert done.returncode == 2 and "share no run" in done.stderr, done.stderr


def _written(tmp_path: Path, table: pd.DataFrame, header: str) -> Path:
    folder = tmp_path / "other"
    folder.mkdir()
    table.to_csv(folder / "runs.csv", index=False)
    (folder / "header.md").write_text(header)
    return folder


def test_a_terminated_experiment_leaves_no_roscore_simulator_or_move_base_behind(tmp_path: Path) -> None:
    """`kill` (or systemd, or a CI timeout) on a running experiment: roscore, the simulated robot, the bridge and
    move_base each run in a session of their own, so they outlived the experiment before; now they go with it."""
    require_ros()
    site = short_route_school(tmp_path)
    proc = subprocess.Popen(
        [sys.executable, "-m", "wsnav.cli", "experiment", "--backend", "ros", "--move-base-cmd", STANDIN,
         "--site", str(site), "--runs", "1", "--out", str(tmp_path / "out")],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    experiment = psutil.Process(proc.pid)
    deadline = time.monotonic() + 120
    started: list[psutil.Process] = []
    while not any("move_base_standin" in " ".join(p.cmdline()) for p in started):
        assert proc.poll() is None and time.monotonic() < deadline, "move_base never started"
        time.sleep(0.5)
        with contextlib.suppress(psutil.Error):
            started = experiment.children(recursive=True)
    proc.terminate()
    assert proc.wait(timeout=60) != 0
    assert "Traceback" not in (proc.stderr.read() if proc.stderr else "")
    _, alive = psutil.wait_procs(started, timeout=20)
    left: list[str] = []
    for p in alive:
        with contextlib.suppress(psutil.Error):
            left.append(" ".join(p.cmdline()))
            p.kill()  # not left to the next test
    assert not left, f"left behind: {left}"
