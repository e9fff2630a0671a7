"""`wsnav robot`: the robot agent against a broker, in real time, on a simulated TurtleBot3 (`--sim`) or on a robot
backend another component adds to the command (`--ros`, from ros_bridge: this module never imports ROS).

Kept apart from robot_agent.cli so that other wsnav commands start without loading the agent's dependencies.
Prints one line per change of state (and of blocked zones); with `--exit-on-arrival` it exits 0 when the goal
is reached and 1 when it is cancelled. Ctrl-C or SIGTERM stop the robot and disconnect cleanly.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
from types import FrameType

from wsnav.navigation.backend import Pose
from wsnav.navigation.planning.offline_plan import parse_point
from wsnav.robot_agent.agent import RobotAgent
from wsnav.robot_agent.agent_config import AgentConfig, AgentConfigError, load_agent_config
from wsnav.robot_agent.robot_session import BackendFactory, RobotSession
from wsnav.robot_agent.sim.turtlebot3 import SimTurtleBot3
from wsnav.robot_agent.sim.world_grid import SimWorldGrid
from wsnav.runtime.cli_support import CliError, read_robot_credentials, refuse_bad_login
from wsnav.runtime.clock import WallClock
from wsnav.runtime.mqtt_bus import BusError, connect_with_credentials
from wsnav.schemas.credentials import Credentials
from wsnav.schemas.messages import RobotStatus
from wsnav.schemas.site import Site, SiteError, load_site
from wsnav.zones.last_known import LastKnownZones

SIM_DT_S = 0.02
"""The simulated robot is advanced at 50 Hz of real time."""


def robot_command(args: argparse.Namespace) -> int:
    factory: BackendFactory | None = getattr(args, "backend", None)
    if factory is not None and args.sim:
        raise CliError("--sim and --ros are two different robots: pass one of them")
    if factory is None and not args.sim:
        raise CliError(
            "pass --sim (a simulated TurtleBot3) or --ros (a robot on ROS: /scan, /odom, tf, /cmd_vel)"
        )
    try:
        site = load_site(args.site)
    except SiteError as exc:
        raise CliError(str(exc)) from None
    try:
        config = load_agent_config(args.config)
    except AgentConfigError as exc:
        raise CliError(str(exc)) from None
    creds = read_robot_credentials(args.credentials, site)
    if args.sim and args.start is None:
        raise CliError("--sim needs --start: where the simulated robot stands")
    start = parse_point(site, args.start, "--start") if args.start is not None else None
    goal = parse_point(site, args.goal, "--goal") if args.goal is not None else None
    if args.exit_on_arrival and goal is None:
        raise CliError("--exit-on-arrival needs --goal")
    if not (math.isfinite(args.connect_timeout) and args.connect_timeout > 0):
        raise CliError(f"--connect-timeout {args.connect_timeout:g}: expected a positive number of seconds")

    session = (
        factory(args, site, creds.username, start) if factory is not None else sim_session(site, creds, start)
    )
    try:
        return _drive(args, site, config, creds, session, goal)
    finally:
        session.close()


def sim_session(site: Site, creds: Credentials, start: Pose | None) -> RobotSession:
    """The simulated TurtleBot3, stepped by the loop in real time; the zone simulator's obstacles reach it."""
    assert start is not None
    world = SimWorldGrid(site.grid)
    robot = SimTurtleBot3(creds.username, world, start)
    clock = WallClock()
    last = [clock.now()]

    def tick(now: float) -> float:
        robot.step(min(now - last[0], 0.1), now)
        last[0] = now
        return now + SIM_DT_S

    return RobotSession(robot, tick, "a simulated TurtleBot3", sim_world=world, close=robot.stop)


def _drive(
    args: argparse.Namespace,
    site: Site,
    config: AgentConfig,
    creds: Credentials,
    session: RobotSession,
    goal: Pose | None,
) -> int:
    """Connect to the broker and run the agent on `session`'s robot until stopped (or arrived)."""
    clock = WallClock()
    host, port = args.broker
    memory = LastKnownZones.in_dir(args.state_dir, site.spec) if args.state_dir is not None else None
    try:
        bus = connect_with_credentials(
            host,
            port,
            creds,
            clock=clock,
            timeout_s=args.connect_timeout,
            tls_ca=args.tls_ca,
            wait=memory is None,
        )
    except BusError as exc:
        raise CliError(str(exc)) from None
    if memory is not None:  # it has the last known states to drive on: it rides out a broker that is down
        refuse_bad_login(bus, args.connect_timeout)
        if not bus.connected:
            print(
                f"MQTT broker {bus.address} unreachable: starting from the last known zone states in "
                f"{memory.path} (stale policy {site.spec.policy.stale}); connecting in the background",
                flush=True,
            )
    robot = session.robot
    printer = StatusPrinter(origin=clock.now())
    agent = RobotAgent(
        site,
        config,
        robot,
        bus,
        clock,
        creds.username,
        sim_world=session.sim_world,
        on_status=printer,
        zone_memory=memory,
    )
    stop = threading.Event()

    def world_tick(now: float) -> float:
        next_due = session.tick(now)
        if args.exit_on_arrival and agent.navigator.state in ("arrived", "cancelled"):
            stop.set()
        return next_due

    def on_signal(_sig: int, _frame: FrameType | None) -> None:
        stop.set()

    previous = signal.signal(signal.SIGTERM, on_signal)
    print(
        f"robot {creds.username} on {site.name} (config {config.name}) at {host}:{port}, {session.describe}"
        + (f", start {args.start}" if args.start is not None else "")
        + (f", goal {args.goal}" if goal is not None else ""),
        flush=True,
    )
    try:
        if goal is not None:
            label = args.goal if args.goal in site.spec.points else goal
            agent.set_goal(goal, label, clock.now())
        agent.run(stop, world_tick)
    except KeyboardInterrupt:
        robot.stop()
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
        robot.stop()
        bus.close()
        if memory is not None:
            memory.flush()
    state = agent.navigator.state
    return 0 if state == "arrived" or not args.exit_on_arrival else 1


class StatusPrinter:
    """One line per change of state, reason or blocked zones (not per replan: stock configs replan at 5 Hz)."""

    def __init__(self, origin: float = 0.0) -> None:
        """`origin`: the clock time printed as t=0 (a wall clock's origin is arbitrary)."""
        self._origin = origin
        self._last: tuple[object, ...] | None = None

    def __call__(self, status: RobotStatus, changed: bool) -> None:
        key = (status.state, status.reason, tuple(status.blocked_zones), status.goal)
        if not changed or key == self._last:
            return
        self._last = key
        x, y, yaw = status.pose
        goal = status.goal if isinstance(status.goal, str) or status.goal is None else list(status.goal)
        parts = [
            f"t={(status.t or self._origin) - self._origin:.1f}",
            status.state,
            f"pose=[{x:.2f}, {y:.2f}, {yaw:.2f}]",
            f"goal={goal}",
            f"replans={status.replans}",
            f"blocked={','.join(status.blocked_zones) or '-'}",
        ]
        if status.plan_length_m is not None:
            parts.append(f"plan={status.plan_length_m:.2f}m")
        if status.reason:
            parts.append(f"reason: {status.reason}")
        print(" ".join(parts), flush=True)
        sys.stdout.flush()
