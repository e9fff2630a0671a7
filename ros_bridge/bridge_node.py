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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wsnav.ros_bridge.costmap_params import check_global_costmap
from wsnav.ros_bridge.move_base_supervisor import Action, Cancel, Goal, MoveBaseSupervisor, Resend
from wsnav.ros_bridge.robot_link import publish_robot_status, take_mqtt_goal
from wsnav.ros_bridge.ros_env import master_alive, master_param, master_uri, require_rospy, wait_for_master
from wsnav.ros_bridge.zone_feed import ESCAPE_COST, ZoneFeed
from wsnav.ros_bridge.zone_grid import UpdateWindow, ZoneGridCodec
from wsnav.ros_bridge.zone_source import LinkWatch, load_bridge_site, start_broker_link
from wsnav.runtime.bus import Bus
from wsnav.runtime.cli_support import CliError, refuse_bad_login
from wsnav.runtime.clock import WallClock
from wsnav.schemas import topics
from wsnav.schemas.credentials import Credentials
from wsnav.schemas.ros_map import FREE
from wsnav.schemas.site import Site
from wsnav.zones.cost_values import LETHAL_OBSTACLE
from wsnav.zones.geometry import Bounds, GridFrame
from wsnav.zones.last_known import LastKnownZones
from wsnav.zones.zone_rule import BlockedArea

log = logging.getLogger(__name__)

STATUS_PERIOD_S = 0.5
HOLD_GOALS_S = 30.0
"""How long goals wait for move_base to listen before they are dropped (and the robot's goal cancelled)."""
MASTER_CHECK_PERIOD_S = 2.0


