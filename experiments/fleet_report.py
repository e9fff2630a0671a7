"""The fleet scenario's outputs: one row per robot and configuration (fleet.csv), a short report (report.md) and
the robots' trails over the map, one panel per configuration (trails.png)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pandas as pd
from matplotlib.figure import Figure

from wsnav.experiments.fleet_scenario import DEADLOCK_M, DEADLOCK_S, FleetResult
from wsnav.schemas.site import Site
from wsnav.schemas.site_render import draw_site


def summary_rows(results: Sequence[FleetResult]) -> list[dict[str, object]]:
    """One line per configuration: what the issue asks of a fleet."""
    out: list[dict[str, object]] = []
    for r in results:
        distances = [float(str(row["distance_m"])) for row in r.rows]
        out.append(
            {
                "config": r.config,
                "robots": len(r.rows),
                "collisions": r.collisions,
                "deadlocks": r.deadlocks,
                "goals reached": r.goals_reached,
                "goals per hour": round(r.goals_per_hour, 1),
                "distance per robot, mean (min-max) m": (
                    f"{sum(distances) / len(distances):.1f} ({min(distances):.1f}-{max(distances):.1f})"
                ),
                "yields": sum(int(str(row["yields"])) for row in r.rows),
                "closest footprints (m)": round(r.min_separation_m, 3),
                "wall (s)": round(r.wall_s),
            }
        )
    return out


def _markdown(rows: list[dict[str, object]]) -> str:
    if not rows:
        return ""
    keys = list(rows[0])
    lines = ["| " + " | ".join(keys) + " |", "| " + " | ".join("---" for _ in keys) + " |"]
    lines += ["| " + " | ".join(str(row[k]) for k in keys) + " |" for row in rows]
    return "\n".join(lines)


def trails_figure(site: Site, results: Sequence[FleetResult], png: Path) -> None:
    """Each configuration's trails of every robot over the map (start: a dot, end: a cross)."""
    x0, y0, x1, y1 = site.grid.bounds
    width = 12.0
    panel_h = width * (y1 - y0) / (x1 - x0) + 0.6
    fig = Figure(figsize=(width, panel_h * len(results)))
    for i, r in enumerate(results):
        ax = fig.add_subplot(len(results), 1, i + 1)
        draw_site(ax, site, show_nodes=False, show_routes=False)
        for j, (robot, xy) in enumerate(r.trajectories.items()):
            if not len(xy):
                continue
            colour = f"C{j % 10}"
            ax.plot(xy[:, 0], xy[:, 1], color=colour, linewidth=1.4, label=robot, alpha=0.85)
            ax.plot(xy[0, 0], xy[0, 1], "o", color=colour, markersize=5)
            ax.plot(xy[-1, 0], xy[-1, 1], "x", color=colour, markersize=7)
        ax.set_title(
            f"{r.config}: {len(r.rows)} robots, {r.duration_s / 60:.0f} simulated min, {r.goals_reached} goals, "
            f"{r.collisions} collisions, {r.deadlocks} deadlocks"
        )
        ax.legend(loc="upper right", fontsize=7, ncol=5)
    fig.tight_layout()
    fig.savefig(png, dpi=100)


def write_fleet_report(site: Site, results: Sequence[FleetResult], out: Path, reproduce: str) -> Path:
    """fleet.csv, trails.png and report.md in `out`; returns the report's path."""
    out.mkdir(parents=True, exist_ok=True)
    table = pd.DataFrame([row for r in results for row in r.rows])
    table.to_csv(out / "fleet.csv", index=False)
    trails_figure(site, results, out / "trails.png")
    events = results[0].zone_events if results else []
    schedule = ", ".join(f"{e.zone} {e.action} at {e.t:.0f} s" for e in events)
    lines = [
        f"# Fleet scenario: site {site.name}",
        "",
        f"Reproduce: `{reproduce}`",
        "",
        "Every robot of the site on random goals among the site's points (never one another robot stands on or",
        "is heading to), one zone at a time blocked by an obstacle and reported by the emulated nodes, the same",
        "goals' seed and zone schedule for every configuration; lock-step simulated time over a real MQTT",
        "broker, each robot with its own credentials and connection. A deadlock: a robot with a goal that moved",
        f"less than {DEADLOCK_M} m in {DEADLOCK_S:.0f} simulated s. Goals per hour: goals reached by the whole",
        "fleet per simulated hour. `default` has no zone layer (it learns of an obstacle from its lidar).",
        "",
        _markdown(summary_rows(results)),
        "",
        f"Zone schedule: {schedule}.",
        "",
        "Per robot (fleet.csv):",
        "",
        _markdown([{k: v for k, v in row.items()} for r in results for row in r.rows]),
        "",
        "![Trails](trails.png)",
        "",
    ]
    report = out / "report.md"
    report.write_text("\n".join(lines))
    return report
