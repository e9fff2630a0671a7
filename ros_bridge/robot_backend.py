# pyright: reportMissingImports=false, reportUnknownMemberType=false, reportUnknownVariableType=false, reportUnknownArgumentType=false, reportAttributeAccessIssue=false
"""`wsnav robot --ros`: the agent's RobotBackend over a robot's ROS 1 topics, so wsnav's own navigator drives a
TurtleBot3 (or `wsnav sim --ros`) where no move_base runs.

In: `/odom` (nav_msgs/Odometry: velocity, and the pose when no map frame exists), `/scan` (sensor_msgs/LaserScan),
tf. Out: `/cmd_vel` (geometry_msgs/Twist). The pose is tf's map -> base_footprint (amcl, a SLAM node, or the
simulator's identity map -> odom). Where tf has no map frame, the pose is /odom's composed with a fixed map -> odom
(`--start`: where odometry began on the map; identity without it); if tf's map pose stops being current (more
than MAP_POSE_MAX_AGE_S old) the last map -> odom it gave is kept, so the robot dead-reckons on odometry instead of
holding a frozen pose or jumping. A robot whose odometry falls silent is not driven blind: commands become zero
until it speaks again.
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from wsnav.navigation.backend import BURGER_RADIUS_M, DriveLimits, LaserScan, Pose, Velocity
from wsnav.robot_agent.robot_session import RobotSession
from wsnav.ros_bridge.ros_env import master_uri, require_rospy, wait_for_master
from wsnav.runtime.cli_support import CliError
from wsnav.schemas.site import Site

ODOM_SILENCE_S = 0.5
"""Odometry older than this stops the robot (the TurtleBot3's own cmd_vel watchdog is of this order)."""
MAP_POSE_MAX_AGE_S = 1.0
"""tf's map pose older than this (localization stopped, its map -> odom no longer refreshed) is not used: the
robot dead-reckons on odometry from the last map -> odom instead of holding a frozen pose."""
TF_SETTLE_S = 1.0
"""After the first odometry, how long tf gets to show a map frame before the pose falls back to odometry."""


@dataclass(frozen=True)
class RosRobotTopics:
    scan: str = "/scan"
    odom: str = "/odom"
    cmd_vel: str = "/cmd_vel"
    map_frame: str = "map"
    base_frame: str = "base_footprint"


@dataclass(frozen=True)
class _Odom:
    pose: Pose
    """In the odometry frame."""
    velocity: Velocity
    received: float
    """time.monotonic() at reception."""


class RosRobotBackend:
    """A RobotBackend on ROS topics; rospy.init_node must have run in this process."""

    def __init__(
        self,
        robot_id: str,
        topics: RosRobotTopics | None = None,
        *,
        map_to_odom: Pose = (0.0, 0.0, 0.0),
        limits: DriveLimits | None = None,
        radius: float = BURGER_RADIUS_M,
        say: Any = print,
    ) -> None:
        """`map_to_odom`: where the odometry frame lies on the map while tf has no map frame; `limits` and
        `radius`: the robot's (a TurtleBot3 Burger's by default)."""
        import rospy
        import tf2_ros
        from geometry_msgs.msg import Twist
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import LaserScan as LaserScanMsg

        self._id = robot_id
        self.topics = topics or RosRobotTopics()
        self.limits = limits or DriveLimits()
        self._radius = radius
        self._say = say
        self._rospy = rospy
        self._twist = Twist
        self._lock = threading.Lock()
        """Guards the pose's bookkeeping (map -> odom, its source)."""
        self._odom: _Odom | None = None
        self._scan: LaserScan | None = None
        self._map_to_odom = map_to_odom
        self.pose_source: str | None = None
        """"tf" or "odom": where the last pose came from (a change is said in one line)."""
        self._silent = False
        self._laser_offset: dict[str, Pose] = {}
        self._tf_error: type[Exception] = tf2_ros.TransformException
        """Lookup, connectivity and extrapolation errors: the transform is not (yet) known."""
        self._tf = tf2_ros.Buffer(cache_time=rospy.Duration(10.0))
        self._tf_listener = tf2_ros.TransformListener(self._tf)
        self._cmd = rospy.Publisher(self.topics.cmd_vel, Twist, queue_size=1)
        self._subs = [
            rospy.Subscriber(self.topics.odom, Odometry, self._on_odom, queue_size=1),
            rospy.Subscriber(self.topics.scan, LaserScanMsg, self._on_scan, queue_size=1, buff_size=2**18),
        ]

    # -- RobotBackend ------------------------------------------------------------------------------------

    @property
    def robot_id(self) -> str:
        return self._id

    @property
    def radius(self) -> float:
        return self._radius

    def pose(self) -> Pose:
        with self._lock:  # the agent's loop and the scan callback both ask
            odom = self._odom
            if odom is None:
                return self._map_to_odom
            try:
                pose = self._lookup(self.topics.map_frame, self.topics.base_frame, None, MAP_POSE_MAX_AGE_S)
            except self._tf_error:
                self._set_source("odom")
                return compose(self._map_to_odom, odom.pose)
            self._set_source("tf")
            self._map_to_odom = compose(pose, invert(odom.pose))
            return pose

    def velocity(self) -> Velocity:
        odom = self._odom
        return odom.velocity if odom is not None else Velocity(0.0, 0.0)

    def scan(self) -> LaserScan | None:
        return self._scan

    def command(self, velocity: Velocity) -> None:
        if self.odometry_silent():
            self._publish(0.0, 0.0)
            return
        p = self.limits
        linear = velocity.linear if math.isfinite(velocity.linear) else 0.0
        angular = velocity.angular if math.isfinite(velocity.angular) else 0.0
        self._publish(
            min(max(linear, -p.max_linear), p.max_linear), min(max(angular, -p.max_angular), p.max_angular)
        )

    def stop(self) -> None:
        self._publish(0.0, 0.0)

    # -- for the command ---------------------------------------------------------------------------------

    def has_odometry(self) -> bool:
        return self._odom is not None

    def odometry_silent(self) -> bool:
        """True (said once per silence) when the newest odometry is older than ODOM_SILENCE_S."""
        odom = self._odom
        silent = odom is None or time.monotonic() - odom.received > ODOM_SILENCE_S
        if silent != self._silent and odom is not None:
            self._say(
                f"no odometry on {self.topics.odom} for {ODOM_SILENCE_S:g} s: the robot is stopped until it comes back"
                if silent
                else f"odometry on {self.topics.odom} is back"
            )
        self._silent = silent
        return silent

    def close(self) -> None:
        self.stop()
        for sub in self._subs:
            sub.unregister()

    # -- ROS callbacks (rospy's threads) -----------------------------------------------------------------

    def _on_odom(self, msg: Any) -> None:
        p, t = msg.pose.pose, msg.twist.twist
        pose = (p.position.x, p.position.y, yaw_of(p.orientation))
        self._odom = _Odom(pose, Velocity(t.linear.x, t.angular.z), time.monotonic())

    def _on_scan(self, msg: Any) -> None:
        if self._odom is None:
            return
        sensor = self._sensor_pose(msg.header.frame_id, msg.header.stamp)
        ranges = np.asarray(msg.ranges, dtype=np.float32)
        if not (math.isfinite(msg.angle_min) and math.isfinite(msg.angle_increment) and len(ranges)):
            return
        self._scan = LaserScan(
            stamp=msg.header.stamp.to_sec(),
            pose=sensor,
            angle_min=float(msg.angle_min),
            angle_increment=float(msg.angle_increment),
            range_min=float(msg.range_min),
            range_max=float(msg.range_max),
            ranges=ranges,
        )

    # -- tf ----------------------------------------------------------------------------------------------

    def _sensor_pose(self, laser_frame: str, stamp: Any) -> Pose:
        """The lidar's pose on the map when the sweep was taken: tf at the sweep's stamp if it has it, else the
        robot's pose now composed with the base -> laser offset (the sweep is at most one odometry period old)."""
        laser_frame = laser_frame.lstrip("/") or self.topics.base_frame
        try:
            return self._lookup(self.topics.map_frame, laser_frame, stamp)
        except self._tf_error:
            pass
        return compose(self.pose(), self._offset(laser_frame))

    def _offset(self, laser_frame: str) -> Pose:
        """base_frame -> laser_frame (static on a TurtleBot3); identity until tf has it."""
        if laser_frame == self.topics.base_frame:
            return (0.0, 0.0, 0.0)
        known = self._laser_offset.get(laser_frame)
        if known is not None:
            return known
        try:
            offset = self._lookup(self.topics.base_frame, laser_frame, None)
        except self._tf_error:
            return (0.0, 0.0, 0.0)
        self._laser_offset[laser_frame] = offset
        return offset

    def _lookup(self, target: str, source: str, stamp: Any, max_age_s: float | None = None) -> Pose:
        """`target` -> `source` at `stamp` (None: the newest tf has; older than `max_age_s` counts as missing)."""
        rospy = self._rospy
        t = self._tf.lookup_transform(target, source, stamp if stamp is not None else rospy.Time(0))
        if max_age_s is not None and (rospy.Time.now() - t.header.stamp).to_sec() > max_age_s:
            raise self._tf_error(f"{target} -> {source} is {max_age_s:g} s old")
        tr = t.transform.translation
        return (tr.x, tr.y, yaw_of(t.transform.rotation))

    def _set_source(self, source: str) -> None:
        if source == self.pose_source:
            return
        if source == "tf":
            self._say(f"pose from tf {self.topics.map_frame} -> {self.topics.base_frame}")
        else:
            x, y, yaw = self._map_to_odom
            self._say(
                f"no current {self.topics.map_frame} -> {self.topics.base_frame} on tf: pose from {self.topics.odom} with "
                f"{self.topics.map_frame} -> odom at [{x:.2f}, {y:.2f}, {yaw:.2f}]"
            )
        self.pose_source = source

    def _publish(self, linear: float, angular: float) -> None:
        msg = self._twist()
        msg.linear.x, msg.angular.z = float(linear), float(angular)
        self._cmd.publish(msg)


def yaw_of(q: Any) -> float:
    """Yaw of a quaternion (a planar robot: roll and pitch ignored)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def compose(a: Pose, b: Pose) -> Pose:
    """Pose b given in frame a, expressed in a's parent frame."""
    ax, ay, ath = a
    bx, by, bth = b
    c, s = math.cos(ath), math.sin(ath)
    return (ax + c * bx - s * by, ay + s * bx + c * by, math.atan2(math.sin(ath + bth), math.cos(ath + bth)))


def invert(a: Pose) -> Pose:
    x, y, th = a
    c, s = math.cos(th), math.sin(th)
    return (-(c * x + s * y), s * x - c * y, -th)


def ros_session(args: argparse.Namespace, site: Site, robot_id: str, start: Pose | None) -> RobotSession:
    """`wsnav robot --ros`: wait for the master, become a node, wait for the robot's odometry; a RobotSession."""
    require_rospy()
    import rospy

    if not (math.isfinite(args.ros_timeout) and args.ros_timeout > 0):
        raise CliError(f"--ros-timeout {args.ros_timeout:g}: expected a positive number of seconds")
    uri = master_uri()
    wait_for_master(uri)
    rospy.init_node(f"wsnav_robot_{robot_id}", disable_signals=True)
    topics = RosRobotTopics(
        args.scan_topic, args.odom_topic, args.cmd_vel_topic, args.map_frame, args.base_frame
    )
    backend = RosRobotBackend(robot_id, topics, map_to_odom=start or (0.0, 0.0, 0.0))
    deadline = time.monotonic() + args.ros_timeout
    while not backend.has_odometry():
        if time.monotonic() > deadline or rospy.is_shutdown():
            backend.close()
            rospy.signal_shutdown("no odometry")
            raise CliError(
                f"no odometry on {topics.odom} within {args.ros_timeout:g} s: is the robot's driver "
                "(or `wsnav sim --ros`) running on this master?"
            )
        time.sleep(0.05)
    time.sleep(TF_SETTLE_S)  # let tf's buffer fill, so the first pose says map if there is one
    backend.pose()

    def tick(now: float) -> float:
        backend.odometry_silent()
        return now + 0.1

    def close() -> None:
        backend.close()
        time.sleep(0.2)  # the last zero velocity leaves before the node goes (the base's watchdog: backstop)
        rospy.signal_shutdown("wsnav robot done")

    return RobotSession(backend, tick, f"ROS robot on {uri} ({topics.cmd_vel})", close=close)
