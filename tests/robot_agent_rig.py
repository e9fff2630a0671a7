"""Shared by the robot agent's end-to-end tests (no tests here): the school site on the real broker, the agent on
robot1's MqttBus with a simulated TurtleBot3, driven in lock-step on a SimClock.

Whenever the test publishes something, it waits (in real time, with a timeout) until the agent's bus has
delivered it and the agent has taken it in, stepping the agent without advancing simulated time: so what the
agent sees at each simulated instant does not depend on the machine's speed.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

import numpy as np
from matplotlib.path import Path as MplPath

from tests.conftest import SCHOOL
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.navigation.backend import LaserScan
from wsnav.robot_agent.agent import RobotAgent
from wsnav.robot_agent.agent_config import AgentConfig, load_agent_config
from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.runtime.clock import SimClock
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.messages import RobotGoal, RobotStatus, SimObstacle, SimWorld, ZoneState, ZoneStateValue
from wsnav.schemas.site import load_site

DT = 0.05
REAL_TIMEOUT_S = 20.0
LIDAR_RANGE_M = 3.5


def connect(broker: BrokerThread, ident: str, clock: SimClock | None = None) -> MqttBus:
    return connect_with_credentials(broker.host, broker.port, broker.credentials(ident), clock=clock)


def distance_to_polygon(polygon: list[tuple[float, float]], x: float, y: float) -> float:
    """Metres from a point to a polygon (0 inside)."""
    pts = np.asarray(polygon, dtype=np.float64)
    if MplPath(pts).contains_point((x, y)):
        return 0.0
    best = np.inf
    for a, b in zip(pts, np.roll(pts, -1, axis=0), strict=True):
        ab = b - a
        t = float(np.clip(np.dot((x, y) - a, ab) / float(np.dot(ab, ab)), 0.0, 1.0))
        best = min(best, float(np.hypot(*((x, y) - (a + t * ab)))))
    return best


@dataclass
class Rig:
    tmp: Path
    config: AgentConfig | str = "full"
    start: str = "A"
    clock: SimClock = field(default_factory=SimClock)
    statuses: list[RobotStatus] = field(default_factory=list)
    """Every status the operator received over MQTT, in order."""
    trajectory: list[tuple[float, float, float]] = field(default_factory=list)

    def __enter__(self) -> Rig:
        self.site = load_site(SCHOOL)
        self.broker = BrokerThread(SCHOOL).__enter__()
        self.world = SimWorldGrid(self.site.grid)
        self.robot = SimTurtleBot3("robot1", self.world, self.site.point(self.start))
        self.agent_bus = connect(self.broker, "robot1", self.clock)
        config = load_agent_config(self.config) if isinstance(self.config, str) else self.config
        self.agent = RobotAgent(
            self.site, config, self.robot, self.agent_bus, self.clock, "robot1", sim_world=self.world
        )
        self.operator = connect(self.broker, "operator")
        self.operator.subscribe(topics.robot_status(self.site.name, "robot1"))
        self._nodes: dict[str, MqttBus] = {}
        self._seq: dict[str, int] = {}
        self.place_obstacles()  # retained: also a handshake that the agent's subscriptions are in place
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        for bus in [*self._nodes.values(), self.operator, self.agent_bus]:  # closing twice is harmless
            bus.close()
        self.broker.__exit__(kind, exc, tb)

    # -- publishing, each followed by a wait until the agent took it in -----------------------------------

    def node(self, node_id: str) -> MqttBus:
        if node_id not in self._nodes:
            self._nodes[node_id] = connect(self.broker, node_id)
        return self._nodes[node_id]

    def settle(self, done: Callable[[], bool], what: str) -> None:
        """Step the agent at the current simulated instant until `done()`; fail after a real-time timeout."""
        deadline = time.monotonic() + REAL_TIMEOUT_S
        while not done():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for the agent to receive {what}")
            self.agent_bus.wait(0.05)
            self.agent.step(self.clock.now())

    def set_zone(self, zone: str, state: ZoneStateValue) -> None:
        """Every node watching `zone` publishes `state` (retained, QoS 1, next seq), as the firmware does."""
        watchers = [n.id for n in self.site.spec.nodes if n.zone == zone]
        intake = self.agent.intake
        target = (intake.accepted if intake is not None else 0) + len(watchers)
        for node_id in watchers:
            self._seq[node_id] = self._seq.get(node_id, 100) + 1
            msg = ZoneState(zone=zone, node=node_id, state=state, seq=self._seq[node_id])
            topic = topics.zone_state(self.site.name, zone, node_id)
            self.node(node_id).publish(topic, msg.to_payload(), qos=1, retain=True)
        if intake is not None:  # an agent without a zone layer does not even subscribe
            self.settle(lambda: intake.accepted >= target, f"{zone} {state}")

    def place_obstacles(self, *zones: str) -> None:
        """The simulated world: an obstacle filling each zone (what the lidar and the bumper meet)."""
        obstacles = [
            SimObstacle(id=f"ob-{z}", zone=z, polygon=list(self.site.spec.zone(z).polygon)) for z in zones
        ]
        world = SimWorld(t=self.clock.now(), obstacles=obstacles)
        target = self.agent.stats.sim_worlds + 1
        self.operator.publish(topics.sim_world(self.site.name), world.to_payload(), qos=1, retain=True)
        self.settle(lambda: self.agent.stats.sim_worlds >= target, "the simulated world")

    def block(self, zone: str) -> None:
        self.place_obstacles(zone)
        self.set_zone(zone, "blocked")

    def send_goal(self, goal: str | tuple[float, float, float]) -> None:
        target = self.agent.stats.goals + 1
        payload = RobotGoal(goal=goal).to_payload()
        self.operator.publish(topics.robot_goal(self.site.name, "robot1"), payload, qos=1)
        self.settle(lambda: self.agent.stats.goals >= target, f"goal {goal}")

    # -- driving ------------------------------------------------------------------------------------------

    def drive(self, until: Callable[[], bool], max_sim_s: float = 400.0) -> None:
        """Lock-step: the agent decides at t, the robot moves to t + DT; stop when `until()` holds."""
        end = self.clock.now() + max_sim_s
        while not until():
            now = self.clock.now()
            if now > end:
                raise AssertionError(f"not done after {max_sim_s} simulated s: {self.agent.status(now)}")
            self.agent.step(now)
            self.robot.step(DT, now + DT)
            self.clock.advance(DT)
            self.trajectory.append(self.robot.pose())

    def state(self) -> str:
        return self.agent.navigator.state

    def finished(self) -> bool:
        return self.state() in ("arrived", "cancelled")

    def collect_statuses(self) -> list[RobotStatus]:
        """The statuses received so far over MQTT, up to the agent's latest change."""
        last = self.agent.status(self.clock.now())
        deadline = time.monotonic() + REAL_TIMEOUT_S
        while time.monotonic() < deadline:
            self.operator.wait(0.05)
            for m in self.operator.poll():
                self.statuses.append(RobotStatus.model_validate_json(m.payload))
            if self.statuses and (self.statuses[-1].state, self.statuses[-1].replans) == (
                last.state,
                last.replans,
            ):
                break
        return self.statuses


def scan_from(pose: tuple[float, float, float], ranges: dict[int, float], beams: int = 360) -> LaserScan:
    """An LDS-01-like sweep: beam i at yaw + i degrees; beams not given see nothing (+inf)."""
    r = np.full(beams, np.inf, dtype=np.float32)
    for i, value in ranges.items():
        r[i] = value
    return LaserScan(0.0, pose, 0.0, 2 * math.pi / beams, 0.12, 3.5, r)
