"""The zone simulator: a world, its emulated nodes and a scenario, advanced together on one clock.

    sim = ZoneSimulator(site, credentials_dir, ("127.0.0.1", 1883), clock, scenario, seed=7)
    sim.start()                 # loads every node's config.json, starts connecting (non-blocking)
    sim.step(clock.now())       # lock-step: advance everything to the clock's time, handle I/O, never block
    sim.block("z4"); sim.clear("z4"); sim.kill_node("n5"); sim.reboot_node("n5")
    sim.run(duration_s=60)      # or: real time on its own (sleeps on the sockets between steps)
    sim.stop()                  # power off: links cut, the broker publishes every node's `offline`

Single-threaded and not thread-safe: call everything from the thread that steps it. The world is published
retained on `sim/world` with the operator's credentials whenever it changes, for simulated lidars.
"""

from __future__ import annotations

import json
import random
import resource
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from wsnav.runtime.bus import Bus
from wsnav.runtime.clock import Clock
from wsnav.runtime.mqtt_bus import BusError, MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.credentials import CredentialsError, load_credentials, tool_login
from wsnav.schemas.site import Site
from wsnav.zone_sim.emulated_node import EmulatedNode, Power, Sent
from wsnav.zone_sim.firmware_modules import ConfigError, parse_node_config
from wsnav.zone_sim.links import LinkLoop
from wsnav.zone_sim.scenario import Event, Scenario
from wsnav.zone_sim.sensor_model import SensorSettings, SimulatedSensor
from wsnav.zone_sim.world import World, WorldError

OPERATOR = "operator"
OPERATOR_CONNECT_TIMEOUT_S = 10.0
"""How long start() waits for the broker before giving up with one line."""
LOOP_MS = 50
"""firmware/device/app.py's _LOOP_MS: one sensor reading per loop iteration."""
MAX_CONNECTING = 32
"""Connect attempts in flight at once: 1000 nodes join in waves, not one storm of argon2 checks."""


class SimulatorError(Exception):
    """Cannot start (bad credentials file, broker unreachable, unknown id); one line for the user."""


@dataclass
class SimStats:
    published: int = 0
    world_updates: int = 0
    link_failures: int = 0
    events: list[str] = field(default_factory=list)


