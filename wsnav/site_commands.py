"""`wsnav site check DIR` and `wsnav site render DIR --png FILE`."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.runtime.cli_support import CliError
from wsnav.schemas.site import SiteError, load_site

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser


EXAMPLE_SITES = Path(__file__).resolve().parent / "sites"
"""The example sites: sites/ of the checkout, or the copy an installed wheel carries (wsnav/sites links to it)."""


def default_site() -> Path:
    """`sites/school` where the command runs (a checkout), else the school site the install ships."""
    local = Path("sites/school")
    return local if local.exists() else EXAMPLE_SITES / "school"


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    site = sub.add_parser("site", help="check or draw a site")
    site_sub = site.add_subparsers(dest="site_command", required=True, parser_class=type(site))
    check = site_sub.add_parser("check", help="validate site.yaml against its map")
    check.add_argument("site", type=Path, help="site directory or site.yaml")
    check.set_defaults(func=check_command)
    render = site_sub.add_parser("render", help="draw map, zones, nodes, points and routes to a PNG")
    render.add_argument("site", type=Path, help="site directory or site.yaml")
    render.add_argument("--png", type=Path, required=True, help="output picture")
    render.set_defaults(func=render_command)


def check_command(args: argparse.Namespace) -> int:
    try:
        site = load_site(args.site)
    except SiteError as exc:
        raise CliError(str(exc)) from None
    spec, grid = site.spec, site.grid
    print(
        f"{site.path}: ok: site {spec.name!r}, map {grid.width}x{grid.height} at {grid.resolution:g} m, "
        f"{len(spec.zones)} zones, {len(spec.nodes)} nodes, {len(spec.robots)} robots, "
        f"{len(spec.points)} points, {len(spec.routes)} routes"
    )
    return 0


def render_command(args: argparse.Namespace) -> int:
    from wsnav.schemas.site_render import render_site

    try:
        site = load_site(args.site)
    except SiteError as exc:
        raise CliError(str(exc)) from None
    try:
        render_site(site, args.png)
    except OSError as exc:
        raise CliError(f"{args.png}: cannot write picture: {exc.strerror}") from None
    print(f"wrote {args.png}")
    return 0
