"""What `wsnav zones` does once its arguments parse: load, check, run in real time, print a summary."""

from __future__ import annotations

import argparse
import sys

from wsnav.runtime.cli_support import CliError
from wsnav.runtime.clock import WallClock
from wsnav.schemas.site import SiteError, load_site
from wsnav.zone_sim.scenario import ScenarioError, blocks_scenario, load_scenario
from wsnav.zone_sim.sensor_model import SensorSettings
from wsnav.zone_sim.simulator import SimulatorError, ZoneSimulator
from wsnav.zone_sim.world import WorldError


def run_zones(args: argparse.Namespace) -> int:
    try:
        site = load_site(args.site)
    except SiteError as exc:
        raise CliError(str(exc)) from None
    if args.scenario is not None:
        try:
            scenario = load_scenario(args.scenario, site.spec)
        except ScenarioError as exc:
            raise CliError(str(exc)) from None
    else:
        zones = {z.id for z in site.spec.zones}
        for zone in args.block:
            if zone not in zones:
                raise CliError(
                    f"--block: unknown zone {zone!r} (site {site.name} has {', '.join(sorted(zones))})"
                )
        scenario = blocks_scenario(args.block)
    seed = args.seed if args.seed is not None else (scenario.seed or 0)
    duration = args.duration if args.duration is not None else scenario.duration_s
    sensor = SensorSettings(
        args.detection_delay if args.detection_delay is not None else scenario.sensor.detection_delay_s,
        args.miss_rate if args.miss_rate is not None else scenario.sensor.miss_rate,
    )
    log = (lambda _line: None) if args.quiet else (lambda line: print(line, flush=True))
    sim = ZoneSimulator(
        site,
        args.credentials,
        args.broker,
        WallClock(),
        scenario,
        seed=seed,
        sensor=sensor,
        log=log,
        nodes=args.nodes,
    )
    try:
        sim.start()
    except (SimulatorError, WorldError) as exc:
        sim.stop(clear_world=False)
        raise CliError(str(exc)) from None
    host, port = args.broker
    log(f"{len(sim.nodes)} nodes of site {site.name} connecting to {host}:{port} (seed {seed})")
    try:
        sim.run(duration)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
    finally:
        online = sim.online_count
        sim.stop()
    s = sim.stats
    print(
        f"{len(sim.nodes)} nodes ({online} online at the end), {s.published} messages published, "
        f"{s.world_updates} world updates, {s.link_failures} link failures, {sim.elapsed:.1f} s"
    )
    return 0