@dataclass(frozen=True)
class BridgeOptions:
    frame_id: str
    namespace: str
    map_topic: str
    map_wait_s: float
    update_hold_s: float
    robot: str | None
    move_base: str
    plan_topic: str
    base_frame: str
    master_costmap: str = "/move_base/global_costmap/costmap"
    relay: str | None = None
    """An action name where the bridge serves MoveBaseAction and relays to move_base (`_on_relay_goal`)."""
    state_dir: Path | None = None
    """Where the last known zone states are kept across restarts (`--state-dir`), or None."""


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
        self.supervisor = MoveBaseSupervisor(options.robot, self.feed) if options.robot else None
        self._lock = threading.Lock()
        """Held while the grid changes and an update goes out, and while a new subscriber gets the grid."""
        self._pose: tuple[float, float, float] | None = None
        self._mqtt_goals = 0
        self._outbox: list[tuple[Any, Any]] = []
        """(publisher, message) of goals and cancels not yet sent: see _flush_outbox."""
        self._master_frame: GridFrame | None = None
        """move_base's global costmap's cells (from its `costmap` topic), to read its updates."""
        self._held_since: float | None = None
        """Since when the outbox has waited for move_base (monotonic seconds)."""
        self._told_unconnected = False
        self._relayed: tuple[Any, str] | None = None
        """The relay's goal in progress: (its actionlib ServerGoalHandle, the goal id it has at move_base)."""
        self._relays = 0
        for topic_filter in self.feed.subscriptions():
            bus.subscribe(topic_filter, qos=1)
        if options.robot:
            bus.subscribe(topics.robot_goal(site.name, options.robot), qos=1)
        self.updates_sent = 0
        self._walls = site.grid.data != FREE

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
        if self.supervisor is not None:
            self._wire_move_base(rospy)
            self._read_planner_frequency(uri)
        say(
            f"zone bridge for site {self.site.name}: {ns}/zone_grid ({self.frame.width}x{self.frame.height} cells, "
            f"frame {self.options.frame_id})"
            + (f", supervising {self.options.move_base} for {self.options.robot}" if self.supervisor else "")
        )
        if self.supervisor is not None:
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
                window = self.window.add([c.window for c in changes], now)
                if window is not None:
                    self.update_pub.publish(self._update_message(OccupancyGridUpdate, window))
                    self.updates_sent += 1
                if self.supervisor is not None:
                    for m in messages:
                        if m.topic == goal_topic:
                            self._mqtt_goal(m.payload)
                    waits = self._master_updates.get_num_connections() > 0
                    self._act(
                        self.supervisor.on_zones_changed(changes, now, wait_for_master=waits, pose=self._pose)
                    )
                    self._act(self.supervisor.tick(now, wait_for_master=waits))
                    self._flush_outbox()
            if self.supervisor is not None and self.options.relay:
                self._finish_relayed()
            if self.supervisor is not None and (now >= next_status or changes):
                self._publish_status()
                self._check_escape(now, OccupancyGridUpdate)
                next_status = now + STATUS_PERIOD_S
            if time.monotonic() >= next_master_check:
                next_master_check = time.monotonic() + MASTER_CHECK_PERIOD_S
                if not master_alive(uri):
                    say(f"lost the ROS master at {uri}", warn=True)
                    rospy.signal_shutdown("master lost")
                    wait_for_master(uri)
                    return True
                if self.supervisor is not None:
                    self._read_planner_frequency(uri)
        return False

    def _read_planner_frequency(self, uri: str) -> None:
        """Whether move_base replans on its own timer (planner_frequency > 0, its default 0): only where it does
        not is a zone change re-sent as a goal, which preempts whoever sent it (read again, as move_base may load
        its parameters after the bridge starts)."""
        assert self.supervisor is not None
        key = f"{self.options.move_base}/planner_frequency"
        try:
            value = master_param(uri, key)
        except OSError:
            return  # the master check says so
        itself = isinstance(value, int | float) and not isinstance(value, bool) and value > 0
        if itself != self.supervisor.replans_itself:
            with self._lock:
                self.supervisor.replans_itself = itself
            say(
                f"{key} = {value}: "
                + (
                    "move_base replans by itself, zone changes re-send no goal"
                    if itself
                    else "zone changes re-send the goal"
                )
            )

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

    # -- move_base -----------------------------------------------------------------------------------------

    def _wire_move_base(self, rospy: Any) -> None:
        import tf2_ros
        from actionlib_msgs.msg import GoalID, GoalStatusArray
        from map_msgs.msg import OccupancyGridUpdate
        from move_base_msgs.msg import MoveBaseActionGoal
        from nav_msgs.msg import OccupancyGrid, Path

        mb = self.options.move_base
        self._goal_type, self._goal_id_type = MoveBaseActionGoal, GoalID
        self.goal_pub = rospy.Publisher(f"{mb}/goal", MoveBaseActionGoal, queue_size=5)
        self.cancel_pub = rospy.Publisher(f"{mb}/cancel", GoalID, queue_size=5)
        rospy.Subscriber(f"{mb}/goal", MoveBaseActionGoal, self._on_ros_goal, queue_size=10)
        rospy.Subscriber(f"{mb}/status", GoalStatusArray, self._on_ros_status, queue_size=10)
        rospy.Subscriber(self.options.plan_topic, Path, self._on_ros_plan, queue_size=2)
        master = self.options.master_costmap
        rospy.Subscriber(master, OccupancyGrid, self._on_master_costmap, queue_size=1)
        self._master_updates = rospy.Subscriber(
            f"{master}_updates", OccupancyGridUpdate, self._on_master_update, queue_size=20
        )
        self.tf_buffer = tf2_ros.Buffer()
        self._tf_listener = tf2_ros.TransformListener(self.tf_buffer)
        if self.options.relay:
            import actionlib
            from move_base_msgs.msg import MoveBaseAction, MoveBaseResult

            self._result_type = MoveBaseResult
            self._relay = actionlib.ActionServer(
                self.options.relay,
                MoveBaseAction,
                self._on_relay_goal,
                self._on_relay_cancel,
                auto_start=False,
            )
            self._relay.start()

    def _on_ros_goal(self, msg: Any) -> None:
        p = msg.goal.target_pose.pose
        yaw = 2 * math.atan2(p.orientation.z, p.orientation.w)
        pose = self._in_map_frame(msg.goal.target_pose.header.frame_id, (p.position.x, p.position.y, yaw))
        assert self.supervisor is not None
        with self._lock:
            self._act(self.supervisor.on_goal(Goal(msg.goal_id.id, pose, pose)))

    def _in_map_frame(self, frame: str, pose: tuple[float, float, float]) -> tuple[float, float, float]:
        """A goal's pose in the site map's frame (`--frame`): move_base transforms a goal given in another frame
        (`odom`, a robot's frame), so the zone check must too. Without the transform, the pose is taken as is,
        with a warning."""
        frame = frame.lstrip("/")
        if not frame or frame == self.options.frame_id.lstrip("/"):
            return pose
        import rospy

        try:
            t = self.tf_buffer.lookup_transform(
                self.options.frame_id, frame, rospy.Time(0), rospy.Duration(1.0)
            )
        except Exception as exc:  # tf2's lookup, connectivity and extrapolation errors
            say(
                f"goal in frame {frame!r}: no transform to {self.options.frame_id!r} ({exc}); taken as is",
                warn=True,
            )
            return pose
        tr, q = t.transform.translation, t.transform.rotation
        turn = 2 * math.atan2(q.z, q.w)
        x, y, yaw = pose
        c, s = math.cos(turn), math.sin(turn)
        return (tr.x + c * x - s * y, tr.y + s * x + c * y, yaw + turn)

    def _on_master_costmap(self, msg: Any) -> None:
        info = msg.info
        with self._lock:
            self._master_frame = GridFrame(
                info.width, info.height, info.resolution, info.origin.position.x, info.origin.position.y
            )

    def _on_master_update(self, msg: Any) -> None:
        """An update of move_base's master costmap: if it shows the changes a replan waits for, re-send now."""
        assert self.supervisor is not None
        with self._lock:
            waiting, master = self.supervisor.waiting, self._master_frame
            if waiting is None or master is None:
                return
            if master_shows(master, self.frame, waiting.window, self.feed.costs, msg):
                self._act(self.supervisor.master_caught_up())

    def _on_ros_status(self, msg: Any) -> None:
        assert self.supervisor is not None
        with self._lock:
            self._act(self.supervisor.on_statuses([(s.goal_id.id, s.status) for s in msg.status_list]))

    def _on_ros_plan(self, msg: Any) -> None:
        assert self.supervisor is not None
        xy = np.array([(p.pose.position.x, p.pose.position.y) for p in msg.poses], dtype=np.float64).reshape(
            -1, 2
        )
        with self._lock:
            self.supervisor.on_plan(xy)

    def _mqtt_goal(self, payload: bytes) -> None:
        """A goal or cancel from `robots/<id>/goal`, turned into a move_base goal (or cancel)."""
        assert self.supervisor is not None
        actions, goal = take_mqtt_goal(
            self.site, self.supervisor, payload, self._mqtt_goal_id, lambda text, warn: say(text, warn=warn)
        )
        self._act(actions)
        if goal is not None:
            self._send_goal(goal)

    def _mqtt_goal_id(self) -> str:
        self._mqtt_goals += 1
        return f"wsnav-mqtt-{self._mqtt_goals}-{time.time():.3f}"

    def _act(self, actions: list[Action]) -> None:
        for action in actions:
            if isinstance(action, Cancel):
                assert action.goal_id, "an empty goal id cancels every goal in actionlib"
                say(f"cancel goal {action.goal_id}: {action.reason}")
                held = [
                    m
                    for _p, m in self._outbox
                    if getattr(m, "goal_id", None) and m.goal_id.id == action.goal_id
                ]
                if held:  # never reached move_base: forget it instead
                    self._outbox = [(p, m) for p, m in self._outbox if m not in held]
                else:
                    self._outbox.append((self.cancel_pub, self._goal_id_type(id=action.goal_id)))
            elif isinstance(action, Resend):
                say(f"replan now ({action.reason}): goal re-sent as {action.goal.goal_id}")
                self._send_goal(action.goal)

    def _send_goal(self, goal: Goal) -> None:
        import rospy

        say(f"goal {goal.goal_id} -> {self.options.move_base}: {goal.pose}")
        msg = self._goal_type()
        now = rospy.Time.now()
        msg.header.stamp = now
        msg.goal_id.id, msg.goal_id.stamp = goal.goal_id, now
        target = msg.goal.target_pose
        target.header.stamp, target.header.frame_id = now, self.options.frame_id
        x, y, yaw = goal.pose
        target.pose.position.x, target.pose.position.y = x, y
        target.pose.orientation.z, target.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        self._outbox.append((self.goal_pub, msg))

    def _flush_outbox(self) -> None:
        """Send held goals and cancels, in order, once move_base listens: rospy drops what is published to a
        topic nobody is connected to yet (move_base started later, or the connection still being made)."""
        while self._outbox:
            publisher, msg = self._outbox[0]
            ours = 1 if publisher is self.goal_pub else 0  # our own subscriber that watches move_base/goal
            if publisher.get_num_connections() <= ours:
                now = time.monotonic()
                self._held_since = self._held_since if self._held_since is not None else now
                if (
                    now - self._held_since > HOLD_GOALS_S
                ):  # a goal sent much later would start a drive nobody awaits
                    self._outbox.clear()
                    self._held_since = None
                    if self.supervisor is not None and self.supervisor.state == "navigating":
                        self.supervisor.state = "cancelled"
                        self.supervisor.reason = f"move_base did not listen within {HOLD_GOALS_S:g} s"
                    say(f"goals held for move_base dropped after {HOLD_GOALS_S:g} s", warn=True)
                    return
                if not self._told_unconnected:
                    say(
                        f"move_base is not listening on {publisher.resolved_name}: holding goals until it is",
                        warn=True,
                    )
                    self._told_unconnected = True
                return
            publisher.publish(msg)
            self._outbox.pop(0)
        self._told_unconnected = False
        self._held_since = None

    # -- the relay: move_base's action interface for scripts, kept through re-sends -------------------------

    def _on_relay_goal(self, handle: Any) -> None:
        """A script's goal on the relay: sent to move_base as the bridge's own, followed through every re-send;
        the script's goal ends as the supervisor's goal ends (`_finish_relayed`)."""
        assert self.supervisor is not None
        target = handle.get_goal().target_pose
        p = target.pose
        yaw = 2 * math.atan2(p.orientation.z, p.orientation.w)
        pose = self._in_map_frame(target.header.frame_id, (p.position.x, p.position.y, yaw))
        with self._lock:
            if self._relayed is not None:
                self._relayed[0].set_canceled(self._result_type(), "another goal was received on the relay")
                self._relayed = None
            handle.set_accepted("relayed to move_base")
            self._relays += 1
            goal = Goal(f"wsnav-relay-{self._relays}-{time.time():.3f}", pose, pose)
            say(f"relay goal -> {goal.goal_id}: {pose}")
            cancel = self.supervisor.sending(goal)
            if cancel:
                handle.set_aborted(self._result_type(), cancel[0].reason)
                return
            self._relayed = (handle, goal.goal_id)
            self._send_goal(goal)
            self._flush_outbox()

    def _on_relay_cancel(self, handle: Any) -> None:
        assert self.supervisor is not None
        with self._lock:
            relayed = self._relayed
            if relayed is not None and relayed[0].get_goal_id().id == handle.get_goal_id().id:
                self._relayed = None
                self._act(self.supervisor.cancel("cancelled on the relay"))
                self._flush_outbox()
            handle.set_canceled(self._result_type(), "cancelled")

    def _finish_relayed(self) -> None:
        """End the relay's goal as the supervisor's ends: arrived, cancelled (with the reason), or replaced by a
        goal someone else sent move_base."""
        assert self.supervisor is not None
        with self._lock:
            if self._relayed is None:
                return
            handle, goal_id = self._relayed
            current = self.supervisor.goal
            if current is None or current.goal_id.split("#wsnav")[0] != goal_id:
                handle.set_aborted(self._result_type(), "move_base was given another goal")
            elif self.supervisor.state == "arrived":
                handle.set_succeeded(self._result_type(), "arrived")
            elif self.supervisor.state == "cancelled":
                handle.set_aborted(self._result_type(), self.supervisor.reason or "cancelled")
            else:
                return
            self._relayed = None

    def _check_escape(self, now: float, update_type: Any) -> None:
        """Drive out of a blocked area the robot stands in (MoveBaseSupervisor.on_pose): the grid sends those
        areas passable but dear until it is out, then lethal again."""
        assert self.supervisor is not None
        if self._pose is None:
            return
        with self._lock:
            waits = self._master_updates.get_num_connections() > 0
            actions = self.supervisor.on_pose(self._pose, self._exit_of, now, wait_for_master=waits)
            changes = self.feed.set_escape(self.supervisor.escape_areas)
            window = self.window.add([c.window for c in changes], now)
            if window is not None:
                self.update_pub.publish(self._update_message(update_type, window))
                self.updates_sent += 1
            self._act(actions)
            self._flush_outbox()

    def _exit_of(self, areas: list[BlockedArea]) -> tuple[float, float] | None:
        assert self._pose is not None
        from wsnav.navigation.behaviors.escape import exit_beside  # loaded after the grid is out (see `run`)

        return exit_beside(self.frame, self._walls, self.feed.blocked_mask(areas), self._pose[:2])

    def _publish_status(self) -> None:
        import rospy

        assert self.supervisor is not None and self.options.robot is not None
        try:
            t = self.tf_buffer.lookup_transform(self.options.frame_id, self.options.base_frame, rospy.Time(0))
        except Exception:  # tf2's lookup, connectivity and extrapolation errors: no pose known yet
            if self._pose is None:
                return
        else:
            tr, q = t.transform.translation, t.transform.rotation
            self._pose = (tr.x, tr.y, 2 * math.atan2(q.z, q.w))
        assert self._pose is not None
        with self._lock:
            publish_robot_status(
                self.bus, self.site, self.options.robot, self.supervisor, self._pose, time.time()
            )


