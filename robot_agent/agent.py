"""The robot agent: MQTT in (zone states through the validating intake, goals, the simulated world), the
layered costmap, the navigator, and the robot's status out on `robots/<id>/status`.

`step(now)` does everything due at `now` and never blocks, so the experiment can drive it in lock-step with a
simulated robot on a SimClock; `run` is the real-time loop, asleep on the bus between ticks so a zone message
is acted on as soon as it arrives. Nothing a message carries can raise out of `step`: bad payloads are dropped
and counted by reason.

Status is published retained (an operator's dashboard that connects late sees at once where each robot is and
what it is doing, and `t` says how old that is): QoS 1 on every change (state, reason, goal, replans, blocked
zones), QoS 0 for the 2 Hz repeats in between.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from wsnav.navigation.backend import Pose, RobotBackend
from wsnav.navigation.behaviors.escape import ZoneEscape
from wsnav.navigation.behaviors.right_of_way import must_yield_to, yield_reason
from wsnav.navigation.control.controller import ControllerParams, PathFollower
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.costmap.layers import OtherRobot, RobotsLayer
from wsnav.navigation.costmap.local_costmap import LocalCostmap
from wsnav.navigation.navigator import GoalLabel, Navigator, NavigatorParams
from wsnav.navigation.planning.global_planner import GlobalPlanner
from wsnav.robot_agent.agent_config import AgentConfig
from wsnav.runtime.bus import Bus, Message
from wsnav.runtime.clock import Clock
from wsnav.runtime.drop_log import DropLog
from wsnav.runtime.timers import Every
from wsnav.schemas import topics
from wsnav.schemas.goal_check import GoalRefused, read_goal
from wsnav.schemas.messages import (
    MAX_OPERATOR_PAYLOAD_BYTES,
    OPERATOR_CANCEL_REASON,
    ROBOT_PATH_POINTS,
    PayloadError,
    RobotStatus,
    SimWorld,
    parse_payload,
)
from wsnav.schemas.site import Site
from wsnav.zones.geometry import GridFrame
from wsnav.zones.intake import ZoneIntake
from wsnav.zones.last_known import LastKnownZones
from wsnav.zones.zone_rule import ZoneRule

log = logging.getLogger(__name__)


def path_ahead(path: NDArray[np.float64], x: float, y: float) -> list[tuple[float, float]] | None:
    """The plan from its point nearest the robot to the goal, thinned evenly to the status's point budget."""
    if len(path) == 0:
        return None
    ahead = path[int(np.argmin(np.hypot(path[:, 0] - x, path[:, 1] - y))) :]
    if len(ahead) > ROBOT_PATH_POINTS:  # (a plan's vertices are mostly fewer: then all of them, as they are)
        ahead = ahead[np.unique(np.linspace(0, len(ahead) - 1, ROBOT_PATH_POINTS).round().astype(int))]
    return [(round(px, 2), round(py, 2)) for px, py in ahead.tolist()]


class SimWorldSink(Protocol):
    """The simulated world the sim backend's lidar and bumper see (wsnav.robot_agent.sim.world_grid.SimWorldGrid)."""

    def apply(self, world: SimWorld) -> None: ...


@dataclass(frozen=True)
class ZoneReaction:
    """A batch of zone messages that changed the costmap, and when the agent had acted on it."""

    received_at: float
    """The bus's stamp on the earliest message of the batch that changed the zone layer."""
    done_at: float
    """Clock time once the navigator had decided (replanned, waited or cancelled)."""
    replanned: bool


@dataclass
class AgentStats:
    steps: int = 0
    messages: int = 0
    cpu_s: float = 0.0
    """CPU time of the agent's own work (thread time inside `step`), what the experiment compares."""
    costmap_scans: int = 0
    zone_updates: int = 0
    statuses: int = 0
    goals: int = 0
    sim_worlds: int = 0
    robot_statuses: int = 0
    """Other robots' statuses taken into the robots layer."""
    dropped: Counter[str] = field(default_factory=Counter)
    """Messages the agent itself dropped (goals, simulated world, unexpected topics), by reason."""


