# pyright: reportMissingImports=false, reportUnknownMemberType=false, reportAttributeAccessIssue=false
"""`wsnav ros bridge --robot`: Algorithm 3 over move_base, the ROS half (the decisions are
move_base_supervisor's, the grid is bridge_node's).

move_base's goal, status, plan and master-costmap topics; goals and cancels held until move_base listens (rospy
drops what goes to a topic nobody is connected to); the relay that serves move_base's action to scripts and keeps
their goal through re-sends; the escape out of a zone blocked around the robot; the robot's status on MQTT.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wsnav.ros_bridge.bridge_options import BridgeOptions
from wsnav.ros_bridge.move_base_supervisor import Action, Cancel, Goal, MoveBaseSupervisor, Resend
from wsnav.ros_bridge.robot_link import publish_robot_status, take_mqtt_goal
from wsnav.ros_bridge.ros_env import master_param, say
from wsnav.ros_bridge.zone_feed import ESCAPE_COST, ZoneChange, ZoneFeed
from wsnav.runtime.bus import Bus
from wsnav.schemas.ros_map import FREE
from wsnav.schemas.site import Site
from wsnav.zones.cost_values import LETHAL_OBSTACLE
from wsnav.zones.geometry import Bounds, GridFrame
from wsnav.zones.zone_rule import BlockedArea

HOLD_GOALS_S = 30.0
"""How long goals wait for move_base to listen before they are dropped (and the robot's goal cancelled)."""


class MoveBaseLink:
    """The ROS side of `--robot`: move_base's topics and action, goals held until it listens, the relay that
    keeps a script's goal through re-sends, the escape, and the robot's status on MQTT."""

    def __init__(
        self,
        site: Site,
        options: BridgeOptions,
        feed: ZoneFeed,
        bus: Bus,
        lock: threading.Lock,
        publish_changes: Callable[[list[ZoneChange], float], None],
    ) -> None:
        assert options.robot is not None
        self.site = site
        self.options = options
        self.feed = feed
        self.frame = feed.frame
        self.bus = bus
        self.lock = lock
        """The node's lock: held while the grid changes and while the supervisor decides."""
        self._publish_changes = publish_changes
        self.supervisor = MoveBaseSupervisor(options.robot, feed)
        self._walls = site.grid.data != FREE
        self._pose: tuple[float, float, float] | None = None
        self._mqtt_goals = 0
        self._outbox: list[tuple[Any, Any]] = []
        """(publisher, message) of goals and cancels not yet sent: see flush_outbox."""
        self._master_frame: GridFrame | None = None
        """move_base's global costmap's cells (from its `costmap` topic), to read its updates."""
        self._held_since: float | None = None
        """Since when the outbox has waited for move_base (monotonic seconds)."""
        self._told_unconnected = False
        self._relayed: tuple[Any, str] | None = None
        """The relay's goal in progress: (its actionlib ServerGoalHandle, the goal id it has at move_base)."""
        self._relays = 0

    def master_waits(self) -> bool:
        """Whether move_base's master costmap updates are subscribed (a re-send then waits for them)."""
        return self.master_updates.get_num_connections() > 0

    def on_zone_changes(self, changes: list[ZoneChange], now: float) -> None:
        """Called with the node's lock held, every loop turn: Algorithm 3's decisions, then what they send."""
        waits = self.master_waits()
        self.act(self.supervisor.on_zones_changed(changes, now, wait_for_master=waits, pose=self._pose))
        self.act(self.supervisor.tick(now, wait_for_master=waits))
        self.flush_outbox()

    def read_planner_frequency(self, uri: str) -> None:
        """Whether move_base replans on its own timer (planner_frequency > 0, its default 0): only where it does
        not is a zone change re-sent as a goal, which preempts whoever sent it (read again, as move_base may load
        its parameters after the bridge starts)."""
        key = f"{self.options.move_base}/planner_frequency"
        try:
            value = master_param(uri, key)
        except OSError:
            return  # the master check says so
        itself = isinstance(value, int | float) and not isinstance(value, bool) and value > 0
        if itself != self.supervisor.replans_itself:
            with self.lock:
                self.supervisor.replans_itself = itself
            say(
                f"{key} = {value}: "
                + (
                    "move_base replans by itself, zone changes re-send no goal"
                    if itself
                    else "zone changes re-send the goal"
                )
            )

    def wire(self, rospy: Any) -> None:
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
        self.master_updates = rospy.Subscriber(
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
        with self.lock:
            self.act(self.supervisor.on_goal(Goal(msg.goal_id.id, pose, pose)))

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
        with self.lock:
            self._master_frame = GridFrame(
                info.width, info.height, info.resolution, info.origin.position.x, info.origin.position.y
            )

    def _on_master_update(self, msg: Any) -> None:
        """An update of move_base's master costmap: if it shows the changes a replan waits for, re-send now."""
        with self.lock:
            waiting, master = self.supervisor.waiting, self._master_frame
            if waiting is None or master is None:
                return
            if master_shows(master, self.frame, waiting.window, self.feed.costs, msg):
                self.act(self.supervisor.master_caught_up())

    def _on_ros_status(self, msg: Any) -> None:
        with self.lock:
            self.act(self.supervisor.on_statuses([(s.goal_id.id, s.status) for s in msg.status_list]))

    def _on_ros_plan(self, msg: Any) -> None:
        xy = np.array([(p.pose.position.x, p.pose.position.y) for p in msg.poses], dtype=np.float64).reshape(
            -1, 2
        )
        with self.lock:
            self.supervisor.on_plan(xy)

    def take_mqtt_goal(self, payload: bytes) -> None:
        """A goal or cancel from `robots/<id>/goal`, turned into a move_base goal (or cancel)."""
        actions, goal = take_mqtt_goal(
            self.site, self.supervisor, payload, self._mqtt_goal_id, lambda text, warn: say(text, warn=warn)
        )
        self.act(actions)
        if goal is not None:
            self._send_goal(goal)

    def _mqtt_goal_id(self) -> str:
        self._mqtt_goals += 1
        return f"wsnav-mqtt-{self._mqtt_goals}-{time.time():.3f}"

    def act(self, actions: list[Action]) -> None:
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

    def flush_outbox(self) -> None:
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
        target = handle.get_goal().target_pose
        p = target.pose
        yaw = 2 * math.atan2(p.orientation.z, p.orientation.w)
        pose = self._in_map_frame(target.header.frame_id, (p.position.x, p.position.y, yaw))
        with self.lock:
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
            self.flush_outbox()

    def _on_relay_cancel(self, handle: Any) -> None:
        with self.lock:
            relayed = self._relayed
            if relayed is not None and relayed[0].get_goal_id().id == handle.get_goal_id().id:
                self._relayed = None
                self.act(self.supervisor.cancel("cancelled on the relay"))
                self.flush_outbox()
            handle.set_canceled(self._result_type(), "cancelled")

    def finish_relayed(self) -> None:
        """End the relay's goal as the supervisor's ends: arrived, cancelled (with the reason), or replaced by a
        goal someone else sent move_base."""
        with self.lock:
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

    def check_escape(self, now: float) -> None:
        """Drive out of a blocked area the robot stands in (MoveBaseSupervisor.on_pose): the grid sends those
        areas passable but dear until it is out, then lethal again."""
        if self._pose is None:
            return
        with self.lock:
            waits = self.master_waits()
            actions = self.supervisor.on_pose(self._pose, self._exit_of, now, wait_for_master=waits)
            changes = self.feed.set_escape(self.supervisor.escape_areas)
            self._publish_changes(changes, now)
            self.act(actions)
            self.flush_outbox()

    def _exit_of(self, areas: list[BlockedArea]) -> tuple[float, float] | None:
        assert self._pose is not None
        from wsnav.navigation.behaviors.escape import exit_beside  # loaded after the grid is out (see `run`)

        return exit_beside(self.frame, self._walls, self.feed.blocked_mask(areas), self._pose[:2])

    def publish_status(self) -> None:
        import rospy

        assert self.options.robot is not None
        try:
            t = self.tf_buffer.lookup_transform(self.options.frame_id, self.options.base_frame, rospy.Time(0))
        except Exception:  # tf2's lookup, connectivity and extrapolation errors: no pose known yet
            if self._pose is None:
                return
        else:
            tr, q = t.transform.translation, t.transform.rotation
            self._pose = (tr.x, tr.y, 2 * math.atan2(q.z, q.w))
        assert self._pose is not None
        with self.lock:
            publish_robot_status(
                self.bus, self.site, self.options.robot, self.supervisor, self._pose, time.time()
            )


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
