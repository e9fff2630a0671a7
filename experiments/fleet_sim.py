"""A simulated fleet in one process: every robot of a site on its own simulated TurtleBot3 in one shared world
(each robot an obstacle for the others' lidars and bumpers), each driven by its own agent with its own
credentials and its own MQTT connection to a real broker, and optionally the site's emulated nodes.

Everything advances in lock-step simulated time (experiments.lockstep): after each step, simulated time waits
until every status an agent published has reached every other agent, so what each agent knows at each instant
does not depend on the machine's speed. `run(..., speed=1.0)` paces it to real time (`wsnav fleet --sim`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from wsnav.experiments.lockstep import Audience, Deliveries, ExpectingBus, FleetBus, settle
from wsnav.experiments.single_run import DT, TRAJECTORY_EVERY_S, BrokerAt
from wsnav.navigation.backend import Pose
from wsnav.navigation.navigator import GoalLabel
from wsnav.robot_agent.agent import RobotAgent
from wsnav.robot_agent.agent_config import AgentConfig
from wsnav.robot_agent.sim.lidar import LidarParams
from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3, TurtleBot3Params
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.runtime.clock import SimClock
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.messages import SimWorld
from wsnav.schemas.site import Site
from wsnav.zone_sim.emulated_node import Sent
from wsnav.zone_sim.sensor_model import SensorSettings
from wsnav.zone_sim.simulator import ZoneSimulator


class FleetError(ValueError):
    """A fleet that cannot start (a robot without a start point, ...): one line for the user."""


def start_poses(site: Site) -> dict[str, Pose]:
    """Each robot of the site at its `start` point; FleetError when one has none."""
    out: dict[str, Pose] = {}
    for robot in site.spec.robots:
        if robot.start is None:
            raise FleetError(f"site {site.name}: robot {robot.id} has no start point (robots[].start)")
        out[robot.id] = site.point(robot.start)
    if not out:
        raise FleetError(f"site {site.name} lists no robots")
    return out


@dataclass
class Member:
    """One robot of the fleet: the simulated TurtleBot3 and the agent that drives it."""

    robot: SimTurtleBot3
    agent: RobotAgent
    bus: FleetBus
    trajectory: list[tuple[float, float]] = field(default_factory=list)


class SimFleet:
    """The fleet, its shared world, and (with `nodes`) the site's emulated nodes, on one SimClock."""

    def __init__(
        self,
        site: Site,
        broker: BrokerAt,
        config: AgentConfig,
        poses: dict[str, Pose] | None = None,
        *,
        nodes: bool = False,
        seed: int = 0,
        drive: TurtleBot3Params | None = None,
        lidar: LidarParams | None = None,
        sensors: SensorSettings | None = None,
    ) -> None:
        self.site = site
        self.clock = SimClock()
        self.world = SimWorldGrid(site.grid)
        self.audience = Audience()
        self.members: dict[str, Member] = {}
        self._buses: list[MqttBus] = []
        poses = poses if poses is not None else start_poses(site)
        try:
            for i, (robot_id, pose) in enumerate(poses.items()):
                inner = self._connect(broker, robot_id, robot_id)
                deliveries = Deliveries([])
                self.audience.members.append(deliveries)
                bus = FleetBus(inner, deliveries, self.audience)
                robot = SimTurtleBot3(robot_id, self.world, pose, drive, lidar, seed=seed * 1000 + i)
                agent = RobotAgent(site, config, robot, bus, self.clock, robot_id, sim_world=self.world)
                deliveries.filters = agent.subscriptions()
                self.members[robot_id] = Member(robot, agent, bus, [pose[:2]])
            self.operator = ExpectingBus(self._connect(broker, "operator", "operator-fleet"), self.audience)
            self.zones: ZoneSimulator | None = None
            if nodes:
                self.zones = ZoneSimulator(
                    site,
                    broker.credentials_dir,
                    (broker.host, broker.port),
                    self.clock,
                    seed=seed,
                    sensor=sensors,
                    world_bus=self.operator,
                    on_sent=self._sent,
                )
        except BaseException:
            self.close()
            raise
        self._next_sample = TRAJECTORY_EVERY_S

    def _connect(self, broker: BrokerAt, ident: str, client_id: str) -> MqttBus:
        creds = load_credentials(broker.credentials_dir / f"{ident}.json")
        bus = connect_with_credentials(broker.host, broker.port, creds, client_id=client_id, clock=self.clock)
        self._buses.append(bus)
        return bus

    def _sent(self, sent: Sent) -> None:
        self.audience.expect(sent.topic, sent.payload)

    # -- lock-step ---------------------------------------------------------------------------------------

    def _poke(self) -> None:
        if self.zones is not None:
            self.zones.step(self.clock.now(), io_timeout_s=0.0)
        for m in self.members.values():
            m.bus.fetch()

    def _synced(self) -> bool:
        return self.audience.pending == 0

    def _settle(self, what: str) -> None:
        if not self._synced():
            settle(self._synced, self._poke, time.sleep, what)

    def start(self) -> None:
        """Connect the nodes, hand every agent the world, and let each publish its first status to the others."""
        if self.zones is not None:
            self.zones.start()
            zones = self.zones
            n = len(zones.nodes)
            settle(lambda: self._synced() and zones.online_count == n, self._poke, time.sleep, "the nodes")
        else:
            # Retained and subscribed last: once every agent has it, its other subscriptions are in place too.
            world = SimWorld(t=self.clock.now()).to_payload()
            self.operator.publish(topics.sim_world(self.site.name), world, qos=1, retain=True)
            settle(
                lambda: all(m.agent.stats.sim_worlds > 0 for m in self.members.values()),
                lambda: self._step_agents(),
                time.sleep,
                "the simulated world",
            )
        self._step_agents()
        self._settle("the first statuses")
        self._step_agents()

    def _step_agents(self) -> None:
        self._poke()
        for m in self.members.values():
            m.agent.step(self.clock.now())

    def set_goal(self, robot_id: str, goal: Pose, label: GoalLabel) -> None:
        self.members[robot_id].agent.set_goal(goal, label, self.clock.now())

    def step(self) -> None:
        """The agents decide at t, the robots move to t + DT, the nodes catch up; then every message is in."""
        now = self.clock.now()
        for m in self.members.values():
            m.agent.step(now)
        for m in self.members.values():
            m.robot.step(DT, now + DT)
        self.clock.advance(DT)
        if self.zones is not None:
            self.zones.step(self.clock.now(), io_timeout_s=0.0)
        self._settle("fleet messages")
        if self.clock.now() >= self._next_sample - 1e-9:
            for m in self.members.values():
                m.trajectory.append(m.robot.pose()[:2])
            self._next_sample += TRAJECTORY_EVERY_S

    def run(self, duration_s: float, speed: float = math.inf) -> None:
        """Step for `duration_s` simulated seconds, at most `speed` times real time (inf: as fast as it goes)."""
        t0, wall0 = self.clock.now(), time.monotonic()
        while self.clock.now() - t0 < duration_s - 1e-9:
            self.step()
            if math.isfinite(speed):
                ahead = (self.clock.now() - t0) / speed - (time.monotonic() - wall0)
                if ahead > 0:
                    time.sleep(ahead)

    # -- what it measured --------------------------------------------------------------------------------

    @property
    def collisions(self) -> int:
        return sum(m.robot.collisions for m in self.members.values())

    def min_separation_m(self) -> float:
        """Smallest gap between two robots' footprints right now (negative: overlapping)."""
        best = math.inf
        items = list(self.members.values())
        for i, a in enumerate(items):
            for b in items[i + 1 :]:
                (ax, ay, _), (bx, by, _) = a.robot.pose(), b.robot.pose()
                gap = math.hypot(ax - bx, ay - by) - a.robot.radius - b.robot.radius
                best = min(best, gap)
        return best

    def trajectories(self) -> dict[str, np.ndarray]:
        return {r: np.asarray(m.trajectory, dtype=np.float64) for r, m in self.members.items()}

    def close(self) -> None:
        if getattr(self, "zones", None) is not None:
            assert self.zones is not None
            self.zones.stop()
        for bus in self._buses:
            bus.close()
