"""What `wsnav fleet` and `wsnav fleet-experiment` do once their arguments parse: check them, run, report."""

from __future__ import annotations

import argparse
import contextlib
import math
from collections.abc import Iterator
from pathlib import Path

from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.experiments.fleet_report import summary_rows, write_fleet_report
from wsnav.experiments.fleet_scenario import run_fleet
from wsnav.experiments.fleet_sim import FleetError, SimFleet, start_poses
from wsnav.experiments.single_run import BrokerAt
from wsnav.robot_agent.agent_config import AgentConfigError, load_agent_config
from wsnav.runtime.cli_support import CliError
from wsnav.schemas.site import Site, SiteError, load_site


def _site(path: Path) -> Site:
    try:
        site = load_site(path)
        start_poses(site)
    except (SiteError, FleetError) as exc:
        raise CliError(str(exc)) from None
    return site


@contextlib.contextmanager
def _broker(args: argparse.Namespace, site: Site) -> Iterator[BrokerAt]:
    """The broker given (with the site's credentials), or an embedded amqtt broker for the run."""
    if args.broker is None:
        if args.credentials is not None:
            raise CliError("--credentials goes with --broker")
        with BrokerThread(site.path) as broker:
            yield BrokerAt(broker.host, broker.port, broker.credentials_dir)
        return
    creds: Path | None = args.credentials
    missing = [r.id for r in site.spec.robots if creds is None or not (creds / f"{r.id}.json").is_file()]
    if creds is None or missing or not (creds / "operator.json").is_file():
        raise CliError(
            "--broker needs --credentials DIR with every robot's and the operator's file "
            f"(`wsnav broker credentials`); missing: {', '.join(missing) or 'operator'}"
        )
    yield BrokerAt(args.broker[0], args.broker[1], creds)


def _config(name: str) -> None:
    try:
        load_agent_config(name)
    except AgentConfigError as exc:
        raise CliError(str(exc)) from None


def _goals(site: Site, specs: list[str]) -> list[tuple[str, str]]:
    out = []
    robots = {r.id for r in site.spec.robots}
    for spec in specs:
        robot, sep, point = spec.partition("=")
        if not sep or robot not in robots or point not in site.spec.points:
            raise CliError(
                f"--goal {spec!r}: expected ROBOT=POINT with a robot of the site ({', '.join(sorted(robots))}) "
                f"and a named point ({', '.join(site.spec.points)})"
            )
        out.append((robot, point))
    return out


def fleet(args: argparse.Namespace) -> int:
    site = _site(args.site)
    _config(args.config)
    goals = _goals(site, args.goal)
    if args.speed < 0 or args.every <= 0:
        raise CliError("--speed must be >= 0 and --every > 0")
    speed = math.inf if args.speed == 0 else args.speed
    with _broker(args, site) as at:
        sim = SimFleet(site, at, load_agent_config(args.config), nodes=args.nodes, seed=args.seed)
        try:
            sim.start()
            for robot, point in goals:
                sim.set_goal(robot, site.point(point), point)
            print(
                f"{len(sim.members)} robots of site {site.name} on {at.host}:{at.port}, each with its own "
                f"credentials and connection; goals over MQTT (robots/<id>/goal) or the console"
            )
            elapsed = 0.0
            while args.duration is None or elapsed < args.duration - 1e-9:
                span = args.every if args.duration is None else min(args.every, args.duration - elapsed)
                sim.run(span, speed)
                elapsed += span
                _print_fleet(sim, elapsed)
        except KeyboardInterrupt:
            pass
        finally:
            sim.close()
    print(f"collisions: {sim.collisions}")
    return 0


def _print_fleet(sim: SimFleet, elapsed: float) -> None:
    print(f"t={elapsed:.0f} s, collisions {sim.collisions}")
    for robot, m in sim.members.items():
        s = m.agent.status(sim.clock.now())
        x, y, _ = s.pose
        goal = s.goal if isinstance(s.goal, str) or s.goal is None else f"({s.goal[0]:.1f}, {s.goal[1]:.1f})"
        reason = f": {s.reason}" if s.reason else ""
        print(f"  {robot:8} {s.state:10} at ({x:5.1f}, {y:5.1f}) goal {goal}{reason}")


def fleet_experiment(args: argparse.Namespace) -> int:
    site = _site(args.site)
    configs = [c.strip() for c in args.configs.split(",") if c.strip()]
    if not configs:
        raise CliError("--configs names no configuration")
    for config in configs:
        _config(config)
    if not 0 < args.minutes <= 600:
        raise CliError(f"--minutes must be in (0, 600], got {args.minutes}")
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"{args.out}: cannot create output directory: {exc.strerror}") from None
    results = []
    for config in configs:  # an embedded broker per configuration: nothing retained or queued carries over
        with _broker(args, site) as at:
            results.append(run_fleet(site, at, config, args.minutes * 60.0, args.seed, progress=print))
    reproduce = (
        f"wsnav fleet-experiment --site {args.site} --minutes {args.minutes:g} --seed {args.seed} "
        f"--configs {','.join(configs)} --out {args.out}"
    )
    report = write_fleet_report(site, results, args.out, reproduce)
    for row in summary_rows(results):
        print(", ".join(f"{k}: {v}" for k, v in row.items()))
    print(f"wrote {report}, {args.out / 'fleet.csv'} and {args.out / 'trails.png'}")
    return 0
