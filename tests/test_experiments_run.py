"""The experiment end to end: one run per route and configuration through the real embedded broker (emulated
nodes with their own credentials, the agent on robot1's connection, a simulated TurtleBot3), its table, its
report, and the same table again for the same seed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.conftest import REPO, SCHOOL, require_tool
from wsnav.cli import main
from wsnav.experiments.run_plan import plan_runs
from wsnav.experiments.runner import run_experiment, write_outputs, write_run_pictures
from wsnav.experiments.single_run import COLUMNS, NONDETERMINISTIC, peak_rss_mb, reset_peak_rss
from wsnav.experiments.worker import run_with_own_broker
from wsnav.schemas.site import load_site


def test_one_run_per_route_and_config_arrives_without_collisions_and_repeats_with_the_seed(
    tmp_path: Path,
) -> None:
    site = load_site(SCHOOL)
    specs = plan_runs(site.spec, ["default", "full"], 1, 3)
    first = run_experiment(site.path, specs, workers=2)
    table = first.table
    assert list(table.columns) == list(COLUMNS)
    rows = table.to_dict("records")
    assert len(rows) == 6 and not table.isna().to_numpy().any()
    assert all(r["success"] for r in rows)
    assert sum(int(r["collisions"]) for r in rows) == 0
    by = {(str(r["route"]), str(r["config"])): r for r in rows}
    assert set(by) == {(r, c) for r in ("A->B", "B->C", "C->D") for c in ("default", "full")}
    for route in ("A->B", "B->C", "C->D"):
        full, default = by[(route, "full")], by[(route, "default")]
        # Paired: the same raffled zone under both configurations; default replans on a timer, full on events.
        assert full["blocked"] == default["blocked"] != "none"
        assert int(full["replans"]) < int(default["replans"])
    report = write_outputs(site, first, tmp_path / "out", "# test")
    for name in ("runs.csv", "summary.csv", "distance_m.png", "time_s.png", "cpu_per_sim_s.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0
    assert (tmp_path / "out" / "paths_A-B.png").stat().st_size > 0
    assert "| A->B | full | 1 | 1 | 100% [20.7, 100] | 0 | 0 | 0 |" in report.read_text()
    assert write_run_pictures(site, first, tmp_path / "pictures") == 6
    assert sorted(p.name for p in (tmp_path / "pictures").glob("*.png"))[:2] == [
        "default_A-B_run00.png",
        "default_B-C_run00.png",
    ]
    again = run_experiment(site.path, [s for s in specs if s.config == "full"], workers=1).table
    deterministic = [c for c in COLUMNS if c not in NONDETERMINISTIC]

    def same_seed_columns(t: pd.DataFrame) -> list[list[object]]:
        return [[r[c] for c in deterministic] for r in t.to_dict("records") if r["config"] == "full"]

    assert same_seed_columns(again) == same_seed_columns(table)
    xy = first.trajectories[("A->B", "full")]
    bx, by_, _ = site.point("B")
    assert np.hypot(xy[-1, 0] - bx, xy[-1, 1] - by_) < 0.3


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["experiment", "--runs", "0"], "--runs must be at least 1"),
        (
            ["experiment", "--runs", "1", "--configs", "default,fastest"],
            "--configs: fastest: no such agent config (built in: default, zones, full)",
        ),
        (["experiment", "--runs", "1", "--broker", "127.0.0.1:1"], "--broker needs --credentials"),
        (["experiment", "--site", "/nonexistent/site", "--runs", "1"], "/nonexistent/site"),
        (
            ["experiment", "--runs", "1", "--run-broker", "mosquitto", "--broker", "127.0.0.1:1883"],
            "--run-broker is the broker each run starts for itself: it does not go with --broker",
        ),
        (["experiment", "--report-only"], "no runs.csv to render the report from"),
    ],
)
def test_bad_experiment_arguments_are_one_line(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([*argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


@pytest.mark.parametrize(
    ("runs_csv", "message"),
    [
        (
            "config,route\ndefault,A->B\n",
            "not a runs table (no run, success, time_s, distance_m, blocked column)",
        ),
        (
            "config,route,blocked,run,success,time_s,distance_m\ndefault,A->B,z1,0,True,fast,50.0\n",
            "column time_s holds a value that is not a number",
        ),
        (
            "config,route,blocked,run,success,time_s,distance_m\ndefault,A->B,z1,0,maybe,1,2\n",
            "column success",
        ),
    ],
)
def test_a_report_from_a_broken_runs_table_is_one_line(
    runs_csv: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "runs.csv").write_text(runs_csv)
    (tmp_path / "header.md").write_text("# test\n")
    assert main(["experiment", "--report-only", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_a_run_on_its_own_mosquitto_gives_the_row_and_path_it_gives_on_amqtt() -> None:
    """The broker a run starts for itself carries the messages and nothing else: the robot drives the same."""
    require_tool("mosquitto")
    site = load_site(SCHOOL)
    spec = next(s for s in plan_runs(site.spec, ["full"], 1, 5) if s.route == "B->C")
    _, on_amqtt = run_with_own_broker(site, spec, "amqtt")
    _, on_mosquitto = run_with_own_broker(site, spec, "mosquitto")
    deterministic = [c for c in COLUMNS if c not in NONDETERMINISTIC]
    assert on_amqtt.row["success"] and on_amqtt.row["replans"] not in (0, None)
    assert [on_mosquitto.row[c] for c in deterministic] == [on_amqtt.row[c] for c in deterministic]
    assert np.array_equal(on_mosquitto.trajectory, on_amqtt.trajectory)


def test_a_recorded_run_keeps_every_pose_plan_zone_message_and_event_with_its_time_and_drives_the_same(
    tmp_path: Path,
) -> None:
    """The run's MCAP record: one pose per 50 ms step, the navigator's plans, the nodes' zone messages as the
    agent took them in (the blocked zone's first `blocked` report 0.5-2 s in, the moment `full` replans on
    it), the events, and the row; recording only reads, so the row is the unrecorded run's."""
    import json

    from mcap.reader import make_reader

    site = load_site(SCHOOL)
    spec = next(s for s in plan_runs(site.spec, ["full"], 1, 5) if s.route == "B->C")
    _, recorded = run_with_own_broker(site, spec, "amqtt", tmp_path)
    _, plain = run_with_own_broker(site, spec, "amqtt")
    deterministic = [c for c in COLUMNS if c not in NONDETERMINISTIC]
    assert [recorded.row[c] for c in deterministic] == [plain.row[c] for c in deterministic]
    (record,) = tmp_path.glob("*.mcap")
    assert record.name == "full_B-C_run00.mcap"
    by_topic: dict[str, list[tuple[float, dict[str, object]]]] = {}
    with record.open("rb") as f:
        reader = make_reader(f)
        for _, channel, message in reader.iter_messages():
            by_topic.setdefault(channel.topic, []).append((message.log_time / 1e9, json.loads(message.data)))
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    poses = by_topic["/robot/pose"]
    assert len(poses) == round(float(recorded.row["time_s"]) / 0.05)  # type: ignore[arg-type]
    last = poses[-1][1]["pose"]["position"]  # type: ignore[index]
    assert np.hypot(last["x"] - recorded.trajectory[-1, 0], last["y"] - recorded.trajectory[-1, 1]) < 1e-9  # type: ignore[index]
    zone = spec.blocked[0]
    first_blocked = min(
        t
        for t, m in by_topic["/agent/messages"]
        if f"/zones/{zone}/state/" in str(m["topic"]) and json.loads(str(m["payload"]))["state"] == "blocked"
    )
    assert 0.5 <= first_blocked <= 2.0 + 0.05
    replans = [(t, e) for t, e in by_topic["/navigator/events"] if e["kind"] == "replan"]
    assert [e["trigger"] for _, e in replans] == ["zone"] and replans[0][0] == pytest.approx(first_blocked)
    assert len(by_topic["/navigator/plan"]) >= 2
    assert [s["state"] for _, s in by_topic["/navigator/state"]][-1] == "arrived"
    assert meta["run"]["seed"] == str(spec.seed) and meta["result"]["outcome"] == "arrived"


