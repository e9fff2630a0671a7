"""Pictures of a site: the map in grey, zones coloured and labelled, nodes, points and routes.

`draw_site` is reused by `wsnav plan`, the demo and the experiment report to draw paths over the same
background. It lives beside the site model (matplotlib drawing of a Site, nothing else) so that components such as
experiments can draw a site without importing the wsnav CLI.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import FancyArrowPatch, Polygon

from wsnav.schemas.site import Site

ZONE_COLOURS = (
    "tab:blue",
    "tab:orange",
    "tab:green",
    "tab:purple",
    "tab:brown",
    "tab:pink",
    "tab:olive",
    "tab:cyan",
)
"""Pyplot is never imported: figures are built object-oriented, so nothing needs a display or a global backend."""


def figure_for(site: Site, width_in: float = 12.0) -> tuple[Figure, Axes]:
    x0, y0, x1, y1 = site.grid.bounds
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    fig = Figure(figsize=(width_in, max(3.0, width_in * aspect + 0.8)))
    return fig, fig.add_subplot()


def draw_site(
    ax: Axes,
    site: Site,
    *,
    blocked: Iterable[str] = (),
    show_nodes: bool = True,
    show_routes: bool = True,
) -> None:
    """Map, zones (blocked ones hatched red), nodes, points and, optionally, the routes as arrows."""
    grid = site.grid
    shade = np.select([grid.data == 0, grid.data < 0], [1.0, 0.75], default=1.0 - grid.data / 100.0 * 0.9)
    x0, y0, x1, y1 = grid.bounds
    ax.imshow(
        shade, cmap="gray", vmin=0, vmax=1, origin="lower", extent=(x0, x1, y0, y1), interpolation="nearest"
    )
    blocked_set = set(blocked)
    for i, zone in enumerate(site.spec.zones):
        is_blocked = zone.id in blocked_set
        colour: str = "red" if is_blocked else ZONE_COLOURS[i % len(ZONE_COLOURS)]
        ax.add_patch(
            Polygon(
                zone.polygon,
                closed=True,
                facecolor=colour,
                alpha=0.45 if is_blocked else 0.3,
                edgecolor=colour,
                hatch="xx" if is_blocked else None,
                linewidth=1.2,
            )
        )
        cx, cy = np.mean(np.asarray(zone.polygon), axis=0)
        ax.text(cx, cy, zone.id, ha="center", va="center", fontsize=9, fontweight="bold", color="black")
    if show_nodes:
        for node, (nx, ny) in node_positions(site).items():
            ax.plot(nx, ny, marker="^", color="navy", markersize=6)
            ax.annotate(node, (nx, ny), xytext=(3, 3), textcoords="offset points", fontsize=6, color="navy")
    for name, (px, py, yaw) in site.spec.points.items():
        ax.plot(px, py, marker="o", color="darkgreen", markersize=9)
        ax.annotate(
            "",
            (px + 0.8 * np.cos(yaw), py + 0.8 * np.sin(yaw)),
            (px, py),
            arrowprops={"arrowstyle": "->", "color": "darkgreen"},
        )
        ax.text(px, py + 0.6, name, ha="center", fontsize=11, fontweight="bold", color="darkgreen")
    if show_routes:
        for route in site.spec.routes:
            a, b = site.point(route.from_), site.point(route.to)
            ax.add_patch(
                FancyArrowPatch(
                    a[:2],
                    b[:2],
                    arrowstyle="-|>",
                    mutation_scale=14,
                    color="purple",
                    linestyle="--",
                    connectionstyle="arc3,rad=0.15",
                    alpha=0.7,
                )
            )
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def node_positions(site: Site) -> dict[str, tuple[float, float]]:
    """Each node's position: its own if given, else spread around its zone's centre."""
    out: dict[str, tuple[float, float]] = {}
    per_zone: dict[str, int] = {}
    for node in site.spec.nodes:
        if node.position is not None:
            out[node.id] = node.position
            continue
        k = per_zone.get(node.zone, 0)
        per_zone[node.zone] = k + 1
        cx, cy = np.mean(np.asarray(site.spec.zone(node.zone).polygon), axis=0)
        out[node.id] = (float(cx) + 0.5 * k, float(cy) - 0.6)
    return out


def render_site(site: Site, png: Path) -> None:
    fig, ax = figure_for(site)
    draw_site(ax, site)
    ax.set_title(
        f"site {site.name}: {len(site.spec.zones)} zones, {len(site.spec.nodes)} nodes, "
        f"routes {', '.join(f'{r.from_}->{r.to}' for r in site.spec.routes) or 'none'}"
    )
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
