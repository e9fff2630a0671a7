"""The experiment's report: success rate with its Wilson interval, mean and 95% confidence interval of every
metric per route and configuration (the paper's Figures 10-12 as bar charts with error bars, each bar saying how
many runs arrived), paired differences between configurations that say what each change brings, stalls and
move_base's recoveries, the deviations from the paper, and one run's paths under each configuration.

The rule for failed runs: a run that did not arrive (move_base's rules aborted it, or the 600 s cap ended it) is
a failure and counts in the success rate; time, distance, replans and CPU are means over the runs that arrived
(an aborted run ended at 81-253 s: counting it at the cap would make the mean depend on the cap). Every number is
printed to three significant figures. Reads only the runs table (and the saved path figures), so a report can be
remade from a published runs.csv without rerunning anything.
"""

from __future__ import annotations

import itertools
import math
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from numpy.typing import NDArray
from scipy import stats

from wsnav.schemas.site import Site
from wsnav.schemas.site_render import draw_site, figure_for

CONFIG_COLOURS = {"default": "tab:orange", "zones": "tab:gray", "full": "tab:blue"}
"""The paper's colours: orange for stock move_base (`default`), blue for wsnav (`full`); `zones`, which the paper
does not have, in grey between them."""
CONFIG_ORDER = ("default", "zones", "full")
STEPS = {
    ("default", "zones"): "the sensor network (zone layer + Algorithm 3)",
    ("zones", "full"): "event-driven replanning + coarser planning + a smaller, slower local costmap",
    ("default", "full"): "everything wsnav changes",
}
"""What each paired comparison isolates (the configurations differ in exactly that)."""
TIME_CAP_S = 600.0
"""wsnav.experiments.single_run.TIMEOUT_SIM_S: a run not arrived by then ends as a timeout."""
LEVEL = 0.95

STOCK_DIFFERENCES = (
    "global planner: A* (pyastar2d) over NavFn's cost model, at full resolution in `default` and `zones` "
    "(3x coarser in `full`), instead of NavFn's Dijkstra; paths are smoothed",
    "local planner: Regulated Pure Pursuit with a collision check over a 1 s arc, instead of DWA's sampled "
    "trajectories",
    "footprint: a circle of the site's robot radius (0.105 m inscribed and circumscribed), instead of the "
    "Burger's rectangular footprint; aggressive reset keeps move_base's 4 x 0.148 m square",
    "lidar: beams with no return (+inf) clear up to the raytrace range (costmap_2d's `inf_is_valid`), which "
    "stock LaserScan handling drops",
    "costmaps: as move_base's, a global costmap for the planner and a local one for the controller (a rolling "
    "window with its own obstacle and inflation layers, 3 x 3 m at 10 Hz); the robots layer of a site with "
    "several robots is in both",
    "recoveries: move_base's default behaviours with ROBOTIS' parameters, rotate_recovery without its "
    "footprint collision check (a round robot turning in place touches nothing new)",
    "simulation: a kinematic TurtleBot3 with velocity noise and the LDS-01's range noise, no Gazebo physics",
)
"""Every remaining difference between `default` and stock move_base on a TurtleBot3, for the report's header."""


@dataclass(frozen=True)
class Metric:
    column: str
    label: str
    figure: str
    """The paper's figure this chart reproduces."""


METRICS = (
    Metric("distance_m", "distance travelled (m)", "Figure 10"),
    Metric("time_s", "time to goal (s, simulated)", "Figure 11"),
    Metric("cpu_per_sim_s", "agent-step CPU per simulated second (s/s)", "Figure 12"),
    Metric("process_cpu_per_sim_s", "run-process CPU per simulated second (s/s)", "Figure 12"),
)
"""Every metric is a mean over the runs that arrived."""
SOURCE_COLUMN = {"cpu_per_sim_s": "agent_cpu_s", "process_cpu_per_sim_s": "process_cpu_s"}
"""Derived metrics and the runs-table column each needs (a table from older code may lack it)."""


def metrics_of(table: pd.DataFrame) -> tuple[Metric, ...]:
    """The metrics this runs table can give (a column the code that wrote it did not measure, or left empty in
    every run as the ROS backend leaves the agent's CPU, is left out)."""
    return tuple(m for m in METRICS if _measured(table, SOURCE_COLUMN.get(m.column, m.column)))


def _measured(table: pd.DataFrame, column: str) -> bool:
    return column in table.columns and bool(np.isfinite(table[column].to_numpy(dtype=np.float64)).any())


def wilson(successes: int, runs: int, level: float = LEVEL) -> tuple[float, float]:
    """The Wilson score interval of a success rate (low, high), as fractions; sound at 0 and at n of n, where
    the normal approximation's interval collapses to a point."""
    if runs == 0:
        return float("nan"), float("nan")
    ci = stats.binomtest(successes, runs).proportion_ci(confidence_level=level, method="wilson")
    return float(ci.low), float(ci.high)