def say(text: str, *, warn: bool = False) -> None:
    """Log as a ROS node does: through rospy, to /rosout and the console (the node is initialised by then)."""
    import rospy

    (rospy.logwarn if warn else rospy.loginfo)(text)


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


MASTER_LETHAL = 99
"""costmap_2d publishes its costs translated: 100 lethal, 99 inscribed (the robot's centre there collides)."""


def master_shows(
    master: GridFrame, zones: GridFrame, window: Bounds, costs: NDArray[np.uint8], update: Any
) -> bool:
    """Whether an update of move_base's master costmap covers the zone-grid `window`, and (when both grids share
    their cells) shows every cell the zone layer holds lethal there as lethal or inscribed: then a plan made now
    is made over the change."""
    # by cell centres: a cell's edge may round to either side in the other grid (float32 resolution)
    row0, col0 = master.world_to_cell(*zones.cell_to_world(window.row0, window.col0))
    row1, col1 = master.world_to_cell(*zones.cell_to_world(window.row1 - 1, window.col1 - 1))
    if not (
        update.x <= col0
        and col1 < update.x + update.width
        and update.y <= row0
        and row1 < update.y + update.height
    ):
        return False
    if not same_cells(master, zones):
        return True  # other cells: covering the change is all that can be told
    data = np.asarray(update.data, dtype=np.int16).reshape(update.height, update.width)
    shown = data[
        window.row0 - update.y : window.row1 - update.y, window.col0 - update.x : window.col1 - update.x
    ]
    held = costs[window.rows, window.cols]
    escape = held == ESCAPE_COST  # sent passable for the robot to drive out: some of it must show so
    return bool(np.all(shown[held == LETHAL_OBSTACLE] >= MASTER_LETHAL)) and (
        not escape.any() or bool(np.any(shown[escape] < MASTER_LETHAL))
    )


def same_cells(a: GridFrame, b: GridFrame) -> bool:
    """The same grid of cells (the resolution as the float32 a ROS message carries it)."""
    return (
        (a.width, a.height) == (b.width, b.height)
        and np.float32(a.resolution) == np.float32(b.resolution)
        and abs(a.origin_x - b.origin_x) < 1e-6
        and abs(a.origin_y - b.origin_y) < 1e-6
    )


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
