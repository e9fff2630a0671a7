"""The experiment report: confidence intervals as a statistician computes them, failed runs counted as failures
(a success rate with its Wilson interval; time, distance and CPU over the runs that arrived), paired differences
between configurations, three significant figures, the deviations from the paper, and the report written with
its charts and rendered again from its runs table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from matplotlib.colors import to_rgba
from matplotlib.container import BarContainer

from tests.conftest import SITES
from wsnav.experiments.report import (
    CONFIG_COLOURS,
    METRICS,
    bar_chart,
    markdown_table,
    mean_ci,
    paired_differences,
    rerender,
    sig3,
    summarise,
    verdicts,
    wilson,
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
                    "outcome": "aborted" if (config == "default" and i == 3) else "arrived",
                    "collisions": 0,
                    "time_s": 81.0 if (config == "default" and i == 3) else dist / 0.2 + i,
                    "distance_m": 1000.0 if (config == "default" and i == 3) else dist + i,
                    "replans": 3,
                    "agent_cpu_s": 2.0 if config == "default" else 0.5,
                }
            )
    return pd.DataFrame(rows)


def test_an_aborted_run_is_a_failure_in_the_success_rate_not_a_time_at_the_cap() -> None:
    """move_base's rules aborted default's run 3 after 81 s: it lowers the success rate (3 of 4, with its
    Wilson interval) and stays out of the time, distance and CPU means, which are over the 3 runs that
    arrived; the mean time no longer depends on where the cap is."""
    summary = summarise(table()).set_index("config")
    assert summary.loc["default", "runs"] == 4
    assert summary.loc["default", "success"] == 3
    assert summary.loc["default", "aborted"] == 1 and summary.loc["default", "timeouts"] == 0
    assert summary.loc["default", "time_s_mean"] == pytest.approx((250 + 251 + 252) / 3)
    assert summary.loc["default", "distance_m_mean"] == pytest.approx(51.0)  # the 1000 m failure is out
    assert summary.loc["full", "distance_m_mean"] == pytest.approx(32.5)
    assert summary.loc["full", "cpu_per_sim_s_mean"] < summary.loc["default", "cpu_per_sim_s_mean"]
    assert summary.loc["default", "success_ci_low"] == pytest.approx(wilson(3, 4)[0])
    text = markdown_table(summarise(table()))
    assert "| A->B | default | 4 | 3 | 75.0% [30.1, 95.4] | 1 | 0 | 0 |" in text
    assert "replans (arrived runs)" in text


def test_success_rates_carry_the_wilson_interval() -> None:
    """Wilson's score interval, from its formula: sound at n of n (where p +- z*se collapses to a point)."""
    z = 1.959963984540054

    def by_formula(k: int, n: int) -> tuple[float, float]:
        p = k / n
        centre = (p + z * z / (2 * n)) / (1 + z * z / n)
        half = z / (1 + z * z / n) * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
        return centre - half, centre + half

    for k, n in ((44, 50), (50, 50), (0, 14), (9, 14)):
        assert wilson(k, n) == pytest.approx(by_formula(k, n), abs=1e-9)
    low, high = wilson(50, 50)
    assert 0.92 < low < 0.93 and high == pytest.approx(1.0)


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


def test_paired_differences_compare_run_i_with_run_i_where_both_arrived() -> None:
    diff = paired_differences(table(), "default", "full").set_index("group")
    assert diff.loc["A->B", "pairs"] == 4 and diff.loc["A->B", "both_arrived"] == 3
    # full's time is default's minus 95 s in runs 0-2; run 3 was aborted under default: not a pair.
    assert diff.loc["A->B", "time_s_diff"] == pytest.approx(-95.0)
    assert diff.loc["A->B", "time_s_n"] == 3
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
    deviations = body[body.index("## Deviations from the paper's experiment") :]
    for says in (
        "reconstruction of the paper's school floor",
        "the paper chains the three routes",
        "emulated nodes",
        "0.5-2.0 s",
        "wait for a zone to clear",
    ):
        assert says in deviations


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
    assert "| A->B | z4 | full | 6 | 6 | 100% [61.0, 100] | 0 | 0 | 0 |" in markdown_table(
        summarise(t, ("route", "blocked")), ("route", "blocked")
    )


def test_configurations_take_turns_run_by_run_so_load_drift_falls_on_each_alike() -> None:
    """The runs go out in plan order: at no point has one configuration had more than one run more than
    another, so a machine growing busier during the experiment slows every configuration alike."""
    spec = load_site(SITES / "school").spec
    configs = ["default", "zones", "full"]
    runs = plan_runs(spec, configs, runs=10, seed=1)
    counts = dict.fromkeys(configs, 0)
    for r in runs:
        counts[r.config] += 1
        assert max(counts.values()) - min(counts.values()) <= 1, f"{counts} after {r}"
    assert counts == dict.fromkeys(configs, 30)