def test_recording_into_a_folder_that_cannot_be_made_or_on_a_cluster_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("")
    assert (
        main(["experiment", "--runs", "1", "--record", str(blocked / "sub"), "--out", str(tmp_path / "o")])
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "cannot create output directory" in err and len(err.splitlines()) == 1
    assert (
        main(["experiment", "--runs", "1", "--record", str(tmp_path), "--scheduler", "tcp://127.0.0.1:1"])
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "--record writes on this machine's disk" in err and len(err.splitlines()) == 1


def test_each_run_measures_its_own_memory_peak_not_the_workers_lifetime_peak() -> None:
    block = np.ones(40_000_000)  # 320 MB held for a moment, as an earlier run in the same worker might
    lifetime = peak_rss_mb()
    del block
    reset_peak_rss()
    assert peak_rss_mb() < lifetime - 200


def test_an_earlier_runs_garbage_in_reference_cycles_is_not_counted_in_the_next_runs_memory() -> None:
    """A run's costmaps, plans and clients refer to each other: freed only by the cycle collector, which a
    worker may not have run by the time the next run starts (in the published experiment the peak grew with a
    worker's run order, 346 -> 712 MB). The next run's peak starts from what is really in use."""
    import gc

    class Run:
        def __init__(self) -> None:
            self.costmap = np.ones(40_000_000)  # 320 MB
            self.me = self  # a cycle: only the collector frees it

    gc.disable()  # the collector's thresholds not reached yet, as between two runs of a worker
    try:
        reset_peak_rss()
        before = peak_rss_mb()
        run = Run()
        del run
        reset_peak_rss()
        assert peak_rss_mb() < before + 100, "the earlier run's 320 MB are not this run's"
    finally:
        gc.enable()


def test_each_step_of_the_ablation_changes_only_what_the_report_attributes_to_it() -> None:
    """default -> zones: the sensor network only (zone layer, Algorithm 3's waiting instead of planner
    patience); zones -> full: event-driven replanning and coarser, less frequent work only (a smaller local
    costmap updated less often among it)."""
    from wsnav.robot_agent.agent_config import load_agent_config

    def settings(name: str) -> dict[str, object]:
        flat = load_agent_config(name).model_dump()
        flat.pop("name")
        for section in ("inflation", "planner", "recovery"):
            for key, value in flat.pop(section).items():
                flat[f"{section}.{key}"] = value
        return flat

    default, zones, full = settings("default"), settings("zones"), settings("full")
    # the zone layer: its switch and its place in the costmap's plugins list
    assert {k for k in default if default[k] != zones[k]} == {"plugins", "zone_layer", "recovery.on_no_path"}
    assert [p for p in zones["plugins"] if p not in default["plugins"]] == ["zone_layer"]  # type: ignore[union-attr]
    assert {k for k in zones if zones[k] != full[k]} == {
        "replan_rate_hz",
        "global_costmap_rate_hz",
        "local_costmap_size_m",
        "local_costmap_rate_hz",
        "planner.downsample",
    }
    assert default["recovery.enabled"] and zones["recovery.enabled"] and full["recovery.enabled"]


@pytest.mark.parametrize(("config", "route", "run"), [("default", "C->D", 1), ("full", "B->C", 3)])
def test_a_row_of_the_published_experiment_comes_out_again_to_the_digit(
    config: str, route: str, run: int
) -> None:
    """docs/experiment is what the code does: a change to what a run does must come with the experiment rerun
    (a `default` run that move_base's rules abort after its recoveries, and a `full` run)."""
    published = pd.read_csv(REPO / "docs" / "experiment" / "runs.csv", keep_default_na=False)
    row = published[
        (published["config"] == config) & (published["route"] == route) & (published["run"] == run)
    ]
    site = load_site(SCHOOL)
    spec = next(s for s in plan_runs(site.spec, [config], run + 1, 1) if s.route == route and s.run == run)
    _, result = run_with_own_broker(site, spec)
    fresh = pd.DataFrame([result.row], columns=list(COLUMNS)).astype(published.dtypes.to_dict())
    deterministic = [c for c in COLUMNS if c not in NONDETERMINISTIC]
    assert len(row) == 1
    assert {c: fresh.iloc[0][c] for c in deterministic} == {c: row.iloc[0][c] for c in deterministic}
