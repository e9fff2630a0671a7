"""The fleet scenario: every robot of a site on random goals among the site's points for a stretch of simulated
time, zones raffled and cleared as it goes (the emulated nodes report them), in lock-step over a real broker.

What it measures, per configuration: collisions (must be 0), deadlocks (a robot with a goal that has not moved
`DEADLOCK_M` in `DEADLOCK_S`), goals reached per hour, and each robot's distance, yields and agent CPU. The
goals and the zone schedule are drawn from the seed alone, so two configurations face the same raffles.
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from wsnav.experiments.fleet_sim import SimFleet, start_poses
from wsnav.experiments.single_run import DRIVE, LIDAR, SENSORS, BrokerAt
from wsnav.robot_agent.agent_config import load_agent_config
from wsnav.schemas.site import Site

DEADLOCK_S = 60.0
DEADLOCK_M = 0.5
"""A robot with a goal that moved less than this in DEADLOCK_S simulated seconds is deadlocked."""
ZONE_FIRST_S = 30.0
ZONE_HOLD_S = (40.0, 90.0)
ZONE_GAP_S = (10.0, 40.0)
"""One zone blocked at a time: the first 30 s in, each for 40-90 s, the next 10-40 s after it cleared."""
GOAL_CLEARANCE_M = 1.0
"""A goal is never a point another robot stands on (within this) or is already heading to."""


@dataclass(frozen=True)
class ZoneEvent:
    t: float
    action: str
    """`block` or `clear`."""
    zone: str


def zone_schedule(site: Site, duration_s: float, seed: int) -> list[ZoneEvent]:
    """The raffled zones: which zone is blocked when, the same for every configuration of one seed."""
    rng = random.Random(seed)
    zones = [z.id for z in site.spec.zones]
    out: list[ZoneEvent] = []
    t = ZONE_FIRST_S
    while t < duration_s:
        zone = rng.choice(zones)
        end = t + rng.uniform(*ZONE_HOLD_S)
        out += [ZoneEvent(t, "block", zone), ZoneEvent(min(end, duration_s), "clear", zone)]
        t = end + rng.uniform(*ZONE_GAP_S)
    return out


@dataclass
class RobotTally:
    goals_set: int = 0
    goals_reached: int = 0
    goals_cancelled: int = 0
    deadlocks: int = 0
    yields: int = 0
    stuck_since: float | None = None
    """Start of the current stretch without progress (None: moving, or no goal)."""
    anchor: tuple[float, float] = (0.0, 0.0)
    """Where that stretch started."""


@dataclass
class FleetResult:
    config: str
    duration_s: float
    rows: list[dict[str, object]]
    """One per robot: distance, goals, deadlocks, yields, collisions, CPU."""
    trajectories: dict[str, NDArray[np.float64]]
    collisions: int
    deadlocks: int
    goals_reached: int
    min_separation_m: float
    wall_s: float
    zone_events: list[ZoneEvent] = field(default_factory=list)

    @property
    def goals_per_hour(self) -> float:
        return self.goals_reached * 3600.0 / self.duration_s


def run_fleet(
    site: Site,
    broker: BrokerAt,
    config_name: str,
    duration_s: float,
    seed: int,
    progress: Callable[[str], None] | None = None,
) -> FleetResult:
    """All the site's robots on random goals for `duration_s` simulated seconds under one agent config."""
    fleet = SimFleet(
        site,
        broker,
        load_agent_config(config_name),
        start_poses(site),
        nodes=True,
        seed=seed,
        drive=DRIVE,
        lidar=LIDAR,
        sensors=SENSORS,
    )
    wall0 = time.monotonic()
    try:
        fleet.start()
        return _drive(site, fleet, config_name, duration_s, seed, progress, wall0)
    finally:
        fleet.close()


