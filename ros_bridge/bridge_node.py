# pyright: reportMissingImports=false, reportUnknownMemberType=false, reportAttributeAccessIssue=false
"""`wsnav ros bridge`: the zone layer on ROS (`zone_grid` + `zone_grid_updates`) and, with `--robot`, Algorithm 3
over move_base and the robot's status on MQTT.

One rospy node. MQTT comes in through the same validating intake the robot agent uses (ZoneFeed); each change
goes out as one OccupancyGridUpdate of the changed window. The grid topic is latched (rosbag play and relays keep
it latched too), and the latched message is the grid as it is when a subscriber connects, never an old one. rospy cannot register again with a restarted master, so when the master goes away the bridge waits for it
with backoff and then re-executes itself; the MQTT side reconnects by itself and its retained state comes back.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import math
import os
import sys
import threading
import time
from typing import Any

import numpy as np

from wsnav.ros_bridge.bridge_options import BridgeOptions
from wsnav.ros_bridge.costmap_params import check_global_costmap
from wsnav.ros_bridge.move_base_link import MoveBaseLink
from wsnav.ros_bridge.ros_env import (
    master_alive,
    master_param,
    master_uri,
    require_rospy,
    say,
    wait_for_master,
)
from wsnav.ros_bridge.zone_feed import ZoneChange, ZoneFeed
from wsnav.ros_bridge.zone_grid import UpdateWindow, ZoneGridCodec
from wsnav.ros_bridge.zone_source import LinkWatch, load_bridge_site, start_broker_link
from wsnav.runtime.bus import Bus
from wsnav.runtime.cli_support import CliError, refuse_bad_login
from wsnav.runtime.clock import WallClock
from wsnav.schemas import topics
from wsnav.schemas.credentials import Credentials
from wsnav.schemas.site import Site
from wsnav.zones.geometry import Bounds, GridFrame
from wsnav.zones.last_known import LastKnownZones

log = logging.getLogger(__name__)

STATUS_PERIOD_S = 0.5
HOLD_GOALS_S = 30.0
"""How long goals wait for move_base to listen before they are dropped (and the robot's goal cancelled)."""
MASTER_CHECK_PERIOD_S = 2.0


def bridge_command(args: argparse.Namespace) -> int:
    require_rospy()
    loaded = load_bridge_site(args.site, args.credentials)
    site, creds, codec = loaded.site, loaded.creds, loaded.codec
    if args.robot is not None and args.robot != creds.username:
        raise CliError(f"--robot {args.robot}: the credentials are robot {creds.username!r}'s")
    options = BridgeOptions(
        frame_id=args.frame,
        namespace=args.namespace.rstrip("/"),
        map_topic=args.map_topic,
        map_wait_s=args.map_wait,
        update_hold_s=args.update_hold,
        robot=args.robot,
        move_base=args.move_base.rstrip("/"),
        plan_topic=args.plan_topic,
        base_frame=args.base_frame,
        state_dir=args.state_dir,
        master_costmap=args.master_costmap,
        relay=args.relay.rstrip("/") if args.relay else None,
    )
    if options.relay and not options.robot:
        raise CliError("--relay needs --robot (the move_base it relays to)")
    uri = master_uri()
    wait_for_master(uri)
    if args.robot is not None and not args.no_costmap_check:
        check_move_base(uri, options)
    bus = start_broker_link(args.broker, creds, args.tls_ca)
    refuse_bad_login(bus, args.connect_timeout)
    node = ZoneBridgeNode(site, creds, bus, codec, options)
    try:
        restart = node.run(uri)
    finally:
        bus.close()
        if node.memory is not None:
            node.memory.flush()
    if restart:
        print(f"ROS master at {uri} is back: restarting to register again", flush=True)
        os.execv(sys.executable, [sys.executable, *sys.orig_argv[1:]])
    return 0


def check_move_base(uri: str, options: BridgeOptions) -> None:
    """Refuse, in one line, a move_base whose global costmap would not use the zone grid as it must
    (ros_bridge.costmap_params); parameters not loaded yet are only noted."""
    key = f"{options.move_base}/global_costmap"
    params = master_param(uri, key)
    if not isinstance(params, dict):
        log.warning(f"no parameters under {key} yet: move_base's costmap set-up not checked")
        return
    namespace = options.move_base.rsplit("/", 1)[0] or "/"
    check = check_global_costmap(params, f"{options.namespace}/zone_grid", namespace)
    for warning in check.warnings:
        log.warning(f"{key}: {warning}")
    if check.errors:
        raise CliError(
            f"{key}: {'; '.join(check.errors)} (docs/ros.md has a working set; --no-costmap-check)"
        )
    log.info(f"{key}: the zone layer is {check.zone_layer}, set up as it must be")


class ZoneBridgeNode:
    """The zone grid on ROS: the latched grid and its updates from the MQTT zone feed; with `--robot`, a
    MoveBaseLink beside it (move_base_link.py)."""

    def __init__(
        self, site: Site, creds: Credentials, bus: Bus, codec: ZoneGridCodec, options: BridgeOptions
    ) -> None:
        grid = site.grid
        self.site = site
        self.options = options
        self.frame = GridFrame.of_grid(grid)
        self.bus = bus
        self.codec = codec
        self.clock = WallClock()
        self.memory = (
            LastKnownZones.in_dir(options.state_dir, site.spec) if options.state_dir is not None else None
        )
        self.feed = ZoneFeed(site.spec, self.frame, self.memory, self.clock.now())
        self.window = UpdateWindow(options.update_hold_s)
        self._lock = threading.Lock()
        """Held while the grid changes and an update goes out, and while a new subscriber gets the grid."""
        self.move_base = (
            MoveBaseLink(site, options, self.feed, bus, self._lock, self.publish_changes)
            if options.robot
            else None
        )
        for topic_filter in self.feed.subscriptions():
            bus.subscribe(topic_filter, qos=1)
        if options.robot:
            bus.subscribe(topics.robot_goal(site.name, options.robot), qos=1)
        self.updates_sent = 0

    # -- ROS wiring ----------------------------------------------------------------------------------------

    def run(self, uri: str) -> bool:
        """Serve until shutdown; True if the master went away (the caller restarts to register again)."""
        import rospy
        from map_msgs.msg import OccupancyGridUpdate
        from nav_msgs.msg import OccupancyGrid

        rospy.init_node(
            "wsnav_zone_bridge" if not self.options.robot else f"wsnav_bridge_{self.options.robot}"
        )
        self._check_map(rospy, OccupancyGrid)
        ns = self.options.namespace
        # Latched, so rosbag play, relays and late subscribers get it; the latched message is one that serializes
        # the grid as it is when a subscriber connects, so it is never a stale grid (changes go as updates).
        self.grid_pub = rospy.Publisher(f"{ns}/zone_grid", OccupancyGrid, queue_size=1, latch=True)
        self.grid_pub.publish(current_grid_message(self))
        self.update_pub = rospy.Publisher(f"{ns}/zone_grid_updates", OccupancyGridUpdate, queue_size=20)
        if self.move_base is not None:
            self.move_base.wire(rospy)
            self.move_base.read_planner_frequency(uri)
        say(
            f"zone bridge for site {self.site.name}: {ns}/zone_grid ({self.frame.width}x{self.frame.height} cells, "
            f"frame {self.options.frame_id})"
            + (f", supervising {self.options.move_base} for {self.options.robot}" if self.move_base else "")
        )
        if self.move_base is not None:
            # The exit finder (navigation.behaviors.escape, with the planner and numba: about 2 s of CPU) loads
            # once the grid is out, so move_base's costmap does not wait for it.
            importlib.import_module("wsnav.navigation.behaviors.escape")
        next_status = 0.0
        next_master_check = time.monotonic() + MASTER_CHECK_PERIOD_S
        link = LinkWatch(self.site.spec.policy.stale, time.monotonic())
        while not rospy.is_shutdown():
            said = link.check(self.bus.connected, time.monotonic())
            if said is not None:
                say(said, warn=True)
            self.bus.wait(0.05)
            now = self.clock.now()
            messages = self.bus.poll()
            goal_topic = topics.robot_goal(self.site.name, self.options.robot) if self.options.robot else None
            zone_messages = [m for m in messages if m.topic != goal_topic]
            with self._lock:
                changes = self.feed.take(zone_messages, now)
                self.publish_changes(changes, now)
                if self.move_base is not None:
                    for m in messages:
                        if m.topic == goal_topic:
                            self.move_base.take_mqtt_goal(m.payload)
                    self.move_base.on_zone_changes(changes, now)
            if self.move_base is not None and self.options.relay:
                self.move_base.finish_relayed()
            if self.move_base is not None and (now >= next_status or changes):
                self.move_base.publish_status()
                self.move_base.check_escape(now)
                next_status = now + STATUS_PERIOD_S
            if time.monotonic() >= next_master_check:
                next_master_check = time.monotonic() + MASTER_CHECK_PERIOD_S
                if not master_alive(uri):
                    say(f"lost the ROS master at {uri}", warn=True)
                    rospy.signal_shutdown("master lost")
                    wait_for_master(uri)
                    return True
                if self.move_base is not None:
                    self.move_base.read_planner_frequency(uri)
        return False

    def _check_map(self, rospy: Any, occupancy_grid: Any) -> None:
        """Refuse, in one line, a site whose map is not the map the robot navigates on (if one is published)."""
        if self.options.map_wait_s <= 0:
            return
        try:
            msg = rospy.wait_for_message(
                self.options.map_topic, occupancy_grid, timeout=self.options.map_wait_s
            )
        except rospy.ROSException:
            say(
                f"no map on {self.options.map_topic} within {self.options.map_wait_s:g} s: not checked against the site's",
                warn=True,
            )
            return
        problem = map_mismatch(self.frame, msg.info)
        if problem:
            raise CliError(
                f"{self.site.path}: the site's map does not match {self.options.map_topic}: {problem}"
            )

    def publish_changes(self, changes: list[ZoneChange], now: float) -> None:
        """Send the changed windows as one OccupancyGridUpdate (held up to `update_hold_s` to merge a burst);
        called with the lock held."""
        from map_msgs.msg import OccupancyGridUpdate

        window = self.window.add([c.window for c in changes], now)
        if window is not None:
            self.update_pub.publish(self._update_message(OccupancyGridUpdate, window))
            self.updates_sent += 1

    def full_grid_message(self) -> Any:
        import rospy
        from nav_msgs.msg import OccupancyGrid

        msg = OccupancyGrid()
        msg.header.stamp = rospy.Time.now()
        msg.header.frame_id = self.options.frame_id
        info = msg.info
        info.map_load_time = msg.header.stamp
        info.resolution = self.frame.resolution
        info.width, info.height = self.frame.width, self.frame.height
        yaw = self.site.grid.origin[2]
        info.origin.position.x, info.origin.position.y = self.frame.origin_x, self.frame.origin_y
        info.origin.orientation.z, info.origin.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        msg.data = self.codec.encode(self.feed.costs).ravel().tolist()
        return msg

    def _update_message(self, update_type: Any, window: Bounds) -> Any:
        import rospy

        msg = update_type()
        msg.header.stamp = rospy.Time.now()
        msg.header.frame_id = self.options.frame_id
        msg.x, msg.y = window.col0, window.row0
        msg.height, msg.width = window.shape
        msg.data = self.codec.encode(self.feed.costs[window.rows, window.cols]).ravel().tolist()
        return msg


def current_grid_message(node: ZoneBridgeNode) -> Any:
    """An OccupancyGrid that is filled with the node's current grid each time rospy serializes it: latched, it is
    what every new subscriber gets, and it is never the grid of some earlier moment."""
    from nav_msgs.msg import OccupancyGrid

    class CurrentGrid(OccupancyGrid):
        def serialize(self, buff: Any) -> None:
            with node._lock:
                now = node.full_grid_message()
            self.header, self.info, self.data = now.header, now.info, now.data
            super().serialize(buff)

    return CurrentGrid()


def map_mismatch(frame: GridFrame, info: Any) -> str | None:
    """How a ROS map's MapMetaData differs from the site's grid, or None if it matches exactly.

    costmap_2d's StaticLayer compares size, resolution and origin with `!=` and, on any difference, resizes the
    master costmap and wipes what the static map put there (seen: a master with no walls), so nothing is
    tolerated here: not half a cell, not a rounding. The resolution travels as float32 on the wire, so it is
    compared as float32."""
    if (info.width, info.height) != (frame.width, frame.height):
        return f"size {info.width}x{info.height} cells, the site's is {frame.width}x{frame.height}"
    if np.float32(info.resolution) != np.float32(frame.resolution):
        return (
            f"resolution {np.float32(info.resolution)!s} m, the site's is {np.float32(frame.resolution)!s} m"
        )
    x, y = info.origin.position.x, info.origin.position.y
    if (x, y) != (frame.origin_x, frame.origin_y):
        return f"origin ({x!r}, {y!r}), the site's is ({frame.origin_x!r}, {frame.origin_y!r})"
    return None
