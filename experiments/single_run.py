"""One run of the experiment: the zone simulator's emulated nodes and the robot agent on a simulated TurtleBot3,
all talking through a real broker, advanced together on a SimClock as fast as the machine allows.

The run's zones are blocked at t=0 (the obstacle appears as the route starts; the nodes' detection delay is
part of what is measured) and cleared once the robot has stopped, so the next run starts from a clear world.
"""

from __future__ import annotations

import gc
import math
import resource
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from wsnav.experiments.lockstep import Deliveries, ExpectingBus, WatchedBus, settle
from wsnav.experiments.run_plan import RunSpec
from wsnav.experiments.run_record import RunRecorder, record_name
from wsnav.navigation.navigator import NavEvent
from wsnav.robot_agent.agent import RobotAgent
from wsnav.robot_agent.agent_config import load_agent_config
from wsnav.robot_agent.sim.lidar import LidarParams
from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3, TurtleBot3Params
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.runtime.clock import SimClock
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.site import Site
from wsnav.zone_sim.emulated_node import Sent
from wsnav.zone_sim.sensor_model import SensorSettings
from wsnav.zone_sim.simulator import ZoneSimulator

DT = 0.05
"""Physics and loop step (s, simulated): the agent and the nodes do whatever is due at each."""
TIMEOUT_SIM_S = 600.0
"""A run not finished after this much simulated time counts as a failure."""
TRAJECTORY_EVERY_S = 0.5
DRAIN_SIM_S = 3.0
"""After clearing: simulated time for the nodes to report `clear` (off delay + detection delay)."""
ROBOT = "robot1"

# What varies from run to run, as it does between two runs of a real robot (all seeded by the run's seed).
LIDAR = LidarParams(noise_std=0.005, noise_fraction=0.0175)
"""LDS-01 precision: +-10 mm near, +-3.5% beyond 0.5 m, read as two standard deviations."""
DRIVE = TurtleBot3Params(velocity_noise=0.03)
"""Wheel slip and motor response: the delivered velocity within a few per cent of the command."""
SENSORS = SensorSettings(detection_delay_s=0.5, detection_jitter_s=1.5)
"""Each node sees the obstacle 0.5-2.0 s after it appears."""
START_SIGMA_M = 0.05
START_SIGMA_RAD = 0.05
"""Where the robot stands at the start: the point give or take a few centimetres and degrees."""

COLUMNS = (
    "config",
    "route",
    "blocked",
    "run",
    "seed",
    "success",
    "collisions",
    "time_s",
    "distance_m",
    "replans",
    "recoveries",
    "stalled_s",
    "outcome",
    "recovery_log",
    "planning_ms",
    "agent_cpu_s",
    "process_cpu_s",
    "peak_mem_mb",
)
NONDETERMINISTIC = ("planning_ms", "agent_cpu_s", "process_cpu_s", "peak_mem_mb")
"""Columns that measure the machine rather than the run (the rest are the same for the same seed)."""


STALL_DISTANCE_M = 0.2
STALL_AFTER_S = 10.0
"""A stall: the robot not STALL_DISTANCE_M from where it was for at least STALL_AFTER_S (move_base's
oscillation_distance and oscillation_timeout), whatever it does meanwhile (turning, waiting, recovering)."""


class StallMeter:
    """Simulated time spent in stalls, measured on the robot's true pose alike for every configuration."""

    def __init__(self, t: float, xy: tuple[float, float]) -> None:
        self.stalled_s = 0.0
        self._t, self._xy = t, xy

    def update(self, t: float, xy: tuple[float, float]) -> None:
        if math.hypot(xy[0] - self._xy[0], xy[1] - self._xy[1]) >= STALL_DISTANCE_M:
            self.close(t)
            self._t, self._xy = t, xy

    def close(self, t: float) -> None:
        """Count the stretch since the last progress if it was a stall (at a move, and at the run's end)."""
        if t - self._t >= STALL_AFTER_S:
            self.stalled_s += t - self._t
        self._t = t


