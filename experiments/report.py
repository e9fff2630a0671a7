"""The experiment's report: mean and 95% confidence interval per route and configuration (the paper's
Figures 10-12 as bar charts with error bars), a markdown table, and one run's paths under both configurations.

Reads only the runs table (and the saved trajectories), so a report can be remade without rerunning anything.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from numpy.typing import NDArray
from scipy import stats

from schemas.site import Site
from schemas.site_render import draw_site, figure_for

CONFIG_COLOURS = {"default": "tab:gray", "full": "tab:blue"}


@dataclass(frozen=True)
class Metric:
    column: str
    label: str
    figure: str
    """The paper's figure this chart reproduces."""


METRICS = (
    Metric("distance_m", "distance travelled (m)", "Figure 10"),
    Metric("time_s", "time to goal (s, simulated)", "Figure 11"),
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


def summarise(table: pd.DataFrame, by: Sequence[str] = ("route",)) -> pd.DataFrame:
    """One row per group (`by`, e.g. route, or route and blocked zone) and config: runs, successes,
    collisions, and mean/CI of every metric over successes. `group` labels the row's group in charts."""
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
        }
        for metric in METRICS:
            mean, low, high = mean_ci(ok[metric.column].to_numpy(dtype=np.float64))
            row[f"{metric.column}_mean"] = mean
            row[f"{metric.column}_ci_low"] = low
            row[f"{metric.column}_ci_high"] = high
        rows.append(row)
    return pd.DataFrame(rows)


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
    return f"{m:.2f} [{lo:.2f}, {hi:.2f}]" if abs(m) >= 0.01 else f"{m:.4f} [{lo:.4f}, {hi:.4f}]"


def markdown_table(summary: pd.DataFrame, by: Sequence[str] = ("route",)) -> str:
    head = "| " + " | ".join(by) + " | config | runs | success | collisions | replans | "
    head += " | ".join(m.label for m in METRICS)
    lines = [head + " |", "|" + " --- |" * (len(by) + 5 + len(METRICS))]
    for r in summary.to_dict("records"):
        cells = [str(r[k]) for k in by] + [
            str(r["config"]),
            str(r["runs"]),
            str(r["success"]),
            str(r["collisions"]),
            f"{float(r['replans_mean']):.1f}",
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


def write_report(table: pd.DataFrame, out: Path, header: str, path_figures: Sequence[Path] = ()) -> Path:
    """report.md plus PNGs in `out` (one per metric by route, the paper's figures, and one per metric by route
    and blocked zone); returns the report's path."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(table)
    summary.to_csv(out / "summary.csv", index=False)
    by_zone = summarise(table, ("route", "blocked"))
    by_zone.to_csv(out / "summary_by_zone.csv", index=False)
    parts = [header, "", "Mean over successful runs, with the 95% confidence interval in brackets.", ""]
    parts += ["## By route (the paper's Figures 10-12)", "", markdown_table(summary), ""]
    parts += [verdict_table(verdicts(summary), "route: full vs default"), ""]
    for metric in METRICS:
        png = out / f"{metric.column}.png"
        bar_chart(summary, metric, png)
        parts += [f"![{metric.label}]({png.name})", ""]
    parts += [
        "## By route and blocked zone",
        "",
        "A route's raffle mixes detours of different lengths, which widens its interval; run i blocks the same "
        "zone under both configurations, so each zone's rows compare like with like.",
        "",
        markdown_table(by_zone, ("route", "blocked")),
        "",
        verdict_table(verdicts(by_zone), "route and zone: full vs default"),
        "",
    ]
    for metric in METRICS:
        png = out / f"{metric.column}_by_zone.png"
        bar_chart(by_zone, metric, png)
        parts += [f"![{metric.label} by blocked zone]({png.name})", ""]
    if path_figures:
        parts += ["## Paths (the paper's Figures 8-9)", ""]
    for png in path_figures:
        parts += [f"![{png.stem}]({png.name})", ""]
    report = out / "report.md"
    report.write_text("\n".join(parts))
    return report
