"""Robot agents at fleet scale: 10 agents and 1000 emulated nodes at 1 Hz on one machine, each agent's CPU and
zone message -> reacted (replanned) p99 per robot, against 1 agent alone in the same run.

    ./.venv/bin/python -m bench.fleet_agents [--nodes 1000] [--changes 100] [--broker amqtt|mosquitto] [--no-write]

The school map and its ten robots, with `--nodes` - 1 emulated nodes spread over its seven zones (all `clear`,
heartbeat 1 s, one ZoneSimulator process) and one probe node in z4 that this process toggles `blocked`/`clear`
every 0.5 s. The broker (`wsnav broker run`, amqtt, or Mosquitto) runs as its own process. Each agent runs in its own process in real time
(`RobotAgent.run`, its simulated TurtleBot3 stepped in the same loop, as `wsnav robot --sim` does), driving to a
point across the building and following the other robots' statuses (the robots layer). Every change of z4
makes every driving robot replan; each is timed from just before `publish()` to the agent's navigator having
decided (CLOCK_MONOTONIC is one clock for every process of the host). Phase 1: robot1 alone; phase 2: all ten.
`--quick`: 20 nodes, 2 agents, 10 changes per phase; the fleet's p50 over robot1 alone's at most 10, and an
agent's CPU in the fleet over robot1's alone at most 3.
"""

from __future__ import annotations

import bisect
import contextlib
import dataclasses
import multiprocessing as mp
import os
import resource
import shutil
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from bench.bench_broker import fresh_broker, mosquitto_broker
from bench.benchmarks_md import machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser

REPO = Path(__file__).resolve().parent.parent
SCHOOL = REPO / "sites" / "school"
SECTION = "## Robot agents at fleet scale: 10 agents and 1000 nodes on one machine (school map, {broker})"
COMMAND = "./.venv/bin/python -m bench.fleet_agents"
PROBE = "probe"
INTERVAL_S = 0.5
SETTLE_S = 3.0
GOALS = {
    "robot1": "B",
    "robot2": "H7",
    "robot3": "H8",
    "robot4": "H9",
    "robot5": "D",
    "robot6": "H1",
    "robot7": "A",
    "robot8": "C",
    "robot9": "H4",
    "robot10": "H7",
}
"""Each robot's goal lies across the building from its start, so it is still driving when the run ends."""