def test_each_bar_says_how_many_runs_arrived_in_the_papers_colours_under_a_whole_title(
    tmp_path: Path,
) -> None:
    time_metric = next(m for m in METRICS if m.column == "time_s")
    fig = bar_chart(summarise(table()), time_metric, tmp_path / "time_s.png")
    ax = fig.axes[0]
    assert sorted(t.get_text() for t in ax.texts) == ["3/4", "4/4"]
    colours = {
        b.get_label(): b.patches[0].get_facecolor() for b in ax.containers if isinstance(b, BarContainer)
    }
    assert CONFIG_COLOURS["default"] == "tab:orange" and CONFIG_COLOURS["full"] == "tab:blue"

    assert colours == {"default": to_rgba("tab:orange"), "full": to_rgba("tab:blue")}
    title = ax.title.get_window_extent()
    page = fig.bbox
    assert page.x0 <= title.x0 and title.x1 <= page.x1 and title.y1 <= page.y1, "the title fits the figure"
    box = ax.get_legend()
    assert box is not None
    legend = box.get_window_extent()
    assert legend.x0 >= ax.bbox.x1 and legend.x1 <= page.x1, "the legend beside the bars, not over them"


def test_the_report_renders_again_from_its_runs_table_alone(tmp_path: Path) -> None:
    rows = table()
    out = tmp_path / "out"
    out.mkdir()
    rows.to_csv(out / "runs.csv", index=False)
    first = write_report(rows, out, "# test\n\n- Code: commit abc").read_text()
    for png in out.glob("*.png"):
        png.unlink()
    again = rerender(out).read_text()
    assert again == first
    assert (out / "time_s.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_published_report_is_what_its_runs_table_renders_to(tmp_path: Path) -> None:
    """docs/experiment/report.md and its summaries are the report code's output for the published runs.csv:
    a change to the report's rules must come with the report rendered again (`--report-only`)."""
    import shutil

    published = SITES.parent / "docs" / "experiment"
    for name in ("runs.csv", "header.md", *(p.name for p in published.glob("paths_*.png"))):
        shutil.copy(published / name, tmp_path / name)
    report = rerender(tmp_path)
    assert report.read_text() == (published / "report.md").read_text()
    for name in ("summary.csv", "summary_by_zone.csv"):
        assert (tmp_path / name).read_text() == (published / name).read_text()


def test_the_real_move_base_report_is_what_its_runs_table_renders_to(tmp_path: Path) -> None:
    """docs/experiment_ros (the ROS backend on the real move_base) is the report code's output for its runs.csv,
    compared run by run with docs/experiment's same runs, as its header's reproduce line says."""
    import shutil

    docs = SITES.parent / "docs"
    published = docs / "experiment_ros"
    for name in ("runs.csv", "header.md", *(p.name for p in published.glob("paths_*.png"))):
        shutil.copy(published / name, tmp_path / name)
    report = rerender(tmp_path, docs / "experiment").read_text()
    assert report == (published / "report.md").read_text()
    assert "## Backends compared run by run: ros (this report) and sim" in report
    assert "| default | A->B | 0 | z1 | aborted | arrived |" in report


def test_both_cpu_figures_are_reported_each_labelled_for_what_it_is(tmp_path: Path) -> None:
    """A table with the run process's CPU gives both figures (each with its own column, chart and definition)
    and the memory per run; a table from code that did not measure it says so instead of showing a blank."""
    rows = table()
    rows["process_cpu_s"] = np.where(rows["config"] == "full", 1.5, 3.0)
    rows["peak_mem_mb"] = np.where(rows["config"] == "full", 340.0, 350.0)
    body = write_report(rows, tmp_path / "new", "# test").read_text()
    assert "run-process CPU per simulated second (s/s) (arrived runs)" in body
    assert "agent-step CPU per simulated second (s/s) (arrived runs)" in body
    assert "Run-process CPU per simulated second: the CPU time of the whole process" in body
    assert "](process_cpu_per_sim_s.png)" in body and "| full | 4 | 340 | 340 | 340 |" in body
    summary = summarise(rows).set_index("config")
    assert summary.loc["full", "process_cpu_per_sim_s_mean"] == pytest.approx(
        np.mean([1.5 / (155 + i) for i in range(4)])
    )
    old = write_report(table(), tmp_path / "old", "# test").read_text()
    assert "Run-process CPU is not in this runs table" in old
    assert "run-process CPU per simulated second" not in old and "## Memory" not in old
