"""The paper's per-route raffles: for run i of a route, which of its zone sets is blocked. Same seed, same draws.

Each route has its own random stream (seeded by the base seed and the route's index in the site file), so the
draws of one route do not depend on how many another route made; the stream is the one experiments/run_plan.py
uses, so draw i here is the zone set of the experiment's run i.
"""

from __future__ import annotations

import numpy as np

from schemas.site_file import Route, SiteFile


class RaffleError(ValueError):
    """An unknown route name; one line."""


def route_name(route: Route) -> str:
    return f"{route.from_}->{route.to}"


def find_route(spec: SiteFile, name: str) -> tuple[int, Route]:
    """The route called `A->B` and its index in the site file."""
    for index, route in enumerate(spec.routes):
        if route_name(route) == name:
            return index, route
    known = ", ".join(route_name(r) for r in spec.routes) or "none"
    raise RaffleError(f"unknown route {name!r} (the site's routes: {known})")


def draws(spec: SiteFile, name: str, seed: int, count: int) -> list[tuple[str, ...]]:
    """The first `count` raffled zone sets of route `name` for `seed`."""
    index, route = find_route(spec, name)
    rng = np.random.default_rng([seed, index])
    picks = rng.integers(0, len(route.raffle), size=count)
    return [tuple(route.raffle[int(p)]) for p in picks]
