"""`wsnav ros2 bridge`: the ROS 1 bridge's zone grid (same MQTT intake, same values) as ROS 2 topics on DDS.

The grid is written from the site before the broker answers (every zone as the site's policy reads a zone with no
word yet), so a Nav2 costmap waiting for its second static map does not hold its start on MQTT; then it is written
again, whole, on every change. Broker outages are ridden out and said once each way.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import signal
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from wsnav.ros2_bridge.discovery import NODE_NAME, Discovery, cyclone_config, discovery_from_env
from wsnav.ros_bridge.zone_feed import ZoneFeed
from wsnav.ros_bridge.zone_source import LinkWatch, load_bridge_site, start_broker_link
from wsnav.runtime.bus import Bus
from wsnav.runtime.cli_support import CliError, refuse_bad_login
from wsnav.runtime.clock import WallClock
from wsnav.schemas.site import Site
from wsnav.zones.geometry import GridFrame
from wsnav.zones.last_known import LastKnownZones

if TYPE_CHECKING:
    from wsnav.ros2_bridge.nav2_robot import Nav2Robot
    from wsnav.ros2_bridge.writer import ZoneGridWriter

log = logging.getLogger(__name__)

MAX_DOMAIN_ID = 232
"""DDS's largest domain id with the standard port mapping (ROS 2 recommends 0-101 on Linux)."""
RETRY_WRITE_S = 1.0
DISTRO_LAYOUT = {"humble": "humble", "iron": "jazzy", "jazzy": "jazzy", "kilted": "jazzy", "rolling": "jazzy"}
"""$ROS_DISTRO -> whose ros_discovery_info layout to write (rmw_dds_common's Gid shrank to 16 bytes in Iron)."""
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class OutageWatch(LinkWatch):
    """The ROS 1 bridge's link watch, saying an outage once (not again every minute): logs go to a file here."""

    REPEAT_S = float("inf")


@dataclass(frozen=True)
class Ros2Options:
    namespace: str
    frame_id: str
    domain: int
    discovery: Discovery
    distro: str


def ros2_options(args: argparse.Namespace) -> Ros2Options:
    """The ROS 2 arguments checked, each problem one line: a name ROS 2 would refuse never reaches the wire."""
    namespace = args.namespace.strip()
    namespace = ("/" + namespace.strip("/")) if namespace.strip("/") else ""
    if namespace and not all(_TOKEN.fullmatch(t) for t in namespace[1:].split("/")):
        raise CliError(
            f"--namespace {args.namespace!r}: not a ROS 2 namespace (tokens of letters, digits and _, "
            "not starting with a digit, separated by single '/')"
        )
    frame = args.frame
    if not frame or frame.startswith("/") or any(c.isspace() for c in frame):
        raise CliError(f"--frame {frame!r}: ROS 2 frame ids are not empty and start without '/' (e.g. map)")
    domain = args.domain
    if domain is None:
        env = os.environ.get("ROS_DOMAIN_ID", "").strip()
        if not env:
            domain = 0
        elif env.isdigit():
            domain = int(env)
        else:
            raise CliError(f"ROS_DOMAIN_ID={env!r}: not a domain id (0-{MAX_DOMAIN_ID})")
    if not 0 <= domain <= MAX_DOMAIN_ID:
        raise CliError(f"--domain {domain}: a ROS 2 domain id is 0-{MAX_DOMAIN_ID}")
    distro = getattr(args, "ros_distro", None)
    if distro is None:
        env_distro = os.environ.get("ROS_DISTRO", "").strip().lower()
        distro = DISTRO_LAYOUT.get(env_distro, "humble") if env_distro else "humble"
        if env_distro and env_distro not in DISTRO_LAYOUT:
            raise CliError(
                f"ROS_DISTRO={env_distro!r}: not one the bridge knows ({', '.join(DISTRO_LAYOUT)}); "
                "give --ros-distro humble or jazzy"
            )
    return Ros2Options(namespace, frame, domain, discovery_from_env(), distro)


def check_robot_arguments(args: argparse.Namespace, username: str) -> None:
    """`--robot` and the Nav2 names, each problem one line."""
    if args.robot != username:
        raise CliError(f"--robot {args.robot}: the credentials are robot {username!r}'s")
    for name, value in (("--nav2-action", args.nav2_action), ("--pose-topic", args.pose_topic),
                        ("--plan-topic", args.plan_topic)):  # fmt: skip
        if not (value.startswith("/") and all(_TOKEN.fullmatch(t) for t in value[1:].split("/"))):
            raise CliError(f"{name} {value!r}: not an absolute ROS 2 name (e.g. /navigate_to_pose)")


def require_cyclonedds() -> None:
    """Fail with one line (not an ImportError traceback) when the ros2 extra is not installed."""
    try:
        import cyclonedds.domain  # noqa: F401  # pyright: ignore[reportUnusedImport]
    except ImportError as exc:
        raise CliError(
            f"Cyclone DDS's Python package is not installed ({exc}): pip install 'wsnav[ros2]' "
            "(or rerun `make .venv/.installed-stamp`)"
        ) from None