def mean_ci(values: Sequence[float] | NDArray[np.float64], level: float = 0.95) -> tuple[float, float, float]:
    """Mean and Student-t confidence interval (low, high); with one value the interval is the value itself."""
    x = np.asarray(values, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return float("nan"), float("nan"), float("nan")
    mean = float(x.mean())
    if x.size < 2:
        return mean, mean, mean
    half = float(stats.t.ppf(0.5 + level / 2, x.size - 1) * x.std(ddof=1) / np.sqrt(x.size))
    return mean, mean - half, mean + half


def sig3(x: float) -> str:
    """Three significant figures, never in exponent notation (0.0151, 2.00, 362, 1230)."""
    if not np.isfinite(x):
        return "n/a"
    rounded = float(f"{x:.3g}")
    if rounded == 0:
        return "0"
    decimals = 2 - math.floor(math.log10(abs(rounded)))
    return f"{rounded:.{max(decimals, 0)}f}"


def metric_values(group: pd.DataFrame, column: str) -> NDArray[np.float64]:
    """A metric's values under the report's rule: over the runs that arrived (a failure is counted in the
    success rate, not as a time)."""
    return group.loc[group["success"].to_numpy(dtype=bool), column].to_numpy(dtype=np.float64)


def _outcomes(group: pd.DataFrame) -> tuple[int, int]:
    """(aborted, timed out) among a group's failed runs; a table without `outcome` counts every failure as a
    timeout."""
    failed = ~group["success"].to_numpy(dtype=bool)
    if "outcome" not in group.columns:
        return 0, int(failed.sum())
    outcome = group["outcome"].astype(str).to_numpy()
    aborted = int((failed & (outcome == "aborted")).sum())
    return aborted, int(failed.sum()) - aborted


def summarise(table: pd.DataFrame, by: Sequence[str] = ("route",)) -> pd.DataFrame:
    """One row per group (`by`, e.g. route, or route and blocked zone) and config: runs, successes with their
    Wilson interval, aborts and timeouts, collisions, stalls, recoveries, and mean/CI of every metric over the
    runs that arrived. `group` labels the row's group in charts."""
    metrics = metrics_of(table)
    table = with_derived(table)
    keys = [*by, "config"]
    rows: list[dict[str, object]] = []
    for key, group in table.groupby(keys, sort=True):
        values = dict(zip(keys, key if isinstance(key, tuple) else (key,), strict=True))
        success = group["success"].to_numpy(dtype=bool)
        ok = group.loc[success]
        row: dict[str, object] = {
            **values,
            "group": " ".join(str(values[k]) for k in by),
            "runs": len(group),
            "success": int(success.sum()),
            "success_ci_low": wilson(int(success.sum()), len(group))[0],
            "success_ci_high": wilson(int(success.sum()), len(group))[1],
            "aborted": _outcomes(group)[0],
            "timeouts": _outcomes(group)[1],
            "collisions": int(group["collisions"].to_numpy(dtype=np.int64).sum()),
            "replans_mean": _finite_mean(ok["replans"].to_numpy(dtype=np.float64)),
            "stalled_s_mean": _mean_of(group, "stalled_s"),
            "recoveries_mean": _mean_of(group, "recoveries"),
        }
        for metric in metrics:
            mean, low, high = mean_ci(metric_values(group, metric.column))
            row[f"{metric.column}_mean"] = mean
            row[f"{metric.column}_ci_low"] = low
            row[f"{metric.column}_ci_high"] = high
        rows.append(row)
    return _in_config_order(pd.DataFrame(rows), list(by))


def _in_config_order(summary: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    """Rows grouped by `by`, each group's configurations in the ablation's order (default, zones, full)."""
    if summary.empty:
        return summary
    rank = {c: i for i, c in enumerate(CONFIG_ORDER)}
    order = [rank.get(str(c), len(rank)) for c in summary["config"]]
    return (
        summary.assign(_rank=order)
        .sort_values([*by, "_rank", "config"], kind="stable")
        .drop(columns="_rank")
        .reset_index(drop=True)
    )


def _mean_of(group: pd.DataFrame, column: str) -> float:
    """Mean over every run of a column older tables may lack (NaN then)."""
    if column not in group.columns:
        return float("nan")
    return _finite_mean(group[column].to_numpy(dtype=np.float64))


def _finite_mean(values: NDArray[np.float64]) -> float:
    """The mean over the runs that measured it (an empty cell is a run that did not: the ROS backend's move_base
    publishing no plan or recovery topic); NaN when none did."""
    measured = values[np.isfinite(values)]
    return float(measured.mean()) if measured.size else float("nan")


def summary_metrics(summary: pd.DataFrame) -> tuple[Metric, ...]:
    """The metrics a summary (or a paired-difference table) carries."""
    return tuple(
        m for m in METRICS if f"{m.column}_mean" in summary.columns or f"{m.column}_diff" in summary.columns
    )


def paired_differences(
    table: pd.DataFrame, before: str, after: str, by: Sequence[str] = ("route",)
) -> pd.DataFrame:
    """Per group and metric: the mean of `after` - `before` over the runs with the same index (same raffled
    zone, same seed) where both arrived, with its 95% Student-t interval."""
    metrics = metrics_of(table)
    table = with_derived(table)
    keys = [*by, "run"]
    a = table[table["config"] == before].set_index(keys)
    b = table[table["config"] == after].set_index(keys)
    common = a.index.intersection(b.index)
    rows: list[dict[str, object]] = []
    if len(common) == 0:
        return pd.DataFrame(rows)
    a, b = a.loc[common], b.loc[common]
    groups = common.droplevel("run").unique()
    for group_key in groups:
        a_g, b_g = a.xs(group_key, drop_level=False), b.xs(group_key, drop_level=False)
        both = a_g["success"].to_numpy(dtype=bool) & b_g["success"].to_numpy(dtype=bool)
        row: dict[str, object] = {
            "group": " ".join(str(k) for k in (group_key if isinstance(group_key, tuple) else (group_key,))),
            "pairs": len(a_g),
            "both_arrived": int(both.sum()),
        }
        for metric in metrics:
            col = metric.column
            diff = (b_g[col].to_numpy(dtype=np.float64) - a_g[col].to_numpy(dtype=np.float64))[both]
            mean, low, high = mean_ci(diff)
            row[f"{col}_n"] = int(np.isfinite(diff).sum())
            row[f"{col}_diff"] = mean
            row[f"{col}_ci_low"] = low
            row[f"{col}_ci_high"] = high
        rows.append(row)
    return pd.DataFrame(rows)


def paired_table(diff: pd.DataFrame, before: str, after: str) -> str:
    """Markdown: each group's paired differences, and whether the interval excludes zero."""
    metrics = summary_metrics(diff)
    lines = [
        "| route | pairs | both arrived | "
        + " | ".join(f"{m.label}: {after} - {before}" for m in metrics)
        + " |",
        "|" + " --- |" * (3 + len(metrics)),
    ]
    for r in diff.to_dict("records"):
        cells = [str(r["group"]), str(r["pairs"]), str(r["both_arrived"])]
        for m in metrics:
            mean, low, high = (float(r[f"{m.column}_{k}"]) for k in ("diff", "ci_low", "ci_high"))
            n = int(r[f"{m.column}_n"])  # type: ignore[arg-type]
            apart = n >= 2 and (high < 0 or low > 0)
            cells.append(f"{_fmt(mean, low, high)}{'' if not np.isfinite(mean) else (' *' if apart else '')}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def verdicts(summary: pd.DataFrame, better: str = "full", baseline: str = "default") -> pd.DataFrame:
    """Per group: is `better`'s success rate or metric mean better than `baseline`'s, and do their 95%
    intervals stay apart?"""
    rows: list[dict[str, object]] = []
    for group in summary["group"].unique():
        part = summary[summary["group"] == group].set_index("config")
        if better not in part.index or baseline not in part.index:
            continue
        b, d = part.loc[better], part.loc[baseline]
        rate_b, rate_d = (float(x["success"]) / float(x["runs"]) for x in (b, d))
        higher = rate_b > rate_d
        rate_apart = float(b["success_ci_low"]) > float(d["success_ci_high"])
        row: dict[str, object] = {
            "group": group,
            "success": "higher, CIs apart"
            if higher and rate_apart
            else ("higher, CIs overlap" if higher else "not higher"),
        }
        for metric in summary_metrics(summary):
            lower = float(b[f"{metric.column}_mean"]) < float(d[f"{metric.column}_mean"])
            apart = float(b[f"{metric.column}_ci_high"]) < float(d[f"{metric.column}_ci_low"])
            row[metric.column] = (
                "lower, CIs apart" if lower and apart else ("lower, CIs overlap" if lower else "not lower")
            )
        rows.append(row)
    return pd.DataFrame(rows)


def with_derived(table: pd.DataFrame) -> pd.DataFrame:
    """The runs table with the per-simulated-second CPU figures its columns allow."""
    out = table.copy()
    seconds = out["time_s"].where(out["time_s"] > 0)
    for derived, source in SOURCE_COLUMN.items():
        if source in out.columns:
            out[derived] = out[source] / seconds
    return out


def bar_chart(summary: pd.DataFrame, metric: Metric, png: Path) -> Figure:
    """One bar per group and configuration with its 95% CI, and over each bar how many runs arrived (the runs
    its mean is over); returns the figure, drawn and saved to `png`."""
    groups = list(dict.fromkeys(summary["group"]))
    configs = [c for c in CONFIG_COLOURS if c in set(summary["config"])] + sorted(
        set(summary["config"]) - set(CONFIG_COLOURS)
    )
    fig = Figure(figsize=(max(7.5, 1.3 * len(groups)), 4.6))
    ax = fig.add_subplot()
    width = 0.8 / max(len(configs), 1)
    x = np.arange(len(groups))
    for i, config in enumerate(configs):
        part = summary[summary["config"] == config].set_index("group").reindex(groups)
        mean = part[f"{metric.column}_mean"].to_numpy(dtype=np.float64)
        high = part[f"{metric.column}_ci_high"].to_numpy(dtype=np.float64)
        err = np.vstack([mean - part[f"{metric.column}_ci_low"].to_numpy(dtype=np.float64), high - mean])
        at = x + (i - (len(configs) - 1) / 2) * width
        ax.bar(at, mean, width, yerr=err, capsize=4, label=config, color=CONFIG_COLOURS.get(config, f"C{i}"))
        for xi, top, arrived, runs in zip(at, high, part["success"], part["runs"], strict=True):
            if np.isfinite(top) and pd.notna(runs):
                ax.annotate(
                    f"{int(arrived)}/{int(runs)}",
                    (float(xi), float(top)),
                    xytext=(0, 2),
                    textcoords="offset points",
                    ha="center",
                    va="bottom",
                    fontsize=7,
                    rotation=90 if len(groups) * len(configs) > 12 else 0,  # narrow bars: labels stand up
                )
    ax.set_xticks(x, groups)
    ax.set_ylabel(textwrap.fill(metric.label, 34))
    ax.margins(y=0.12)
    ax.set_title(
        textwrap.fill(
            f"{metric.figure} of the paper: {metric.label}, mean and 95% CI over the runs that arrived "
            "(arrived/runs over each bar)",
            80,
        ),
        fontsize=10,
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    return fig


def paths_figure(
    site: Site,
    trajectories: Mapping[str, NDArray[np.float64]],
    blocked: Sequence[str],
    title: str,
    png: Path,
) -> None:
    """The robot's driven paths, one per configuration, over the map with the blocked zones hatched."""
    fig, ax = figure_for(site)
    draw_site(ax, site, blocked=blocked, show_routes=False)
    for i, (config, xy) in enumerate(trajectories.items()):
        if len(xy):
            ax.plot(
                xy[:, 0], xy[:, 1], color=CONFIG_COLOURS.get(config, f"C{i}"), linewidth=2.2, label=config
            )
    ax.legend(loc="upper right")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def _fmt(mean: object, low: object, high: object) -> str:
    m, lo, hi = float(mean), float(low), float(high)  # type: ignore[arg-type]
    if not np.isfinite(m):
        return "n/a"
    return f"{sig3(m)} [{sig3(lo)}, {sig3(hi)}]"


def success_cell(successes: int, runs: int) -> str:
    """`88.0% [76.2, 94.4]`: the success rate with its 95% Wilson interval, in per cent."""
    if runs == 0:
        return "n/a"
    low, high = wilson(successes, runs)
    return f"{sig3(100.0 * successes / runs)}% [{sig3(100.0 * low)}, {sig3(100.0 * high)}]"


def markdown_table(summary: pd.DataFrame, by: Sequence[str] = ("route",)) -> str:
    metrics = summary_metrics(summary)
    head = "| " + " | ".join(by) + " | config | runs | arrived | success rate [95% Wilson] | aborted | "
    head += (
        "timed out | collisions | replans (arrived runs) | stalled (s, all runs) | recoveries (all runs) | "
    )
    head += " | ".join(f"{m.label} (arrived runs)" for m in metrics)
    lines = [head + " |", "|" + " --- |" * (len(by) + 10 + len(metrics))]
    for r in summary.to_dict("records"):
        runs, success = int(r["runs"]), int(r["success"])  # type: ignore[arg-type]
        cells = [str(r[k]) for k in by] + [
            str(r["config"]),
            str(runs),
            str(success),
            success_cell(success, runs),
            str(r["aborted"]),
            str(r["timeouts"]),
            str(r["collisions"]),
            sig3(float(r["replans_mean"])),  # type: ignore[arg-type]
            sig3(float(r["stalled_s_mean"])),  # type: ignore[arg-type]
            sig3(float(r["recoveries_mean"])),  # type: ignore[arg-type]
        ]
        cells += [
            _fmt(r[f"{m.column}_mean"], r[f"{m.column}_ci_low"], r[f"{m.column}_ci_high"]) for m in metrics
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def verdict_table(verdict: pd.DataFrame, what: str) -> str:
    columns = [("success", "success rate")] + [
        (m.column, m.label) for m in METRICS if m.column in verdict.columns
    ]
    lines = [
        f"| {what} | " + " | ".join(label for _, label in columns) + " |",
        "|" + " --- |" * (1 + len(columns)),
    ]
    for r in verdict.to_dict("records"):
        lines.append("| " + " | ".join([str(r["group"]), *(str(r[c]) for c, _ in columns)]) + " |")
    return "\n".join(lines)


def comparisons(configs: Sequence[str]) -> list[tuple[str, str]]:
    """The paired comparisons to report: each step of the ablation present, and default -> full."""
    out = list(itertools.pairwise(configs))
    if "default" in configs and "full" in configs and ("default", "full") not in out:
        out.append(("default", "full"))
    return out


def rules_and_differences(metrics: Sequence[Metric] = METRICS, on_ros: bool = False) -> list[str]:
    """The report's rules for failed runs and figures, and what still separates `default` from stock (on the
    ROS backend: stock move_base itself, and what its CPU figure is)."""
    if on_ros:
        return [*_rules(), "", *(f"- {c}" for c in ROS_MEASURES)]
    cpu = [
        "Agent-step CPU per simulated second: thread CPU time inside the agent's step (costmap updates, "
        "planning, control), per simulated second of the run: the share of one core the navigation's own work "
        "would take at real-time pace. It is not the paper's figure, and the periodic replanning is most of "
        "`default`'s."
    ]
    if any(m.column == "process_cpu_per_sim_s" for m in metrics):
        cpu.append(
            "Run-process CPU per simulated second: the CPU time of the whole process that ran the run (user + "
            "system, every thread: the agent, the simulated robot and its lidar, the emulated nodes, the MQTT "
            "clients, and the broker when it is the embedded amqtt), per simulated second: the closest this "
            "simulation comes to the paper's move_base process CPU, an upper bound of it since the simulator "
            "is in the same process."
        )
    else:
        cpu.append(
            "Run-process CPU is not in this runs table (the code that wrote it did not measure it): the report "
            "shows the agent-step CPU only."
        )
    return [
        *_rules(),
        "",
        *(f"- {c}" for c in cpu),
        "",
        "`default` is stock move_base on a TurtleBot3 (ROBOTIS' noetic parameters: planner 5 Hz, controller "
        "10 Hz, global costmap 10 Hz, 3 m local window, obstacle range 3.0 m, raytrace 3.5 m, inflation 1.0 m / "
        "3.0, oscillation timeout 10 s / 0.2 m, planner patience 5 s, controller patience 15 s, recoveries "
        "conservative reset (3 m), rotate, aggressive reset, rotate, then abort) except for:",
        "",
        *(f"- {d}" for d in STOCK_DIFFERENCES),
    ]


ROS_MEASURES = (
    "Backend: the ROS 1 navigation installed here drove every run (move_base with navfn, DWA and "
    "costmap_2d, ROBOTIS' Burger parameters with each configuration's own rates and sizes; for `zones` and "
    "`full` the zone layer as a StaticLayer of the global costmap and `wsnav ros bridge --robot`, Algorithm 3), "
    "the robot `wsnav sim --ros --clock`, simulated time on /clock at the simulator's real-time pace.",
    "Run-process CPU per simulated second: move_base's process CPU (user + system, psutil, its children "
    "included) over the run, per second of /clock, which advanced in real time: move_base's share of a core "
    "in real time, as the paper measured it. Peak memory is move_base's resident set, sampled during the run.",
    "Replans: the global planner's makePlan calls during the run, read from /move_base/NavfnROS/plan (navfn "
    "publishes a plan it found twice with one stamp, an empty one once when it finds no path) less the goal's "
    "first; with the zone layer, each goal the bridge re-sends is planned and counted too. Recoveries: the "
    "messages on /move_base/recovery_status (noetic's move_base publishes one per recovery behaviour), named "
    "in the recovery log. A move_base that publishes neither topic leaves those cells empty in runs.csv (n/a "
    "here), never 0.",
    "Not measured on ROS (empty in runs.csv): agent-step CPU (no wsnav agent runs) and planning time "
    "(move_base does not report it).",
)
"""What the runs table's columns mean when the ROS backend wrote it."""


def _rules() -> list[str]:
    return [
        "How to read it: a run arrives, or fails: move_base's rules abort it (its recoveries all failed) or "
        f"the {TIME_CAP_S:.0f} s simulated-time cap ends it. The success rate counts both failures, with its "
        "95% Wilson interval. Time to goal, distance, replans and CPU are means over the runs that arrived (an "
        "aborted run stops long before the cap, so counting it at the cap would make the mean depend on the "
        "cap); over each bar, how many runs arrived of how many ran. Stalled and recoveries: means over every "
        "run. Stalled: simulated time in stretches of at least 10 s in which the robot got no 0.2 m further "
        "(move_base's oscillation rule, measured alike for every configuration). Brackets: 95% Student-t "
        "intervals of the mean, Wilson for success rates. Three significant figures throughout.",
    ]


DEVIATIONS = (
    "The site: sites/school is the project's reconstruction of the paper's school floor (its Figures 5-7), "
    "drawn from layout.yaml by sites/school/generate.py; the paper publishes no map, so distances and times "
    "compare with the paper's in kind, not to the metre.",
    "A run: one route (A->B, B->C or C->D) from a start drawn around the route's first point (5 cm and "
    "0.05 rad standard deviation), with the route's raffled zone blocked as it starts; the paper chains the "
    "three routes in one drive, so its robot starts each route where the previous one ended.",
    "Zone states: come from emulated nodes (wsnav's zone simulator: the firmware's logic, not ESP8266s) over "
    "MQTT through a real broker; each node sees the obstacle 0.5-2.0 s after it appears (detection delay "
    "drawn per run), and reports it as the firmware does.",
    "No path: `zones` and `full` wait for a zone to clear when the zone layer leaves no path (Algorithm 3's "
    "wait) instead of aborting after planner patience as `default` (stock move_base) does; every raffled zone "
    "of the school leaves a longer way round (site.yaml), so the wait is there for sites where it does not.",
    "Time: simulated, in lock step (50 ms steps) as fast as the machine allows; the paper's runs were in real "
    "time on a TurtleBot3, so its CPU is a process's share of a core over wall time, these are CPU seconds "
    "per simulated second (the same ratio had the run been paced in real time, without the idle costs a "
    "paced process has).",
    "Local costmap: the controller's own rolling window (obstacle and inflation layers, as ROBOTIS' "
    "local_costmap_params), 3 x 3 m updated at 10 Hz in `default` and `zones`, the paper's reduced 2 x 2 m at "
    "5 Hz in `full`; its obstacle layer takes the same lidar sweeps as the global costmap's.",
)
"""What differs between this experiment and the paper's, for the report's deviations section."""


ROS_DEVIATIONS = (
    "Time: simulated on /clock, advanced by `wsnav sim --ros --clock` at its real-time pace (move_base and the "
    "bridge run with /use_sim_time); the robot is wsnav's simulated TurtleBot3, not Gazebo's or a real one.",
)
"""The deviations that differ on the ROS backend (it has move_base's own local costmap and real-time pace)."""


def deviations_section(on_ros: bool = False) -> list[str]:
    kept = [d for d in DEVIATIONS if not on_ros or not d.startswith(("Time:", "Local costmap:"))]
    extra = list(ROS_DEVIATIONS) if on_ros else []
    return ["## Deviations from the paper's experiment", "", *(f"- {d}" for d in [*kept, *extra]), ""]


BACKEND_LINE = "- Backend: "
"""How the report's header names the backend that produced it (`backend_of` reads it back)."""


def backend_of(header: str) -> str:
    """`ros` or `sim`: which backend wrote a report's header (headers older than the ROS backend: `sim`)."""
    for line in header.splitlines():
        if line.startswith(BACKEND_LINE):
            return "ros" if line[len(BACKEND_LINE) :].startswith("ROS") else "sim"
    return "sim"


def _compared(table: pd.DataFrame, key: list[str]) -> pd.DataFrame:
    """The columns compared, `outcome` read from `success` in tables older than it."""
    t = table.copy()
    if "outcome" not in t.columns:
        t["outcome"] = np.where(t["success"].to_numpy(dtype=bool), "arrived", "failed")
    return t.loc[:, [*key, "outcome", "distance_m", "time_s"]]


def backend_comparison(table: pd.DataFrame, header: str, other: pd.DataFrame, other_header: str) -> list[str]:
    """The same plan on both backends, run by run (same configuration, route, run index, seed and blocked
    zones): outcome, distance and time on each. ReportError when the two tables share no run."""
    mine, theirs = backend_of(header), backend_of(other_header)
    key = ["config", "route", "run", "seed", "blocked"]
    both = _compared(table, key).merge(_compared(other, key), on=key, suffixes=("_a", "_b"))
    if both.empty:
        raise ReportError(
            "--compare: the two runs tables share no run (same plan: configuration, route, run, seed)"
        )
    lines = [
        f"## Backends compared run by run: {mine} (this report) and {theirs}",
        "",
        f"{len(both)} runs of the same plan (same configuration, route, run, seed and blocked zones) on both.",
        "",
        f"| config | route | run | blocked | outcome {mine} | outcome {theirs} | distance {mine} (m) | "
        f"distance {theirs} (m) | time {mine} (s) | time {theirs} (s) |",
        "|" + " --- |" * 10,
    ]
    for r in both.sort_values(["route", "run", "config"]).to_dict("records"):
        lines.append(
            f"| {r['config']} | {r['route']} | {r['run']} | {r['blocked']} | {r['outcome_a']} | {r['outcome_b']} "
            f"| {sig3(float(r['distance_m_a']))} | {sig3(float(r['distance_m_b']))} | {sig3(float(r['time_s_a']))} "
            f"| {sig3(float(r['time_s_b']))} |"
        )
    return [*lines, ""]


def memory_section(table: pd.DataFrame, on_ros: bool = False) -> list[str]:
    """Each configuration's peak memory per run, from tables whose runs measured it per run (those with the
    run-process CPU column; before it, the figure grew with a worker's run order and is left out)."""
    if "process_cpu_s" not in table.columns or "peak_mem_mb" not in table.columns:
        return []
    lines = [
        "## Memory",
        "",
        "move_base's resident-set peak during each run (sampled with psutil while the run went)."
        if on_ros
        else "The run process's resident-set peak during each run (Linux VmHWM, reset as the run starts, after "
        "the previous runs' garbage is collected): the agent, the simulated robot, the emulated nodes and "
        "their MQTT clients, and the broker when it is the embedded amqtt.",
        "",
        "| config | runs | median (MB) | min (MB) | max (MB) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for config in [c for c in CONFIG_ORDER if c in set(table["config"])]:
        mem = table.loc[table["config"] == config, "peak_mem_mb"].to_numpy(dtype=np.float64)
        lines.append(
            f"| {config} | {len(mem)} | {sig3(float(np.median(mem)))} | {sig3(float(mem.min()))} | "
            f"{sig3(float(mem.max()))} |"
        )
    return [*lines, ""]


def stall_section(table: pd.DataFrame) -> list[str]:
    """The longest stall of each configuration, with the recoveries move_base ran in it: what remains when
    stock move_base would stall too."""
    if "stalled_s" not in table.columns:
        return []
    parts = [
        "## Stalls and move_base's recoveries",
        "",
        "A stall that outlasts all four recoveries ends as stock move_base ends it: the goal aborted (a failed "
        "run). Why a stock robot stalls before an obstacle about 3 m away: its face sits at the obstacle "
        "layer's 3.0 m marking range, where readings just beyond it clear the marks and the 5 Hz planner "
        "switches between the way through and the detour (docs/architecture.md, the move_base facts).",
        "",
    ]
    for config in [c for c in CONFIG_ORDER if c in set(table["config"])]:
        part = table.loc[table["config"].to_numpy() == config]
        stalled = part["stalled_s"].to_numpy(dtype=np.float64)
        worst = part.iloc[int(np.argmax(stalled))]
        if float(worst["stalled_s"]) <= 0:
            parts += [f"- `{config}`: no stall in {len(part)} runs.", ""]
            continue
        aborted = int((part["outcome"] == "aborted").sum()) if "outcome" in part.columns else 0
        parts += [
            f"- `{config}`: {int((stalled > 0).sum())} of {len(part)} runs stalled, {aborted} aborted by "
            "move_base's rules."
        ]
        log = str(worst.get("recovery_log", "") or "")
        log = "" if log == "nan" else log
        parts += [
            f"  The longest stall is {worst['route']} with {worst['blocked']} blocked, run "
            f"{worst['run']} (seed {worst['seed']}): {sig3(float(worst['stalled_s']))} s stalled, "
            f"{worst.get('outcome', '')} after {sig3(float(worst['time_s']))} s; "
            f"recoveries (s from the goal): {log or 'none'}.",
            "",
        ]
    return parts


HEADER_FILE = "header.md"
"""The report's opening as the run wrote it (what ran, where, how fast, the code and its dependencies), kept
beside runs.csv so that the report can be rendered again from the published files alone."""


def write_report(
    table: pd.DataFrame,
    out: Path,
    header: str,
    path_figures: Sequence[Path] = (),
    compare: tuple[pd.DataFrame, str] | None = None,
) -> Path:
    """report.md plus PNGs in `out` (one per metric by route, the paper's figures, and one per metric by route
    and blocked zone), and the header in header.md; returns the report's path. `compare`: the runs table and
    header of the same plan run by the other backend, for a run-by-run comparison."""
    out.mkdir(parents=True, exist_ok=True)
    (out / HEADER_FILE).write_text(header.rstrip("\n") + "\n")
    metrics = metrics_of(table)
    summary = summarise(table)
    summary.to_csv(out / "summary.csv", index=False)
    by_zone = summarise(table, ("route", "blocked"))
    by_zone.to_csv(out / "summary_by_zone.csv", index=False)
    configs = [c for c in CONFIG_ORDER if c in set(table["config"])]
    configs += sorted(set(table["config"]) - set(configs))
    on_ros = backend_of(header) == "ros"
    parts = [header, "", *rules_and_differences(metrics, on_ros), "", *deviations_section(on_ros)]
    if compare is not None:
        parts += backend_comparison(table, header, *compare)
    parts += ["## By route (the paper's Figures 10-12)", "", markdown_table(summary), ""]
    for before, after in comparisons(configs):
        diff = paired_differences(table, before, after)
        if diff.empty:
            continue
        what = STEPS.get((before, after), f"{before} -> {after}")
        parts += [
            f"### {before} -> {after}: {what}",
            "",
            "Mean paired difference (run i of a route under both: same zone, same seed) over the pairs where "
            "both arrived, with its 95% interval; `*`: the interval excludes zero (two pairs or more).",
            "",
            paired_table(diff, before, after),
            "",
        ]
    for metric in metrics:
        png = out / f"{metric.column}.png"
        bar_chart(summary, metric, png)
        parts += [f"![{metric.label}]({png.name})", ""]
    parts += [
        "## By route and blocked zone",
        "",
        "A route's raffle mixes detours of different lengths, which widens its interval; run i blocks the same "
        "zone under every configuration, so each zone's rows compare like with like.",
        "",
        markdown_table(by_zone, ("route", "blocked")),
        "",
    ]
    if {"full", "default"} <= set(configs):
        parts += [verdict_table(verdicts(by_zone), "route and zone: full vs default"), ""]
    for metric in metrics:
        png = out / f"{metric.column}_by_zone.png"
        bar_chart(by_zone, metric, png)
        parts += [f"![{metric.label} by blocked zone]({png.name})", ""]
    parts += memory_section(table, on_ros)
    parts += stall_section(table)
    if path_figures:
        parts += ["## Paths (the paper's Figures 8-9)", ""]
    for png in path_figures:
        parts += [f"![{png.stem}]({png.name})", ""]
    report = out / "report.md"
    report.write_text("\n".join(parts))
    return report


NEEDED = ("run", "success", "time_s", "distance_m")
NUMERIC = ("collisions", "replans", "recoveries", "stalled_s", "agent_cpu_s", "process_cpu_s")


def _booleans(values: object) -> NDArray[np.bool_]:
    """`success` as written by the runner (True/False), whatever pandas made of it."""
    text = np.char.lower(np.char.strip(np.asarray(values, dtype=str)))
    if not np.isin(text, ["true", "false"]).all():
        raise ValueError("success")
    return text == "true"


class ReportError(Exception):
    """The folder holds no runs table to render a report from; one line for the user."""


def read_runs(out: Path) -> tuple[pd.DataFrame, str]:
    """`out`'s runs.csv (typed as the runner wrote it) and header.md; ReportError, one line, when either is
    missing or not what the runner writes."""
    runs_csv = out / "runs.csv"
    try:
        table = pd.read_csv(runs_csv, keep_default_na=False)
        header = (out / HEADER_FILE).read_text().rstrip("\n")
    except FileNotFoundError as exc:
        raise ReportError(f"{out}: no {Path(str(exc.filename)).name} to render the report from") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ReportError(f"{runs_csv}: not a runs table ({type(exc).__name__})") from None
    missing = [c for c in (*NEEDED, "config", "route", "blocked") if c not in table]
    if missing:
        raise ReportError(f"{runs_csv}: not a runs table (no {', '.join(missing)} column)")
    try:
        table["success"] = _booleans(table["success"])
    except ValueError:
        raise ReportError(f"{runs_csv}: column success holds a value that is not True or False") from None
    for column in [c for c in (*NEEDED, *NUMERIC) if c in table and c != "success"]:
        try:  # an empty cell: a column the backend did not measure in that run (NaN, never 0)
            table[column] = pd.to_numeric(table[column].replace("", np.nan))
        except ValueError:
            raise ReportError(f"{runs_csv}: column {column} holds a value that is not a number") from None
    return table, header


def rerender(out: Path, compare: Path | None = None) -> Path:
    """The report again from `out`'s runs.csv and header.md (and the path figures already there), nothing
    rerun: how a reader checks that a published report is what its table says. `compare`: another backend's
    output of the same plan, compared run by run."""
    table, header = read_runs(out)
    other = read_runs(compare) if compare is not None else None
    return write_report(table, out, header, sorted(out.glob("paths_*.png")), other)
