"""The paper's per-route raffles: for run i of a route, which of its zone sets is blocked. Same seed, same draws.

Run i of a route has its own random stream (seeded by the base seed, the route's index in the site file and i),
so a draw depends on nothing another run or route made, and `--runs 20` draws exactly the first 20 of
`--runs 50`; experiments/run_plan.py takes its runs' draws (and then their noise seeds) from the same streams, so
draw i here is the zone set of the experiment's run i.
"""

from __future__ import annotations

import numpy as np

from wsnav.schemas.site_file import Route, SiteFile


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


def run_stream(seed: int, route_index: int, run: int) -> np.random.Generator:
    """Run `run` of the route at `route_index`: its raffle draw is this stream's first number."""
    return np.random.default_rng([seed, route_index, run])


def draw(route: Route, rng: np.random.Generator) -> tuple[str, ...]:
    """The zone set a run's stream raffles for `route`."""
    return tuple(route.raffle[int(rng.integers(0, len(route.raffle)))])


def draws(spec: SiteFile, name: str, seed: int, count: int) -> list[tuple[str, ...]]:
    """The first `count` raffled zone sets of route `name` for `seed`."""
    index, route = find_route(spec, name)
    return [draw(route, run_stream(seed, index, i)) for i in range(count)]