def outcome_of(state: str, reason: str | None) -> str:
    """How a run ended: arrived, timeout (the cap), aborted (move_base's recoveries all failed) or cancelled."""
    if state == "arrived":
        return "arrived"
    if state == "cancelled":
        return "aborted" if reason is not None and reason.startswith("aborted") else "cancelled"
    return "timeout"


def recovery_log(events: Iterable[NavEvent], t0: float) -> str:
    """The run's recovery behaviours and its abort, if any, as `t name (trigger); ...` (t from the goal)."""
    return "; ".join(
        f"{e.t - t0:.1f} {e.detail}"
        for e in events
        if e.kind == "recovery" or (e.kind == "cancelled" and (e.detail or "").startswith("aborted"))
    )


@dataclass(frozen=True)
class BrokerAt:
    host: str
    port: int
    credentials_dir: Path


@dataclass(frozen=True)
class RunResult:
    row: dict[str, object]
    trajectory: NDArray[np.float64]
    """(x, y) every TRAJECTORY_EVERY_S simulated seconds."""


def _connect(broker: BrokerAt, ident: str, client_id: str, clock: SimClock) -> MqttBus:
    creds = load_credentials(broker.credentials_dir / f"{ident}.json")
    return connect_with_credentials(broker.host, broker.port, creds, client_id=client_id, clock=clock)


PROC_SELF = Path("/proc/self")


def reset_peak_rss() -> None:
    """Start this run's resident-set peak afresh: first free what earlier runs left in reference cycles (the
    costmaps, plans and clients of a run hold each other; left to the collector's thresholds they piled up,
    and a worker's peak grew with its run order, 346 -> 712 MB over 225 runs), then (Linux) write 5 to
    clear_refs, which resets VmHWM; elsewhere the process's lifetime peak stays."""
    gc.collect()
    try:
        (PROC_SELF / "clear_refs").write_text("5")
    except OSError:
        return


