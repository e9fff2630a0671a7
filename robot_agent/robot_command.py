"""`wsnav robot`: the robot agent against a broker, on a simulated TurtleBot3 running in real time.

Kept apart from robot_agent.cli so that other wsnav commands start without loading the agent's dependencies.
Prints one line per change of state (and of blocked zones); with `--exit-on-arrival` it exits 0 when the goal
is reached and 1 when it is cancelled. Ctrl-C or SIGTERM stop the robot and disconnect cleanly.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
from pathlib import Path
from types import FrameType

from pydantic import ValidationError

from robot_agent.agent import RobotAgent
from robot_agent.agent_config import AgentConfigError, load_agent_config
from robot_agent.offline_plan import parse_point
from robot_agent.sim_turtlebot3 import SimTurtleBot3
from robot_agent.sim_world_grid import SimWorldGrid
from runtime.cli_support import CliError
from runtime.clock import WallClock
from runtime.mqtt_bus import BusError, connect_with_credentials
from schemas.credentials import Credentials
from schemas.messages import RobotStatus
from schemas.site import Site, SiteError, load_site

SIM_DT_S = 0.02
"""The simulated robot is advanced at 50 Hz of real time."""


def robot_command(args: argparse.Namespace) -> int:
    if not args.sim:
        raise CliError("only the simulated TurtleBot3 backend exists so far: pass --sim")
    try:
        site = load_site(args.site)
    except SiteError as exc:
        raise CliError(str(exc)) from None
    try:
        config = load_agent_config(args.config)
    except AgentConfigError as exc:
        raise CliError(str(exc)) from None
    creds = read_credentials(args.credentials, site)
    start = parse_point(site, args.start, "--start")
    goal = parse_point(site, args.goal, "--goal") if args.goal is not None else None
    if args.exit_on_arrival and goal is None:
        raise CliError("--exit-on-arrival needs --goal")
    if not (math.isfinite(args.connect_timeout) and args.connect_timeout > 0):
        raise CliError(f"--connect-timeout {args.connect_timeout:g}: expected a positive number of seconds")

    clock = WallClock()
    host, port = args.broker
    try:
        bus = connect_with_credentials(host, port, creds, clock=clock, timeout_s=args.connect_timeout)
    except BusError as exc:
        raise CliError(str(exc)) from None
    world = SimWorldGrid(site.grid)
    robot = SimTurtleBot3(creds.username, world, start)
    printer = StatusPrinter(origin=clock.now())
    agent = RobotAgent(site, config, robot, bus, clock, creds.username, sim_world=world, on_status=printer)
    stop = threading.Event()
    last = [clock.now()]

    def world_tick(now: float) -> float:
        robot.step(min(now - last[0], 0.1), now)
        last[0] = now
        if args.exit_on_arrival and agent.navigator.state in ("arrived", "cancelled"):
            stop.set()
        return now + SIM_DT_S

    def on_signal(_sig: int, _frame: FrameType | None) -> None:
        stop.set()

    previous = signal.signal(signal.SIGTERM, on_signal)
    print(
        f"robot {creds.username} on {site.name} (config {config.name}) at {host}:{port}, "
        f"start {args.start}" + (f", goal {args.goal}" if goal is not None else ""),
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
    state = agent.navigator.state
    return 0 if state == "arrived" or not args.exit_on_arrival else 1


def read_credentials(path: Path, site: Site) -> Credentials:
    """The robot's credentials file (from `wsnav broker credentials`), checked against the site."""
    try:
        creds = Credentials.model_validate(json.loads(path.read_text()))
    except FileNotFoundError:
        raise CliError(f"{path}: no such credentials file") from None
    except OSError as exc:
        raise CliError(f"{path}: cannot read: {exc.strerror}") from None
    except ValueError as exc:
        if isinstance(exc, ValidationError):
            err = exc.errors()[0]
            key = ".".join(str(p) for p in err["loc"]) or "(file)"
            raise CliError(f"{path}: {key}: {err['msg']}") from None
        raise CliError(f"{path}: not a JSON credentials file") from None
    if creds.role != "robot":
        raise CliError(f"{path}: these are the credentials of a {creds.role}, not of a robot")
    if creds.site != site.name:
        raise CliError(f"{path}: credentials for site {creds.site!r}, not {site.name!r}")
    robots = [r.id for r in site.spec.robots]
    if creds.username not in robots:
        raise CliError(f"{path}: robot {creds.username!r} is not in site {site.name!r} (robots: {robots})")
    return creds


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