class ZoneSimulator:
    def __init__(
        self,
        site: Site,
        credentials_dir: Path,
        broker: tuple[str, int],
        clock: Clock,
        scenario: Scenario | None = None,
        *,
        seed: int = 0,
        sensor: SensorSettings | None = None,
        sample_ms: int = LOOP_MS,
        world_bus: Bus | None = None,
        on_sent: Callable[[Sent], None] | None = None,
        log: Callable[[str], None] | None = None,
        nodes: list[str] | None = None,
    ) -> None:
        """`sensor` overrides the scenario's sensor settings; `world_bus` replaces the operator connection the
        world is published on; `on_sent` sees every publication as it leaves a node; `nodes` limits which of
        the site's nodes run (default: all)."""
        self.site = site
        self.spec = site.spec
        self.clock = clock
        self.scenario = scenario or Scenario()
        self.seed = seed
        self._credentials_dir = credentials_dir
        self._broker = broker
        self._sample_ms = sample_ms
        self._settings = sensor or SensorSettings(
            self.scenario.sensor.detection_delay_s, self.scenario.sensor.miss_rate
        )
        self._on_sent = on_sent
        self._log = log or (lambda _line: None)
        self._world_bus = world_bus
        self._own_world_bus: MqttBus | None = None
        self.world = World(self.spec)
        self.links = LinkLoop()
        self.nodes: dict[str, EmulatedNode] = {}
        self._only = nodes
        self._timeline: deque[Event] = deque(self.scenario.timeline(self.spec, seed))
        self._t0: float | None = None
        self._now = 0.0
        self._world_dirty = False
        self.stats = SimStats()

    # -- set-up --------------------------------------------------------------------------------------------
    def _node_config(self, node_id: str) -> dict[str, Any]:
        path = self._credentials_dir / f"{node_id}.json"
        if not path.exists():
            raise SimulatorError(f"{path}: missing (run `wsnav broker credentials` for this site)")
        try:
            load_credentials(path)  # the host's full pydantic check first, as before a deploy
            raw = json.loads(path.read_text())
        except (CredentialsError, ValueError, OSError) as exc:
            raise SimulatorError(str(exc)) from None
        if raw.get("role") != "node" or raw.get("node") != node_id:
            raise SimulatorError(f"{path}: not the config of node {node_id}")
        if raw.get("site") != self.spec.name:
            raise SimulatorError(f"{path}: site {raw.get('site')!r} is not {self.spec.name!r}")
        raw["broker"] = {"host": self._broker[0], "port": self._broker[1]}
        try:
            return parse_node_config(raw)  # then the firmware's own parser, as the board does at boot
        except ConfigError as exc:
            raise SimulatorError(f"{path}: {exc}") from None

    def start(self) -> None:
        """Load every node's config, connect the world publisher, power the nodes on (they connect in waves)."""
        ids = [n.id for n in self.spec.nodes]
        if self._only is not None:
            unknown = sorted(set(self._only) - set(ids))
            if unknown:
                raise SimulatorError(f"unknown nodes {unknown} (site {self.spec.name})")
            ids = [i for i in ids if i in self._only]
        _raise_open_files_limit(3 * len(ids) + 256)
        configs = {i: self._node_config(i) for i in ids}
        if self._world_bus is None:
            self._own_world_bus = self._operator_bus()
            self._world_bus = self._own_world_bus
        self._t0 = self.clock.now()
        self._now = self._t0
        for node_id, cfg in configs.items():
            rng = random.Random(f"{self.seed}/node/{node_id}")
            sensor_rng = random.Random(f"{self.seed}/sensor/{node_id}")
            sensor = SimulatedSensor(cfg, self.world, self._settings, sensor_rng)
            node = EmulatedNode(
                cfg, sensor, self.links, self._broker, rng, self._sample_ms, self._sent, self._node_event
            )
            self.nodes[node_id] = node
            node.boot(self._now)
        while self._timeline and self._timeline[0].t <= 0 and self._timeline[0].kind in ("block", "clear"):
            self._apply(self._timeline.popleft())
        self._publish_world()  # always: it replaces whatever world an earlier run left retained

    def _operator_bus(self) -> MqttBus:
        path = self._credentials_dir / f"{OPERATOR}.json"
        try:
            creds = load_credentials(path)
        except CredentialsError as exc:
            raise SimulatorError(str(exc)) from None
        try:
            return connect_with_credentials(
                self._broker[0],
                self._broker[1],
                tool_login(creds, "zone-sim"),  # beside the console and `wsnav watch` on Mosquitto
                clock=self.clock,
                timeout_s=OPERATOR_CONNECT_TIMEOUT_S,
                copies=True,
            )
        except BusError as exc:
            raise SimulatorError(str(exc)) from None

    # -- time ----------------------------------------------------------------------------------------------
    @property
    def elapsed(self) -> float:
        """Seconds of clock time since start (scenario times count from here)."""
        return 0.0 if self._t0 is None else self._now - self._t0

    def step(self, now: float | None = None, io_timeout_s: float = 0.0) -> None:
        """Advance the world, scenario and nodes to clock time `now` (default: the clock's), and do the I/O.

        Waits on the sockets for at most `io_timeout_s` real seconds (0: never blocks).
        """
        if self._t0 is None:
            raise RuntimeError("start() the simulator first")
        now = self.clock.now() if now is None else now
        if now < self._now:
            now = self._now
        while self._timeline and self._t0 + self._timeline[0].t <= now:
            event = self._timeline.popleft()
            self._advance_nodes(max(self._now, self._t0 + event.t))  # the nodes live up to the event first
            self._apply(event)
        self._advance_nodes(now)
        self._connect_some(now)
        if self._world_dirty:
            self._publish_world()
        self.links.pump(io_timeout_s)

    def _advance_nodes(self, now: float) -> None:
        self._now = now
        for node in self.nodes.values():
            node.advance(now)

    def _connect_some(self, now: float) -> None:
        """Start the due connect attempts, at most MAX_CONNECTING in flight. Runs every step: the attempts in
        flight are counted only when some are due (11 % of the simulator's loop with 1000 nodes up otherwise)."""
        due = [n for n in self.nodes.values() if n.wants_connect]
        if not due:
            return
        budget = MAX_CONNECTING - sum(1 for n in self.nodes.values() if n.connecting)
        for node in due[: max(budget, 0)]:
            node.connect(now)

    def run(self, duration_s: float | None = None, step_s: float = 0.01) -> None:
        """Real time (or a SimClock advanced by its own `sleep`): step until `duration_s` of clock time passed.

        Between steps it waits on the sockets, so messages move as soon as they arrive.
        """
        if self._t0 is None:
            self.start()
        end = None if duration_s is None else self._now + duration_s
        while end is None or self._now < end:
            before = self.clock.now()
            self.step(before, io_timeout_s=step_s)
            waited = self.clock.now() - before
            if waited < step_s:
                self.clock.sleep(step_s - waited)
        self.step(self.clock.now())

    # -- what happens --------------------------------------------------------------------------------------
    def _apply(self, event: Event) -> None:
        t = self._t0 + event.t if self._t0 is not None else event.t
        why = f" ({event.why})" if event.why else ""
        if event.kind == "block":
            self._place(event.target, t, why)
        elif event.kind == "clear":
            self._remove(event.target, t, why)
        elif event.kind == "reboot":
            self.reboot_node(event.target)
        else:
            self.kill_node(event.target, hang=event.kind == "hang")

    def _place(self, zone: str, t: float, why: str = "") -> None:
        if self.world.place(zone, t):
            self._world_dirty = True
            self._note(f"t={t - self._start():.2f} s: obstacle placed in {zone}{why}")

    def _remove(self, zone: str, t: float, why: str = "") -> None:
        if self.world.remove(zone, t):
            self._world_dirty = True
            self._note(f"t={t - self._start():.2f} s: obstacle removed from {zone}{why}")

    def _start(self) -> float:
        return self._t0 if self._t0 is not None else 0.0

    def _at(self, t: float | None) -> float:
        """A requested change time: the clock's now by default, never before the last step."""
        return max(self.clock.now() if t is None else t, self._now)

    def block(self, zone: str, t: float | None = None) -> None:
        """Put an obstacle in `zone` now (or at clock time `t`, not before the last step). Raises WorldError."""
        self._place(zone, self._at(t))
        if self._world_dirty and self._t0 is not None:
            self._publish_world()

    def clear(self, zone: str, t: float | None = None) -> None:
        self._remove(zone, self._at(t))
        if self._world_dirty and self._t0 is not None:
            self._publish_world()

    def _node(self, node_id: str) -> EmulatedNode:
        try:
            return self.nodes[node_id]
        except KeyError:
            raise WorldError(f"unknown node {node_id!r}") from None

    def kill_node(self, node_id: str, hang: bool = False) -> None:
        """Power cut: no DISCONNECT. `hang`: the socket stays open and silent until the broker drops it."""
        self._node(node_id).kill(hang=hang)
        self._note(f"t={self.elapsed:.2f} s: node {node_id} {'hung' if hang else 'killed'}")

    def reboot_node(self, node_id: str) -> None:
        """Power cycle: a fresh boot (new seq base) that reconnects and says `online` again."""
        self._node(node_id).reboot(self._now)
        self._note(f"t={self.elapsed:.2f} s: node {node_id} rebooted")

    def _publish_world(self) -> None:
        self._world_dirty = False
        bus = self._world_bus
        if bus is None:
            return
        t = self._now - self._start()
        bus.publish(topics.sim_world(self.spec.name), self.world.message(t).to_payload(), qos=1, retain=True)
        self.stats.world_updates += 1

    def _sent(self, sent: Sent) -> None:
        self.stats.published += 1
        if self._on_sent is not None:
            self._on_sent(sent)

    def _node_event(self, node_id: str, why: str) -> None:
        self.stats.link_failures += 1
        self._note(f"t={self.elapsed:.2f} s: node {node_id}: {why}")

    def _note(self, line: str) -> None:
        self.stats.events.append(line)
        self._log(line)

    # -- status and shutdown -------------------------------------------------------------------------------
    def wait_online(self, count: int | None = None, timeout_s: float = 300.0) -> float:
        """Step until `count` nodes (all by default) hold a connection, without moving the clock; the real
        seconds it took. SimulatorError after `timeout_s` real seconds."""
        want = len(self.nodes) if count is None else count
        started = time.monotonic()
        while self.online_count < want:
            self.step(io_timeout_s=0.01)
            if time.monotonic() - started > timeout_s:
                raise SimulatorError(f"only {self.online_count} nodes online after {timeout_s:.0f} s")
        return time.monotonic() - started

    @property
    def online_count(self) -> int:
        return sum(1 for n in self.nodes.values() if n.online)

    @property
    def alive_ids(self) -> list[str]:
        return [i for i, n in self.nodes.items() if n.power is Power.ON]

    def stop(self, clear_world: bool = True) -> None:
        """Power every node off (links cut: the broker publishes their `offline`); empty the world topic."""
        for node in self.nodes.values():
            node.power_off()
        if clear_world and self._world_bus is not None and self._t0 is not None:
            for zone in self.world.blocked_zones():
                self.world.remove(zone, self._now)
            self._publish_world()
        self.links.pump(0.0)
        self.links.close()
        if self._own_world_bus is not None:
            self._own_world_bus.close()
            self._own_world_bus = None


def _raise_open_files_limit(wanted: int) -> None:
    """1000 nodes need ~1000 sockets: lift the soft limit toward the hard one when it is lower."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < wanted:
        target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