def peak_rss_mb() -> float:
    """This process's resident-set peak since `reset_peak_rss` (VmHWM), or its lifetime peak (ru_maxrss)."""
    try:
        for line in (PROC_SELF / "status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def start_pose(site: Site, spec: RunSpec) -> tuple[float, float, float]:
    x, y, yaw = site.point(spec.start)
    dx, dy, dyaw = np.random.default_rng([spec.seed, 1]).standard_normal(3)
    return x + START_SIGMA_M * dx, y + START_SIGMA_M * dy, yaw + START_SIGMA_RAD * dyaw


def run_once(site: Site, spec: RunSpec, broker: BrokerAt, record: Path | None = None) -> RunResult:
    """One run; with `record`, a folder, also its MCAP record there (and nothing else changes: the recorder
    only reads)."""
    reset_peak_rss()
    clock = SimClock()
    world = SimWorldGrid(site.grid)
    robot = SimTurtleBot3(ROBOT, world, start_pose(site, spec), DRIVE, LIDAR, seed=spec.seed)
    config = load_agent_config(spec.config)
    inner = _connect(broker, ROBOT, ROBOT, clock)
    deliveries = Deliveries([])
    bus = WatchedBus(inner, deliveries)
    agent = RobotAgent(site, config, robot, bus, clock, ROBOT, sim_world=world)
    deliveries.filters = agent.subscriptions()
    world_bus = ExpectingBus(_connect(broker, "operator", "operator-experiment", clock), deliveries)

    def sent(s: Sent) -> None:
        deliveries.expect(s.topic, s.payload)

    sim = ZoneSimulator(
        site,
        broker.credentials_dir,
        (broker.host, broker.port),
        clock,
        seed=spec.seed,
        sensor=SENSORS,
        world_bus=world_bus,
        on_sent=sent,
    )
    try:
        if record is None:
            return _drive(site, spec, clock, robot, agent, sim, deliveries)
        with RunRecorder(record / f"{record_name(spec.config, spec.route, spec.run)}.mcap", spec) as recorder:
            bus.tap = recorder.messages
            result = _drive(site, spec, clock, robot, agent, sim, deliveries, recorder)
            recorder.result(result.row)
            return result
    finally:
        sim.stop()
        world_bus.close()
        inner.close()


def _drive(
    site: Site,
    spec: RunSpec,
    clock: SimClock,
    robot: SimTurtleBot3,
    agent: RobotAgent,
    sim: ZoneSimulator,
    deliveries: Deliveries,
    recorder: RunRecorder | None = None,
) -> RunResult:
    bus = agent.bus
    assert isinstance(bus, WatchedBus)

    def poke() -> None:
        sim.step(clock.now(), io_timeout_s=0.0)
        bus.fetch()

    def synced() -> bool:
        return deliveries.pending == 0

    sim.start()
    n_nodes = len(sim.nodes)
    settle(lambda: synced() and sim.online_count == n_nodes, poke, agent.bus.wait, "the nodes to come online")
    for zone in spec.blocked:
        sim.block(zone)
    settle(synced, poke, agent.bus.wait, "the blocked world")
    agent.step(clock.now())  # take in the world and the zone states before planning
    agent.set_goal(site.point(spec.goal), spec.goal, clock.now())
    cpu0 = agent.stats.cpu_s
    process_cpu0 = time.process_time()
    trajectory: list[tuple[float, float]] = [robot.pose()[:2]]
    stalls = StallMeter(clock.now(), robot.pose()[:2])
    next_sample = TRAJECTORY_EVERY_S
    t0 = clock.now()
    nav = agent.navigator
    while nav.state not in ("arrived", "cancelled") and clock.now() - t0 < TIMEOUT_SIM_S:
        now = clock.now()
        agent.step(now)
        robot.step(DT, now + DT)
        clock.advance(DT)
        stalls.update(clock.now(), robot.pose()[:2])
        if recorder is not None:
            recorder.navigator(now, nav.state, nav.path, nav.events)
            recorder.pose(clock.now(), *robot.pose())
        sim.step(clock.now(), io_timeout_s=0.0)
        if not synced():
            settle(synced, poke, agent.bus.wait, "zone messages")
        if clock.now() - t0 >= next_sample - 1e-9:
            trajectory.append(robot.pose()[:2])
            next_sample += TRAJECTORY_EVERY_S
    elapsed = clock.now() - t0
    process_cpu_s = time.process_time() - process_cpu0
    stalls.close(clock.now())
    trajectory.append(robot.pose()[:2])
    counters = agent.counters()
    row: dict[str, object] = {
        "config": spec.config,
        "route": spec.route,
        "blocked": spec.blocked_label,
        "run": spec.run,
        "seed": spec.seed,
        "success": nav.state == "arrived",
        "collisions": robot.collisions,
        "time_s": round(elapsed, 3),
        "distance_m": round(robot.distance_m, 3),
        "replans": int(counters["replans"]),
        "recoveries": int(counters["recoveries"]),
        "stalled_s": round(stalls.stalled_s, 3),
        "outcome": outcome_of(nav.state, nav.reason),
        "recovery_log": recovery_log(nav.events, t0),
        "planning_ms": float(counters["planning_ms"]),
        "agent_cpu_s": round(agent.stats.cpu_s - cpu0, 6),
        "process_cpu_s": round(process_cpu_s, 6),
        "peak_mem_mb": round(peak_rss_mb(), 1),
    }
    for zone in spec.blocked:
        sim.clear(zone)
    end = clock.now() + DRAIN_SIM_S
    while clock.now() < end:
        clock.advance(DT)
        poke()
        agent.step(clock.now())
    settle(synced, poke, agent.bus.wait, "the cleared world")
    return RunResult(row, np.asarray(trajectory, dtype=np.float64))