def fleet_site(directory: Path, nodes: int) -> Path:
    """The school (map, zones, robots, points) with `nodes` - 1 nodes round the zones and the probe in z4."""
    directory.mkdir(parents=True, exist_ok=True)
    for name in ("map.yaml", "map.pgm"):
        shutil.copy(SCHOOL / name, directory / name)
    spec: dict[str, Any] = yaml.safe_load((SCHOOL / "site.yaml").read_text())
    zones = [z["id"] for z in spec["zones"]]
    spec["heartbeat_s"] = 1.0
    spec["nodes"] = [
        {"id": f"n{i}", "zone": zones[i % len(zones)], "sensor": {"type": "pir", "pin": 5}}
        for i in range(nodes - 1)
    ]
    spec["nodes"].append({"id": PROBE, "zone": "z4", "sensor": {"type": "pir", "pin": 5}})
    spec["routes"] = []
    (directory / "site.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
    return directory


class MonotonicClock:
    """CLOCK_MONOTONIC: one clock for every process of this host, so a publish and a reaction compare."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


def run_nodes(site_dir: str, creds: str, host: str, port: int, ready: Any, stop: Any) -> None:
    """The emulated nodes (all but the probe), in real time until told to stop."""
    from wsnav.runtime.clock import WallClock
    from wsnav.schemas.site import load_site
    from wsnav.zone_sim.simulator import SimulatorError, ZoneSimulator

    site = load_site(site_dir)
    spec = site.spec.model_copy(update={"nodes": [n for n in site.spec.nodes if n.id != PROBE]})
    site = dataclasses.replace(site, spec=spec)
    sim = ZoneSimulator(site, Path(creds), (host, port), WallClock())
    sim.start()
    try:
        ready.put(sim.wait_online(timeout_s=600))
    except SimulatorError as exc:
        raise SystemExit(str(exc)) from None
    while not stop.is_set():
        sim.step(io_timeout_s=0.01)
    sim.stop()


def run_agent(
    site_dir: str, creds: str, host: str, port: int, robot_id: str, ready: Any, done: Any, out: Any
) -> None:
    """One robot agent in real time, driving to its goal, until told to stop; reports reactions and CPU."""
    from wsnav.robot_agent.agent import RobotAgent
    from wsnav.robot_agent.agent_config import load_agent_config
    from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3
    from wsnav.robot_agent.sim.world_grid import SimWorldGrid
    from wsnav.runtime.mqtt_bus import connect_with_credentials
    from wsnav.schemas.credentials import load_credentials
    from wsnav.schemas.site import load_site

    site = load_site(site_dir)
    clock = MonotonicClock()
    world = SimWorldGrid(site.grid)
    start = next(r.start for r in site.spec.robots if r.id == robot_id)
    assert start is not None
    robot = SimTurtleBot3(robot_id, world, site.point(start))
    bus = connect_with_credentials(
        host, port, load_credentials(Path(creds) / f"{robot_id}.json"), clock=clock
    )
    agent = RobotAgent(site, load_agent_config("full"), robot, bus, clock, robot_id, sim_world=world)
    agent.set_goal(site.point(GOALS[robot_id]), GOALS[robot_id], clock.now())
    stop = threading.Event()
    last = [clock.now()]

    def world_tick(now: float) -> float:
        robot.step(min(now - last[0], 0.1), now)
        last[0] = now
        return now + 0.02

    loop = threading.Thread(target=agent.run, args=(stop, world_tick), daemon=True)
    usage0 = resource.getrusage(resource.RUSAGE_SELF)
    wall0 = time.monotonic()
    loop.start()
    ready.put(robot_id)
    done.wait()
    stop.set()
    loop.join(5.0)
    usage = resource.getrusage(resource.RUSAGE_SELF)
    bus.close()
    cpu = usage.ru_utime + usage.ru_stime - usage0.ru_utime - usage0.ru_stime
    reactions = [(r.received_at, r.done_at, r.replanned) for r in agent.zone_reactions]
    out.put((robot_id, reactions, cpu, agent.stats.cpu_s, time.monotonic() - wall0, agent.navigator.state))


@dataclass
class AgentResult:
    robot: str
    latencies_ms: list[float]
    replanned: int
    process_cpu_s: float
    step_cpu_s: float
    wall_s: float
    state: str

    @property
    def cpu_share(self) -> float:
        """Process CPU (agent loop, paho thread, simulated robot) per wall second."""
        return self.process_cpu_s / self.wall_s


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))]


def phase(
    ctx: Any, site_dir: Path, creds: Path, host: str, port: int, robots: list[str], changes: int, seq0: int
) -> tuple[list[AgentResult], float]:
    """Start the agents, toggle z4 `changes` times, collect each agent's reactions; returns them and the load."""
    from wsnav.runtime.mqtt_bus import connect_with_credentials
    from wsnav.schemas import topics
    from wsnav.schemas.credentials import load_credentials
    from wsnav.schemas.messages import ZoneState

    ready, out, done = ctx.Queue(), ctx.Queue(), ctx.Event()
    procs = [
        ctx.Process(target=run_agent, args=(str(site_dir), str(creds), host, port, r, ready, done, out))
        for r in robots
    ]
    for p in procs:
        p.start()
    for _ in robots:
        ready.get(timeout=120)
    time.sleep(SETTLE_S)
    probe = connect_with_credentials(host, port, load_credentials(creds / f"{PROBE}.json"))
    topic = topics.zone_state("school", "z4", PROBE)
    published: list[float] = []
    for i in range(changes):
        payload = ZoneState(zone="z4", node=PROBE, state="blocked" if i % 2 == 0 else "clear", seq=seq0 + i)
        published.append(time.monotonic())
        probe.publish(topic, payload.to_payload(), qos=1, retain=True)
        time.sleep(INTERVAL_S)
    load = os.getloadavg()[0]
    time.sleep(1.0)
    done.set()
    results = []
    for _ in robots:
        robot, reactions, cpu, step_cpu, wall, state = out.get(timeout=60)
        latencies: dict[int, float] = {}
        replanned = 0
        for received_at, done_at, did in reactions:
            i = bisect.bisect_right(published, received_at) - 1
            if i >= 0 and i not in latencies:
                latencies[i] = (done_at - published[i]) * 1000.0
                replanned += did
        results.append(AgentResult(robot, list(latencies.values()), replanned, cpu, step_cpu, wall, state))
    for p in procs:
        p.join(30)
    probe.close()
    return sorted(results, key=lambda r: int(r.robot.removeprefix("robot"))), load


@dataclass(frozen=True)
class Endpoint:
    host: str
    port: int
    credentials_dir: Path


@contextlib.contextmanager
def broker_at(kind: str, site_dir: Path, root: Path) -> Iterator[Endpoint]:
    """`wsnav broker run` (amqtt) or Mosquitto from `wsnav broker mosquitto-config`, each as its own process."""
    if kind == "amqtt":
        with fresh_broker(site_dir, root) as proc:
            yield Endpoint(proc.host, proc.port, proc.credentials_dir)
        return
    from wsnav.broker.credentials import write_credentials
    from wsnav.schemas.site import load_site

    creds = root / "creds"
    spec = load_site(site_dir).spec
    write_credentials(spec, creds)
    with mosquitto_broker(spec, creds, root) as mq:
        yield Endpoint(mq.host, mq.port, creds)


def main(argv: list[str] | None = None) -> int:
    parser = quick_parser(__doc__)
    parser.add_argument("--nodes", type=int, default=1000)
    parser.add_argument("--changes", type=int, default=100)
    parser.add_argument("--broker", choices=("amqtt", "mosquitto"), default="amqtt")
    args = parse_quick_args(parser, argv)
    ctx = mp.get_context("spawn")
    robots = list(GOALS)
    if args.quick:
        args.nodes, args.changes, robots = min(args.nodes, 20), min(args.changes, 10), robots[:2]
    with tempfile.TemporaryDirectory(prefix="wsnav-bench-") as tmp:
        site_dir = fleet_site(Path(tmp) / "site", args.nodes)
        with broker_at(args.broker, site_dir, Path(tmp)) as broker:
            creds = broker.credentials_dir
            ready, stop = ctx.Queue(), ctx.Event()
            nodes = ctx.Process(
                target=run_nodes, args=(str(site_dir), str(creds), broker.host, broker.port, ready, stop)
            )
            nodes.start()
            joined_s = ready.get(timeout=660)
            print(f"{args.nodes - 1} nodes online after {joined_s:.0f} s; load {os.getloadavg()[0]:.1f}")
            try:
                alone, load1 = phase(
                    ctx, site_dir, creds, broker.host, broker.port, robots[:1], args.changes, 1000
                )
                print(f"1 agent: p99 {pct(alone[0].latencies_ms, 99):.1f} ms, load {load1:.1f}")
                fleet, load10 = phase(
                    ctx, site_dir, creds, broker.host, broker.port, robots, args.changes, 1000 + args.changes
                )
            finally:
                stop.set()
                nodes.join(60)
    base = alone[0]
    rows = [
        "| phase | robot | reactions | replanned | p50 | p99 | max | p99 / alone | CPU (process) | CPU / alone |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for label, results in (("1 agent", alone), ("10 agents", fleet)):
        for r in results:
            rows.append(
                f"| {label} | {r.robot} | {len(r.latencies_ms)} | {r.replanned} | {pct(r.latencies_ms, 50):.1f} ms | "
                f"{pct(r.latencies_ms, 99):.1f} ms | {max(r.latencies_ms, default=float('nan')):.1f} ms | "
                f"{pct(r.latencies_ms, 99) / pct(base.latencies_ms, 99):.2f}x | {100 * r.cpu_share:.1f}% | "
                f"{r.cpu_share / base.cpu_share:.2f}x |"
            )
    every = [v for r in fleet for v in r.latencies_ms]
    table = "\n".join(rows)
    print(table)
    summary = (
        f"All ten together: p99 {pct(every, 99):.1f} ms over {len(every)} reactions "
        f"({pct(every, 99) / pct(base.latencies_ms, 99):.2f}x one agent alone, p99 {pct(base.latencies_ms, 99):.1f} ms); "
        f"CPU per agent {100 * sum(r.cpu_share for r in fleet) / len(fleet):.1f}% of a core on average "
        f"({sum(r.cpu_share for r in fleet) / len(fleet) / base.cpu_share:.2f}x alone). "
        f"Load average while toggling: {load1:.1f} (1 agent), {load10:.1f} (10 agents)."
    )
    short = [r for r in fleet if len(r.latencies_ms) < args.changes]
    if short:
        summary += (
            f" {len(short)} of {len(fleet)} agents had fewer reactions than the {args.changes} changes: the rest"
            f" reached them after the phase had ended, or never (the broker fell behind the fan-out of"
            f" {args.nodes - 1} node messages per second to each of the {len(fleet)} agents)."
        )
    print(summary)
    if args.quick:
        check_ratio(
            f"zone message -> reacted p50, {len(fleet)} agents / 1 alone",
            pct(every, 50) / pct(base.latencies_ms, 50),
            10.0,
        )
        check_ratio(
            f"CPU per agent, {len(fleet)} agents / 1 alone",
            sum(r.cpu_share for r in fleet) / len(fleet) / base.cpu_share,
            3.0,
        )
        finish_quick()
    where = (
        "`wsnav broker run` (amqtt)"
        if args.broker == "amqtt"
        else "Mosquitto (`wsnav broker mosquitto-config`)"
    )
    text = f"""```
{COMMAND} --nodes {args.nodes} --changes {args.changes} --broker {args.broker}
```

The school map with its ten robots and {args.nodes} nodes ({args.nodes - 1} emulated at a 1 s heartbeat by one
ZoneSimulator process, all `clear`, and a probe node in z4 toggled `blocked`/`clear` every {INTERVAL_S} s,
{args.changes} times per phase), {where} as its own process; each agent in its own process in real
time, driving across the building with the robots layer on (the other robots' statuses at 2 Hz). Timed from
just before `publish()` to the navigator having decided; CPU is the agent process's (agent loop, paho thread,
its simulated TurtleBot3) per wall second. Phase 1: robot1 alone; phase 2: all ten, with the same nodes and
broker running. {machine_note()}; the machine was shared with other jobs, so read the ratios, not the absolute
numbers. Agent, nodes and broker all share the 2 cores here; on the robots each agent has its own.

{table}

{summary}
"""
    if not args.no_write:
        write_section(SECTION.format(broker=args.broker), text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