def _drive(
    site: Site,
    fleet: SimFleet,
    config_name: str,
    duration_s: float,
    seed: int,
    progress: Callable[[str], None] | None,
    wall0: float,
) -> FleetResult:
    rng = random.Random(seed * 7919 + 1)
    points = sorted(site.spec.points)
    tally = {r: RobotTally() for r in fleet.members}
    events = zone_schedule(site, duration_s, seed)
    pending = list(events)
    assert fleet.zones is not None
    zones = fleet.zones
    t0 = fleet.clock.now()
    closest = math.inf
    next_report = 60.0
    last_state = {r: m.agent.navigator.state for r, m in fleet.members.items()}
    while fleet.clock.now() - t0 < duration_s - 1e-9:
        now = fleet.clock.now()
        elapsed = now - t0
        while pending and pending[0].t <= elapsed + 1e-9:
            ev = pending.pop(0)
            (zones.block if ev.action == "block" else zones.clear)(ev.zone)
        for robot, m in fleet.members.items():
            nav = m.agent.navigator
            t = tally[robot]
            if nav.state != last_state[robot]:
                t.goals_reached += nav.state == "arrived"
                t.goals_cancelled += nav.state == "cancelled"
                last_state[robot] = nav.state
            if nav.state in ("idle", "arrived", "cancelled"):
                goal = _pick_goal(site, fleet, robot, points, rng)
                if goal is not None:
                    fleet.set_goal(robot, site.point(goal), goal)
                    t.goals_set += 1
                    t.stuck_since = None
                    last_state[robot] = nav.state
            _watch_progress(t, m.robot.pose()[:2], nav.active, now)
        fleet.step()
        closest = min(closest, fleet.min_separation_m())
        if progress is not None and elapsed >= next_report:
            reached = sum(t.goals_reached for t in tally.values())
            progress(
                f"{config_name}: {elapsed:.0f}/{duration_s:.0f} s simulated, {reached} goals reached, "
                f"{fleet.collisions} collisions, {time.monotonic() - wall0:.0f} s wall"
            )
            next_report += 60.0
    rows = []
    for robot, m in fleet.members.items():
        t = tally[robot]
        t.yields = sum(1 for e in m.agent.navigator.events if e.trigger == "yield" and e.kind == "waiting")
        rows.append(
            {
                "config": config_name,
                "robot": robot,
                "distance_m": round(m.robot.distance_m, 2),
                "goals_set": t.goals_set,
                "goals_reached": t.goals_reached,
                "goals_cancelled": t.goals_cancelled,
                "deadlocks": t.deadlocks,
                "yields": t.yields,
                "collisions": m.robot.collisions,
                "agent_cpu_s": round(m.agent.stats.cpu_s, 2),
            }
        )
    return FleetResult(
        config=config_name,
        duration_s=duration_s,
        rows=rows,
        trajectories=fleet.trajectories(),
        collisions=fleet.collisions,
        deadlocks=sum(t.deadlocks for t in tally.values()),
        goals_reached=sum(t.goals_reached for t in tally.values()),
        min_separation_m=closest,
        wall_s=time.monotonic() - wall0,
        zone_events=events,
    )


def _watch_progress(t: RobotTally, xy: tuple[float, float], active: bool, now: float) -> None:
    """Count a deadlock once per stretch of DEADLOCK_S with a goal and under DEADLOCK_M of movement."""
    if not active:
        t.stuck_since = None
        return
    if t.stuck_since is None or math.hypot(xy[0] - t.anchor[0], xy[1] - t.anchor[1]) >= DEADLOCK_M:
        t.stuck_since, t.anchor = now, xy
        return
    if now - t.stuck_since >= DEADLOCK_S:
        t.deadlocks += 1
        t.stuck_since, t.anchor = now, xy  # the next one only after another DEADLOCK_S without progress


def _pick_goal(site: Site, fleet: SimFleet, robot: str, points: list[str], rng: random.Random) -> str | None:
    """A random point no robot stands on or is heading to, other than where this robot is."""
    taken = {
        m.agent.navigator.goal_label
        for r, m in fleet.members.items()
        if r != robot and m.agent.navigator.active and isinstance(m.agent.navigator.goal_label, str)
    }
    stands = [m.robot.pose()[:2] for m in fleet.members.values()]
    free = [
        p
        for p in points
        if p not in taken
        and all(math.hypot(site.point(p)[0] - x, site.point(p)[1] - y) >= GOAL_CLEARANCE_M for x, y in stands)
    ]
    return rng.choice(free) if free else None
