"""The experiment's report: success rate, mean and 95% confidence interval per route and configuration (the
paper's Figures 10-12 as bar charts with error bars), paired differences between configurations that say what
each change brings, stalls and move_base's recoveries, and one run's paths under each configuration.

The rule for failed runs: time to goal counts every run, a run that did not arrive at the cap (a censored value,
a lower bound of its true time); distance and CPU per simulated second are means over the runs that arrived.
Every number is printed to three significant figures. Reads only the runs table (and the saved trajectories),
so a report can be remade without rerunning anything.
"""

from __future__ import annotations

import itertools
import math
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

CONFIG_COLOURS = {"default": "tab:gray", "zones": "tab:orange", "full": "tab:blue"}
CONFIG_ORDER = ("default", "zones", "full")
STEPS = {
    ("default", "zones"): "the sensor network (zone layer + Algorithm 3)",
    ("zones", "full"): "event-driven replanning + coarser planning",
    ("default", "full"): "everything wsnav changes",
}
"""What each paired comparison isolates (the configurations differ in exactly that)."""
TIME_CAP_S = 600.0
"""wsnav.experiments.single_run.TIMEOUT_SIM_S: a failed run's time counts as this (censored)."""

STOCK_DIFFERENCES = (
    "global planner: A* (pyastar2d) over NavFn's cost model, at full resolution in `default` and `zones` "
    "(3x coarser in `full`), instead of NavFn's Dijkstra; paths are smoothed",
    "local planner: Regulated Pure Pursuit with a collision check over a 1 s arc, instead of DWA's sampled "
    "trajectories",
    "footprint: a circle of the site's robot radius (0.105 m inscribed and circumscribed), instead of the "
    "Burger's rectangular footprint; aggressive reset keeps move_base's 4 x 0.148 m square",
    "lidar: beams with no return (+inf) clear up to the raytrace range (costmap_2d's `inf_is_valid`), which "
    "stock LaserScan handling drops",
    "costmaps: one global costmap; the controller reads a rolling window of it instead of a separate local "
    "costmap with its own obstacle layer",
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
    Metric("time_s", "time to goal (s, simulated; failures at the cap)", "Figure 11"),
    Metric("cpu_per_sim_s", "agent CPU per simulated second (s/s)", "Figure 12"),
)


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
    """A metric's values under the report's rule: time counts every run (failures at the cap), the others
    only the runs that arrived."""
    if column == "time_s":
        success = group["success"].to_numpy(dtype=bool)
        return np.where(success, group["time_s"].to_numpy(dtype=np.float64), TIME_CAP_S)
    return group.loc[group["success"].to_numpy(dtype=bool), column].to_numpy(dtype=np.float64)


def summarise(table: pd.DataFrame, by: Sequence[str] = ("route",)) -> pd.DataFrame:
    """One row per group (`by`, e.g. route, or route and blocked zone) and config: runs, successes,
    collisions, stalls, recoveries, and mean/CI of every metric under the report's rule for failed runs.
    `group` labels the row's group in charts."""
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
            "collisions": int(group["collisions"].to_numpy(dtype=np.int64).sum()),
            "replans_mean": float(ok["replans"].to_numpy(dtype=np.float64).mean())
            if len(ok)
            else float("nan"),
            "stalled_s_mean": _mean_of(group, "stalled_s"),
            "recoveries_mean": _mean_of(group, "recoveries"),
        }
        for metric in METRICS:
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
    if column not in group.columns or len(group) == 0:
        return float("nan")
    return float(group[column].to_numpy(dtype=np.float64).mean())


def paired_differences(
    table: pd.DataFrame, before: str, after: str, by: Sequence[str] = ("route",)
) -> pd.DataFrame:
    """Per group and metric: the mean of `after` - `before` over the runs with the same index (same raffled
    zone, same seed), with its 95% Student-t interval; time over every pair (failures at the cap), the other
    metrics over the pairs where both arrived."""
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
        row: dict[str, object] = {
            "group": " ".join(str(k) for k in (group_key if isinstance(group_key, tuple) else (group_key,))),
            "pairs": len(a_g),
            "both_arrived": int(
                (a_g["success"].to_numpy(dtype=bool) & b_g["success"].to_numpy(dtype=bool)).sum()
            ),
        }
        both = a_g["success"].to_numpy(dtype=bool) & b_g["success"].to_numpy(dtype=bool)
        for metric in METRICS:
            if metric.column == "time_s":
                diff = metric_values(b_g, "time_s") - metric_values(a_g, "time_s")
            else:
                col = metric.column
                diff = (b_g[col].to_numpy(dtype=np.float64) - a_g[col].to_numpy(dtype=np.float64))[both]
            mean, low, high = mean_ci(diff)
            row[f"{metric.column}_n"] = int(np.isfinite(diff).sum())
            row[f"{metric.column}_diff"] = mean
            row[f"{metric.column}_ci_low"] = low
            row[f"{metric.column}_ci_high"] = high
        rows.append(row)
    return pd.DataFrame(rows)