def bridge_command(args: argparse.Namespace) -> int:
    options = ros2_options(args)
    loaded = load_bridge_site(args.site, args.credentials)
    if args.robot is not None:
        check_robot_arguments(args, loaded.creds.username)
    require_cyclonedds()
    from wsnav.ros2_bridge.writer import Ros2Names, ZoneGridWriter

    site = loaded.site
    frame = GridFrame.of_grid(site.grid)
    names = Ros2Names(options.namespace)
    config = cyclone_config(options.discovery, os.environ.get("CYCLONEDDS_URI", ""), os.getpid())
    writer = ZoneGridWriter(
        options.domain,
        names,
        options.frame_id,
        frame,
        site.grid.origin[2],
        loaded.codec,
        config,
        options.distro,
    )
    clock = WallClock()
    memory = LastKnownZones.in_dir(args.state_dir, site.spec) if args.state_dir is not None else None
    feed = ZoneFeed(site.spec, frame, memory, clock.now())
    feed.take([], clock.now())
    writer.write_filter_info()
    writer.write_grid(feed)
    log.info(
        "zone bridge for site %s on ROS 2 domain %d (%s, node /%s as %s sees it): %s (%dx%d cells, frame %s), %s",
        site.name,
        options.domain,
        options.discovery.describe(),
        NODE_NAME,
        options.distro,
        names.grid,
        frame.width,
        frame.height,
        options.frame_id,
        names.filter_info,
    )
    bus = start_broker_link(args.broker, loaded.creds, args.tls_ca)
    for topic_filter in feed.subscriptions():
        bus.subscribe(topic_filter, qos=1)
    robot = None
    if args.robot is not None:
        robot = nav2_robot(args, site, feed, bus, writer, options.frame_id)
        bus.subscribe(robot.goal_topic, qos=1)
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda _n, _f: stop.set())
    try:
        refuse_bad_login(bus, args.connect_timeout)
        serve(site, feed, writer, bus, clock, stop, robot)
    finally:
        signal.signal(signal.SIGTERM, previous)
        bus.close()
        if memory is not None:
            memory.flush()
    return 0


def nav2_robot(
    args: argparse.Namespace, site: Site, feed: ZoneFeed, bus: Bus, writer: ZoneGridWriter, frame_id: str
) -> Nav2Robot:
    """`--robot`: the Nav2 supervisor on the bridge's participant (its code, and the exit finder's numba, load
    only here, once the grid is out)."""
    import importlib

    from wsnav.ros2_bridge.nav2_client import Nav2Client, Nav2Names
    from wsnav.ros2_bridge.nav2_robot import Nav2Robot
    from wsnav.ros2_bridge.nav2_supervisor import Nav2Supervisor

    client = Nav2Client(
        writer.participant, Nav2Names(args.nav2_action, args.pose_topic, args.plan_topic), frame_id
    )
    supervisor = Nav2Supervisor(args.robot, feed, replans_itself=not args.nav2_resend)
    importlib.import_module("wsnav.navigation.behaviors.escape")
    log.info(
        "supervising %s's Nav2 (%s, pose from %s): zone changes %s",
        args.robot,
        args.nav2_action,
        args.pose_topic,
        "re-send the goal"
        if args.nav2_resend
        else "re-send no goal (Nav2's behaviour tree replans by itself)",
    )
    return Nav2Robot(site, feed, bus, args.robot, client, supervisor)


def serve(
    site: Site,
    feed: ZoneFeed,
    writer: ZoneGridWriter,
    bus: Bus,
    clock: WallClock,
    stop: threading.Event,
    robot: Nav2Robot | None = None,
) -> None:
    """Until SIGTERM: MQTT messages into the feed, the whole grid out on each change (again after a failed write);
    with a robot, its Nav2 supervised, the grid written before the goals it decided go out."""
    from cyclonedds.core import DDSException

    link = OutageWatch(site.spec.policy.stale, time.monotonic())
    pending = False
    next_try = 0.0
    failed_writes = 0
    while not stop.is_set():
        said = link.check(bus.connected, time.monotonic())
        if said is not None:
            (log.info if said.endswith("zone states are live") else log.warning)(said)
        bus.wait(0.05)
        messages = bus.poll()
        goal_topic = robot.goal_topic if robot is not None else None
        now = clock.now()
        changes = feed.take([m for m in messages if m.topic != goal_topic], now)
        pending |= bool(changes)
        if robot is not None:
            pending |= robot.step([m for m in messages if m.topic == goal_topic], changes, now)
        if pending and time.monotonic() >= next_try:
            try:
                writer.write_grid(feed)
            except (
                DDSException
            ) as exc:  # a reliable reader held the write up: the next try sends the newer grid
                failed_writes += 1
                next_try = time.monotonic() + RETRY_WRITE_S
                if failed_writes == 1:
                    log.warning("zone grid not written (%s): trying again every %g s", exc, RETRY_WRITE_S)
            else:
                pending = False
                if failed_writes:
                    log.warning("zone grid written again after %d failed tries", failed_writes)
                    failed_writes = 0
                log.debug("zone grid written")
        if robot is not None:
            robot.flush(now)
