"""The experiment report: confidence intervals as a statistician computes them, failed runs counted (time at
the cap, a censored value; distance and CPU over the runs that arrived), paired differences between
configurations, three significant figures, and the report written with its charts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.conftest import SITES
from wsnav.experiments.report import (
    TIME_CAP_S,
    markdown_table,
    mean_ci,
    paired_differences,
    sig3,
    summarise,
    verdicts,
    write_report,
)
from wsnav.experiments.run_plan import plan_runs
from wsnav.schemas.site import load_site


def test_mean_ci_is_student_t() -> None:
    mean, low, high = mean_ci([1.0, 2.0, 3.0])
    assert mean == 2.0
    assert high - mean == pytest.approx(4.302653 / np.sqrt(3), rel=1e-5)
    assert mean - low == pytest.approx(high - mean)
    assert mean_ci([5.0]) == (5.0, 5.0, 5.0)


def table() -> pd.DataFrame:
    rows = []
    for config, dist in (("default", 50.0), ("full", 31.0)):
        for i in range(4):
            rows.append(
                {
                    "config": config,
                    "route": "A->B",
                    "blocked": "z4",
                    "run": i,
                    "success": not (config == "default" and i == 3),
                    "collisions": 0,
                    "time_s": dist / 0.2 + i,
                    "distance_m": 1000.0 if (config == "default" and i == 3) else dist + i,
                    "replans": 3,
                    "agent_cpu_s": 2.0 if config == "default" else 0.5,
                }
            )
    return pd.DataFrame(rows)


def test_a_failed_run_counts_at_the_cap_in_time_and_is_left_out_of_distance(tmp_path: Path) -> None:
    summary = summarise(table()).set_index("config")
    assert summary.loc["default", "runs"] == 4
    assert summary.loc["default", "success"] == 3
    assert summary.loc["default", "distance_m_mean"] == pytest.approx(51.0)  # the 1000 m failure is out
    assert summary.loc["default", "time_s_mean"] == pytest.approx((250 + 251 + 252 + TIME_CAP_S) / 4)
    assert summary.loc["full", "distance_m_mean"] == pytest.approx(32.5)
    assert summary.loc["full", "cpu_per_sim_s_mean"] < summary.loc["default", "cpu_per_sim_s_mean"]
    text = markdown_table(summarise(table()))
    assert "| A->B | default | 4 | 3 | 75.0% | 0 |" in text


def test_every_number_has_three_significant_figures() -> None:
    assert [sig3(x) for x in (0.0151, 0.01462, 0.006699, 2.0, 361.74, 1234.5, 99.96, -0.000886)] == [
        "0.0151",
        "0.0146",
        "0.00670",
        "2.00",
        "362",
        "1230",
        "100",
        "-0.000886",
    ]
    rows = table()
    rows["agent_cpu_s"] = np.where(rows["config"] == "full", 0.0151 * rows["time_s"], 2.0)
    text = markdown_table(summarise(rows))
    assert "| 0.0151 [0.0151, 0.0151] |" in text, "the CPU column keeps its figures"


def test_paired_differences_compare_run_i_with_run_i_and_count_failures_at_the_cap() -> None:
    diff = paired_differences(table(), "default", "full").set_index("group")
    assert diff.loc["A->B", "pairs"] == 4 and diff.loc["A->B", "both_arrived"] == 3
    # full's time is default's minus 95 s in runs 0-2; run 3 failed under default, so it counts at the cap.
    expected = np.array([-95.0, -95.0, -95.0, 155.0 + 3 - TIME_CAP_S])
    assert diff.loc["A->B", "time_s_diff"] == pytest.approx(expected.mean())
    assert diff.loc["A->B", "distance_m_diff"] == pytest.approx(-19.0), "over the pairs where both arrived"
    assert diff.loc["A->B", "distance_m_ci_low"] == pytest.approx(-19.0)


def test_a_three_configuration_report_attributes_each_step_and_lists_what_differs_from_stock(
    tmp_path: Path,
) -> None:
    rows = table()
    zones = rows[rows["config"] == "full"].assign(config="zones", agent_cpu_s=1.0)
    body = write_report(pd.concat([rows, zones]), tmp_path, "# test").read_text()
    assert "### default -> zones: the sensor network (zone layer + Algorithm 3)" in body
    assert "### zones -> full: event-driven replanning + coarser planning" in body
    assert "Regulated Pure Pursuit" in body and "NavFn" in body and "+inf" in body
    assert "censored" in body


def test_report_has_table_and_the_three_charts(tmp_path: Path) -> None:
    report = write_report(table(), tmp_path, "# test")
    body = report.read_text()
    for name in ("distance_m.png", "time_s.png", "cpu_per_sim_s.png", "distance_m_by_zone.png"):
        assert f"]({name})" in body
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_run_plan_pairs_configurations_and_follows_the_seed() -> None:
    spec = load_site(SITES / "school").spec
    runs = plan_runs(spec, ["default", "full"], runs=20, seed=7)
    assert len(runs) == 2 * 3 * 20
    by_key = {(r.config, r.route, r.run): r for r in runs}
    for r in runs:
        twin = by_key[("full" if r.config == "default" else "default", r.route, r.run)]
        assert (twin.blocked, twin.seed) == (r.blocked, r.seed)
    ab = {r.blocked for r in runs if r.route == "A->B"}
    assert ab == {("z1",), ("z4",)}  # both raffle outcomes occur in 20 runs
    assert plan_runs(spec, ["default", "full"], runs=20, seed=7) == runs
    fewer = plan_runs(spec, ["default", "full"], runs=5, seed=7)
    assert fewer == [r for r in runs if r.run < 5], "fewer runs are the first runs of more"
    assert plan_runs(spec, ["default", "full"], runs=20, seed=8) != runs


def test_verdicts_say_where_full_wins_with_intervals_apart_per_blocked_zone() -> None:
    """A zone that forces a long detour on the stock robot shows a clear win; a zone both see late does not."""
    rows = []
    for i in range(6):
        for config, far, near in (("default", 80.0, 40.0), ("full", 50.0, 40.5)):
            for zone, dist in (("z4", far), ("z1", near)):
                rows.append(
                    {
                        "config": config,
                        "route": "A->B",
                        "blocked": zone,
                        "run": i,
                        "success": True,
                        "collisions": 0,
                        "time_s": dist * 5 + (i % 3) * 4,
                        "distance_m": dist + (i % 3),
                        "replans": 1,
                        "agent_cpu_s": (0.5 if config == "full" else 4.0) + 0.01 * i,
                    }
                )
    t = pd.DataFrame(rows)
    by_zone = verdicts(summarise(t, ("route", "blocked"))).set_index("group")
    assert by_zone.loc["A->B z4", "distance_m"] == "lower, CIs apart"
    assert by_zone.loc["A->B z4", "time_s"] == "lower, CIs apart"
    assert by_zone.loc["A->B z1", "distance_m"] == "not lower"
    assert by_zone.loc["A->B z1", "cpu_per_sim_s"] == "lower, CIs apart"
    by_route = verdicts(summarise(t)).set_index("group")
    assert by_route.loc["A->B", "distance_m"] in ("lower, CIs apart", "lower, CIs overlap")
    assert "| A->B | z4 | full | 6 | 6 | 100% | 0 |" in markdown_table(
        summarise(t, ("route", "blocked")), ("route", "blocked")
    )