def paired_table(diff: pd.DataFrame, before: str, after: str) -> str:
    """Markdown: each group's paired differences, and whether the interval excludes zero."""
    lines = [
        "| route | pairs | both arrived | "
        + " | ".join(f"{m.label}: {after} - {before}" for m in METRICS)
        + " |",
        "|" + " --- |" * (3 + len(METRICS)),
    ]
    for r in diff.to_dict("records"):
        cells = [str(r["group"]), str(r["pairs"]), str(r["both_arrived"])]
        for m in METRICS:
            mean, low, high = (float(r[f"{m.column}_{k}"]) for k in ("diff", "ci_low", "ci_high"))
            n = int(r[f"{m.column}_n"])  # type: ignore[arg-type]
            apart = n >= 2 and (high < 0 or low > 0)
            cells.append(f"{_fmt(mean, low, high)}{'' if not np.isfinite(mean) else (' *' if apart else '')}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def verdicts(summary: pd.DataFrame, better: str = "full", baseline: str = "default") -> pd.DataFrame:
    """Per group and metric: is `better`'s mean lower than `baseline`'s, and do their 95% CIs stay apart?"""
    rows: list[dict[str, object]] = []
    for group in summary["group"].unique():
        part = summary[summary["group"] == group].set_index("config")
        if better not in part.index or baseline not in part.index:
            continue
        row: dict[str, object] = {"group": group}
        for metric in METRICS:
            b, d = part.loc[better], part.loc[baseline]
            lower = float(b[f"{metric.column}_mean"]) < float(d[f"{metric.column}_mean"])
            apart = float(b[f"{metric.column}_ci_high"]) < float(d[f"{metric.column}_ci_low"])
            row[metric.column] = (
                "lower, CIs apart" if lower and apart else ("lower, CIs overlap" if lower else "not lower")
            )
        rows.append(row)
    return pd.DataFrame(rows)


def with_derived(table: pd.DataFrame) -> pd.DataFrame:
    out = table.copy()
    out["cpu_per_sim_s"] = out["agent_cpu_s"] / out["time_s"].where(out["time_s"] > 0)
    return out


def bar_chart(summary: pd.DataFrame, metric: Metric, png: Path) -> None:
    groups = list(dict.fromkeys(summary["group"]))
    configs = [c for c in CONFIG_COLOURS if c in set(summary["config"])] + sorted(
        set(summary["config"]) - set(CONFIG_COLOURS)
    )
    fig = Figure(figsize=(max(7.5, 1.3 * len(groups)), 4.2))
    ax = fig.add_subplot()
    width = 0.8 / max(len(configs), 1)
    x = np.arange(len(groups))
    for i, config in enumerate(configs):
        part = summary[summary["config"] == config].set_index("group").reindex(groups)
        mean = part[f"{metric.column}_mean"].to_numpy(dtype=np.float64)
        err = np.vstack(
            [
                mean - part[f"{metric.column}_ci_low"].to_numpy(dtype=np.float64),
                part[f"{metric.column}_ci_high"].to_numpy(dtype=np.float64) - mean,
            ]
        )
        ax.bar(
            x + (i - (len(configs) - 1) / 2) * width,
            mean,
            width,
            yerr=err,
            capsize=4,
            label=config,
            color=CONFIG_COLOURS.get(config, f"C{i}"),
        )
    ax.set_xticks(x, groups)
    ax.set_ylabel(metric.label)
    ax.set_title(f"{metric.label}: mean and 95% CI ({metric.figure} of the paper)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(png, dpi=110)


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


def markdown_table(summary: pd.DataFrame, by: Sequence[str] = ("route",)) -> str:
    head = "| " + " | ".join(by) + " | config | runs | success | success rate | collisions | replans | "
    head += "stalled (s) | recoveries | "
    head += " | ".join(m.label for m in METRICS)
    lines = [head + " |", "|" + " --- |" * (len(by) + 8 + len(METRICS))]
    for r in summary.to_dict("records"):
        runs, success = int(r["runs"]), int(r["success"])  # type: ignore[arg-type]
        cells = [str(r[k]) for k in by] + [
            str(r["config"]),
            str(runs),
            str(success),
            f"{sig3(100.0 * success / runs)}%" if runs else "n/a",
            str(r["collisions"]),
            sig3(float(r["replans_mean"])),  # type: ignore[arg-type]
            sig3(float(r["stalled_s_mean"])),  # type: ignore[arg-type]
            sig3(float(r["recoveries_mean"])),  # type: ignore[arg-type]
        ]
        cells += [
            _fmt(r[f"{m.column}_mean"], r[f"{m.column}_ci_low"], r[f"{m.column}_ci_high"]) for m in METRICS
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def verdict_table(verdict: pd.DataFrame, what: str) -> str:
    lines = [
        f"| {what} | " + " | ".join(m.label for m in METRICS) + " |",
        "|" + " --- |" * (1 + len(METRICS)),
    ]
    for r in verdict.to_dict("records"):
        lines.append("| " + " | ".join([str(r["group"]), *(str(r[m.column]) for m in METRICS)]) + " |")
    return "\n".join(lines)


def comparisons(configs: Sequence[str]) -> list[tuple[str, str]]:
    """The paired comparisons to report: each step of the ablation present, and default -> full."""
    out = list(itertools.pairwise(configs))
    if "default" in configs and "full" in configs and ("default", "full") not in out:
        out.append(("default", "full"))
    return out


def rules_and_differences() -> list[str]:
    """The report's rules for failed runs and figures, and what still separates `default` from stock."""
    return [
        "How to read it: success counts the runs that arrived within the "
        f"{TIME_CAP_S:.0f} s simulated-time cap. Time to goal counts every run: a run that did not arrive counts "
        "as the cap (a censored value: its true time is at least that), so failures raise the mean instead of "
        "vanishing. Distance and CPU per simulated second are means over the runs that arrived. Stalled: "
        "simulated time in stretches of at least 10 s in which the robot got no 0.2 m further (move_base's "
        "oscillation rule, measured alike for every configuration). Brackets: 95% Student-t intervals. Three "
        "significant figures throughout.",
        "",
        "`default` is stock move_base on a TurtleBot3 (ROBOTIS' noetic parameters: planner 5 Hz, controller "
        "10 Hz, global costmap 10 Hz, 3 m local window, obstacle range 3.0 m, raytrace 3.5 m, inflation 1.0 m / "
        "3.0, oscillation timeout 10 s / 0.2 m, planner patience 5 s, controller patience 15 s, recoveries "
        "conservative reset (3 m), rotate, aggressive reset, rotate, then abort) except for:",
        "",
        *(f"- {d}" for d in STOCK_DIFFERENCES),
    ]


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


def write_report(table: pd.DataFrame, out: Path, header: str, path_figures: Sequence[Path] = ()) -> Path:
    """report.md plus PNGs in `out` (one per metric by route, the paper's figures, and one per metric by route
    and blocked zone); returns the report's path."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(table)
    summary.to_csv(out / "summary.csv", index=False)
    by_zone = summarise(table, ("route", "blocked"))
    by_zone.to_csv(out / "summary_by_zone.csv", index=False)
    configs = [c for c in CONFIG_ORDER if c in set(table["config"])]
    configs += sorted(set(table["config"]) - set(configs))
    parts = [header, "", *rules_and_differences(), ""]
    parts += ["## By route (the paper's Figures 10-12)", "", markdown_table(summary), ""]
    for before, after in comparisons(configs):
        diff = paired_differences(table, before, after)
        if diff.empty:
            continue
        what = STEPS.get((before, after), f"{before} -> {after}")
        parts += [
            f"### {before} -> {after}: {what}",
            "",
            "Mean paired difference (run i of a route under both: same zone, same seed) with its 95% interval; "
            "`*`: the interval excludes zero (two pairs or more).",
            "",
            paired_table(diff, before, after),
            "",
        ]
    for metric in METRICS:
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
    for metric in METRICS:
        png = out / f"{metric.column}_by_zone.png"
        bar_chart(by_zone, metric, png)
        parts += [f"![{metric.label} by blocked zone]({png.name})", ""]
    parts += stall_section(table)
    if path_figures:
        parts += ["## Paths (the paper's Figures 8-9)", ""]
    for png in path_figures:
        parts += [f"![{png.stem}]({png.name})", ""]
    report = out / "report.md"
    report.write_text("\n".join(parts))
    return report