class RobotAgent:
    def __init__(
        self,
        site: Site,
        config: AgentConfig,
        backend: RobotBackend,
        bus: Bus,
        clock: Clock,
        robot_id: str | None = None,
        *,
        sim_world: SimWorldSink | None = None,
        on_status: Callable[[RobotStatus, bool], None] | None = None,
        zone_memory: LastKnownZones | None = None,
    ) -> None:
        """`sim_world`: where `sim/world` messages go when the backend is the simulator (subscribed only then).
        `on_status(status, changed)` sees every status published (for a console line, a test, a log).
        `zone_memory`: the last known zone states on disk (`--state-dir`): the agent starts from them."""
        self.site = site
        self.config = config
        self.backend = backend
        self.bus = bus
        self.clock = clock
        self.robot_id = robot_id or backend.robot_id
        robots = {r.id: r for r in site.spec.robots}
        if self.robot_id not in robots:
            known = ", ".join(robots) or "none"
            raise ValueError(f"robot {self.robot_id!r} is not in site {site.name!r} (robots: {known})")
        radius = max(robots[self.robot_id].footprint_radius, backend.radius)
        self.radius = radius
        self.priority = list(robots).index(self.robot_id)
        """Place in the site's robot list: the order of right of way (wsnav.navigation.behaviors.right_of_way)."""
        self.fleet: dict[str, tuple[int, float]] = {}
        """The other robots whose status this agent follows: id -> (priority, the site's footprint radius)."""
        if config.fleet_layer:
            self.fleet = {
                r.id: (i, r.footprint_radius) for i, r in enumerate(robots.values()) if r.id != self.robot_id
            }
        self.robots_layer = RobotsLayer(GridFrame.of_grid(site.grid)) if self.fleet else None
        inflation = config.inflation.params(radius)
        self.zone_layer: ZoneRule | None = None
        self.intake: ZoneIntake | None = None
        plugins = config.layer_plugins()
        if "zone_layer" in plugins:
            self.zone_layer = ZoneRule(site.spec, GridFrame.of_grid(site.grid), site.spec.policy)
            self.intake = ZoneIntake(site.spec, self.zone_layer, memory=zone_memory)
            self.intake.restore(clock.now())
        self.costmap = LayeredCostmap(
            site.grid,
            inflation,
            zone_layer=self.zone_layer,
            obstacle_layer=config.obstacle_layer,
            robots_layer=self.robots_layer,
            plugins=plugins,
        )
        self.local_costmap: LocalCostmap | None = None
        """The controller's own rolling-window costmap, when the configuration names its layers."""
        if config.local_plugins is not None:
            self.local_costmap = LocalCostmap(
                self.costmap, config.local_costmap_size_m, inflation, config.local_plugins
            )
        controller = PathFollower(
            ControllerParams(
                inscribed_radius=radius,
                inflation_cost_scaling_factor=config.inflation.cost_scaling_factor,
                control_dt=1.0 / config.controller_rate_hz,
            )
        )
        self.navigator = Navigator(
            self.costmap,
            GlobalPlanner(config.planner.params(), config.planner.downsample),
            controller,
            backend,
            NavigatorParams(
                controller_rate_hz=config.controller_rate_hz,
                replan_rate_hz=config.replan_rate_hz,
                waiting_retry_s=config.waiting_retry_s,
                blocked_replan_interval_s=config.blocked_replan_interval_s,
                zone_replan_interval_s=config.zone_replan_interval_s,
                local_costmap_size_m=config.local_costmap_size_m,
                recovery=config.recovery.params(),
            ),
            blocked_zones=self.blocked_zones,
            escape=ZoneEscape(self.costmap) if self.zone_layer is not None else None,
            local_costmap=self.local_costmap,
        )
        self.sim_world = sim_world
        self.on_status = on_status
        self.stats = AgentStats()
        self._drops = DropLog(log, self.robot_id, "messages", counts=self.stats.dropped)
        """The agent's own drops (goals, other robots' statuses, the simulated world), logged rate-limited."""
        self._link_up: bool | None = None
        self._link_down_since = 0.0
        self._retained_poses: set[str] = set()
        """Robots whose pose held now came retained (a last word from before): the next live one replaces it."""
        self._yielding_since: dict[str, float] = {}
        """The robot this one yields to now, and since when (at most one)."""
        self._yielded_enough: set[str] = set()
        """Robots yielded to for `max_yield_s`: no longer given the right of way until a new goal."""
        self.zone_reactions: list[ZoneReaction] = []
        self.status_topic = topics.robot_status(site.name, self.robot_id)
        self.goal_topic = topics.robot_goal(site.name, self.robot_id)
        self.sim_world_topic = topics.sim_world(site.name)
        self.fleet_topics = {topics.robot_status(site.name, r): r for r in self.fleet}
        self._costmap_timer = Every(config.global_costmap_rate_hz)
        self._local_timer = Every(config.local_costmap_rate_hz)
        self._zone_timer = Every(config.zone_refresh_rate_hz)
        self._status_timer = Every(config.status_rate_hz)
        self._last_status: tuple[object, ...] | None = None
        for topic_filter in self.subscriptions():
            bus.subscribe(topic_filter, qos=1)

    def subscriptions(self) -> list[str]:
        subs = list(self.intake.subscriptions()) if self.intake is not None else []
        subs.append(self.goal_topic)
        subs.extend(self.fleet_topics)
        if self.sim_world is not None:
            subs.append(self.sim_world_topic)
        return subs

    # -- what the experiment and the status read ---------------------------------------------------------

    def blocked_zones(self) -> list[str]:
        return self.zone_layer.blocked_zones() if self.zone_layer is not None else []

    def dropped(self) -> Counter[str]:
        """Every message dropped so far, by reason: the intake's and the agent's own."""
        out: Counter[str] = Counter(self.stats.dropped)
        if self.intake is not None:
            out.update(self.intake.dropped)
        return out

    def counters(self) -> dict[str, float | int]:
        """What the experiment records per run (planning time in ms, agent CPU in s)."""
        nav = self.navigator
        out: dict[str, float | int] = {
            "plans": nav.plans,
            "replans": nav.replans,
            "planning_ms": round(nav.planning_ms, 3),
            "cpu_s": self.stats.cpu_s,
            "plan_length_m": nav.plan_length_m if nav.plan_length_m is not None else float("nan"),
            "messages": self.stats.messages,
            "zone_updates": self.stats.zone_updates,
            "costmap_scans": self.stats.costmap_scans,
        }
        out["recoveries"] = nav.recovery.run if nav.recovery is not None else 0
        out.update({f"replans_{k}": v for k, v in nav.replans_by.items()})
        out.update({f"dropped_{k}": v for k, v in self.dropped().items()})
        return out

    def status(self, now: float) -> RobotStatus:
        nav = self.navigator
        x, y, yaw = self.backend.pose()
        goal = nav.goal_label
        return RobotStatus(
            robot=self.robot_id,
            state=nav.state,
            pose=(round(x, 3), round(y, 3), round(yaw, 3)),
            goal=goal if isinstance(goal, str) or goal is None else (goal[0], goal[1], goal[2]),
            blocked_zones=self.blocked_zones(),
            replans=nav.replans,
            plan_length_m=round(nav.plan_length_m, 3) if nav.plan_length_m is not None else None,
            reason=nav.reason[:200] if nav.reason else None,
            path=path_ahead(nav.path, x, y) if nav.state == "navigating" else None,
            t=round(now, 3),
            footprint_radius=round(self.radius, 3),
        )

    # -- commands from code (the CLI, the experiment) ----------------------------------------------------

    def set_goal(self, goal: Pose, label: GoalLabel, now: float) -> None:
        self.stats.goals += 1
        self._yielded_enough.clear()
        self.navigator.set_goal(goal, label, now)

    # -- the loop -----------------------------------------------------------------------------------------

    def step(self, now: float) -> None:
        """Everything due at `now`: inbound messages, costmap updates, navigation, status. Never blocks."""
        t0 = time.thread_time()
        self.stats.steps += 1
        goal: tuple[Pose, GoalLabel] | None = None
        cancel = False
        zones_changed_at = math.inf
        self._watch_link(now)
        self._drops.flush(now)
        for message in self.bus.poll():
            self.stats.messages += 1
            if message.topic == self.goal_topic:
                parsed = self._goal_of(message)
                if isinstance(parsed, tuple):
                    goal, cancel = parsed, False
                elif parsed == "cancel":
                    goal, cancel = None, True
            elif message.topic == self.sim_world_topic and self.sim_world is not None:
                self._apply_world(message)
            elif message.topic in self.fleet_topics:
                self._take_robot_status(message)
            elif self.intake is not None:
                if self.intake.handle(message):
                    zones_changed_at = min(zones_changed_at, message.received_at)
            else:
                self._drops.drop("unexpected_topic", now, message.topic, "not a topic the agent reads")
        if self.zone_layer is not None and (zones_changed_at < math.inf or self._zone_timer.due(now)):
            self._update_zones(now, zones_changed_at, react=goal is None and not cancel)
        if cancel:
            self.navigator.cancel(now, OPERATOR_CANCEL_REASON)
        elif goal is not None:
            self.set_goal(goal[0], goal[1], now)
        if self.config.obstacle_layer and self._costmap_timer.due(now):
            scan = self.backend.scan()
            if scan is not None:
                self.stats.costmap_scans += 1
                self.costmap.update_scan(scan)
        if self.robots_layer is not None:
            self._update_fleet(now)
        if self.local_costmap is not None and self._local_timer.due(now):
            self.local_costmap.update(self.backend.pose(), self.backend.scan())
        self.navigator.step(now)
        self._publish_status(now)
        self.stats.cpu_s += time.thread_time() - t0

    def _update_zones(self, now: float, changed_at: float, *, react: bool) -> None:
        """Fold the zone layer into the costmap; on a change, let the navigator act at once (unless a goal
        arriving in the same batch is about to be planned over the new costs anyway)."""
        if self.costmap.update_zones(now) is None:
            return
        self.stats.zone_updates += 1
        if react:
            replans = self.navigator.replans
            self.navigator.on_zones_changed(now)
            self.zone_reactions.append(
                ZoneReaction(min(changed_at, now), self.clock.now(), self.navigator.replans > replans)
            )

    def next_due(self) -> float:
        """The earliest clock time at which `step` has timed work to do."""
        due = min(self.navigator.next_due(), self._status_timer.next)
        if self.config.obstacle_layer:
            due = min(due, self._costmap_timer.next)
        if self.local_costmap is not None:
            due = min(due, self._local_timer.next)
        if self.zone_layer is not None:
            due = min(due, self._zone_timer.next)
        return due

    def run(
        self,
        stop: threading.Event,
        world_tick: Callable[[float], float] | None = None,
        max_sleep_s: float = 0.1,
    ) -> None:
        """Real time: step whenever work is due or a message arrives, sleeping on the bus in between.

        `world_tick(now) -> next time it wants to run` lets the owner of a simulated robot advance it in the
        same loop (the agent itself never steps a robot).
        """
        while not stop.is_set():
            now = self.clock.now()
            self.step(now)  # first: a message that woke us is acted on before the world moves on
            world_next = world_tick(now) if world_tick is not None else math.inf
            wait = min(self.next_due(), world_next) - self.clock.now()
            if wait > 0:
                self.bus.wait(min(wait, max_sleep_s))

    # -- inbound ------------------------------------------------------------------------------------------

    def _goal_of(self, message: Message) -> tuple[Pose, GoalLabel] | str | None:
        """The goal a goal message names, "cancel", or None (dropped and counted: schemas.goal_check)."""
        try:
            return read_goal(self.site, message.payload)
        except GoalRefused as refused:
            self._drops.drop(f"goal_{refused.kind}", message.received_at, message.topic, str(refused))
            return None

    def _take_robot_status(self, message: Message) -> None:
        """Another robot's status: its footprint goes into the robots layer until the pose is too old."""
        assert self.robots_layer is not None
        robot = self.fleet_topics[message.topic]
        try:
            status = parse_payload(RobotStatus, message.payload)
        except PayloadError as exc:
            self._drops.drop("robot_status_invalid", message.received_at, message.topic, str(exc))
            return
        x, y, yaw = status.pose
        if status.robot != robot:
            detail = f"payload says robot {status.robot!r}"
            self._drops.drop("robot_status_invalid", message.received_at, message.topic, detail)
            return
        if not self.site.grid.contains(x, y):
            detail = f"pose [{x:g}, {y:g}] lies off the map"
            self._drops.drop("robot_status_off_map", message.received_at, message.topic, detail)
            return
        # Judged by the older of arrival and making: a retained status from a robot long gone is not kept.
        made = min(message.received_at, status.t if status.t is not None else math.inf)
        priority, site_radius = self.fleet[robot]
        before = self.robots_layer.robots.get(robot)
        if before is not None and robot not in self._retained_poses:  # a retained word is no baseline
            made_before = before.expires_at - self.config.robot_pose_timeout_s
            reach = self.config.max_robot_speed_mps * max(made - made_before, 0.0) + 2 * site_radius
            if math.hypot(x - before.pose[0], y - before.pose[1]) > reach:
                detail = f"pose [{x:g}, {y:g}] jumped farther than it can drive"
                self._drops.drop("robot_status_jump", message.received_at, message.topic, detail)
                return
        if message.retain:
            self._retained_poses.add(robot)
        else:
            self._retained_poses.discard(robot)
        self.robots_layer.put(
            OtherRobot(
                robot=robot,
                pose=(x, y, yaw),
                radius=site_radius,  # the site's, not the status's: a status cannot make a robot wider
                state=status.state,
                priority=priority,
                expires_at=made + self.config.robot_pose_timeout_s,
            )
        )
        self.stats.robot_statuses += 1

    def _watch_link(self, now: float) -> None:
        """One line when the broker link goes down (with what the robot then does about zones), one when it is
        back: the bus itself only counts the statuses it could not send."""
        up = self.bus.connected
        if up == self._link_up:
            return
        was, self._link_up = self._link_up, up
        if not up:
            self._link_down_since = now
            policy = self.site.spec.policy
            meaning = {
                "keep": "each zone keeps its last state",
                "unknown": "they count as unknown",
                "lethal": "they count as blocked",
            }[policy.stale]
            log.warning(
                "%s: broker link down: no zone states, goals or statuses arrive and this robot's statuses are not "
                "sent; zones turn stale after %g heartbeats and the stale policy '%s' applies (%s)",
                self.robot_id,
                policy.stale_after_heartbeats,
                policy.stale,
                meaning,
            )
        elif was is not None:
            log.warning(
                "%s: broker link back after %.0f s: zone states and goals arrive again",
                self.robot_id,
                now - self._link_down_since,
            )

    def _update_fleet(self, now: float) -> None:
        """Other robots: expire old poses, fold the layer's changes into the costmap, apply the right of way."""
        assert self.robots_layer is not None
        self.robots_layer.expire(now)
        if self.robots_layer.changed:
            self.costmap.update()
        nav = self.navigator
        if self.config.yield_distance_m <= 0 or nav.state not in ("navigating", "waiting"):
            return
        others = [o for o in self.robots_layer.robots.values() if o.robot not in self._yielded_enough]
        other = must_yield_to(self.backend.pose(), self.priority, others, self.config.yield_distance_m)
        if other is not None:
            since = self._yielding_since.setdefault(other.robot, now)
            if now - since > self.config.max_yield_s:
                self._yielded_enough.add(other.robot)
                log.warning(
                    "%s: yielded to %s for %.0f s; planning round it instead",
                    self.robot_id,
                    other.robot,
                    now - since,
                )
                other = None
        for robot in list(self._yielding_since):
            if other is None or robot != other.robot:
                del self._yielding_since[robot]
        if other is not None:
            nav.hold(now, yield_reason(other))
        elif nav.holding is not None:
            nav.release(now)

    def _apply_world(self, message: Message) -> None:
        assert self.sim_world is not None
        try:
            world = parse_payload(SimWorld, message.payload, max_bytes=MAX_OPERATOR_PAYLOAD_BYTES * 8)
        except PayloadError as exc:
            self._drops.drop("sim_world_invalid", message.received_at, message.topic, str(exc))
            return
        self.sim_world.apply(world)
        self.stats.sim_worlds += 1

    # -- outbound -----------------------------------------------------------------------------------------

    def _publish_status(self, now: float) -> None:
        nav = self.navigator
        key = (nav.state, nav.reason, nav.goal_label, nav.replans, tuple(self.blocked_zones()))
        changed = key != self._last_status
        if not changed and not self._status_timer.due(now):
            return
        if changed:
            self._last_status = key
            self._status_timer.start(now)
        status = self.status(now)
        self.bus.publish(self.status_topic, status.to_payload(), qos=1 if changed else 0, retain=True)
        self.stats.statuses += 1
        if self.on_status is not None:
            self.on_status(status, changed)
