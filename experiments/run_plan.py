"""Which runs an experiment makes: route x configuration x run index, each with its raffled zone set and seed.

Run i of a route blocks the same zones under every configuration (a paired comparison), and the whole list
follows from the base seed alone, so the same seed gives the same table. Run i's zones and seed depend on the
base seed, the route and i only: `--runs 20` makes exactly the first 20 runs of `--runs 50`.
"""

from __future__ import annotations

from dataclasses import dataclass

from wsnav.schemas.site_file import SiteFile
from wsnav.zone_sim.raffle import draw, run_stream


@dataclass(frozen=True)
class RunSpec:
    config: str
    route: str
    """`A->B`: the route's name in tables and figures."""
    start: str
    goal: str
    blocked: tuple[str, ...]
    run: int
    seed: int

    @property
    def blocked_label(self) -> str:
        return "+".join(self.blocked) or "none"


def route_name(start: str, goal: str) -> str:
    return f"{start}->{goal}"


def plan_runs(spec: SiteFile, configs: list[str], runs: int, seed: int) -> list[RunSpec]:
    """All runs, configurations interleaved run by run (run i of a route under each configuration, then run
    i+1): a drift in the machine's load while the experiment runs falls on every configuration alike instead of
    on whichever ran last."""
    out: list[RunSpec] = []
    for r_index, route in enumerate(spec.routes):
        streams = [run_stream(seed, r_index, i) for i in range(runs)]
        blocked = [draw(route, rng) for rng in streams]  # each stream's first number: the raffle
        seeds = [int(rng.integers(0, 2**31 - 1)) for rng in streams]
        for config in configs:
            for i in range(runs):
                out.append(
                    RunSpec(
                        config=config,
                        route=route_name(route.from_, route.to),
                        start=route.from_,
                        goal=route.to,
                        blocked=blocked[i],
                        run=i,
                        seed=seeds[i],
                    )
                )
    return sorted(out, key=lambda s: (s.run, s.route, configs.index(s.config)))
